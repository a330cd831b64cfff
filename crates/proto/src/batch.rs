//! Transition batches: `pb::TransitionBatch` <-> core [`Batch`], validated on the way in.

use hac_core::{Batch, BatchRef, LevelDims};

use crate::{WireError, pb};

/// A batch that passed validation, with the level and weights version it was sent with.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedBatch {
    pub level: usize,
    pub weights_version: u64,
    pub batch: Batch,
}

/// What [`decode_batch_into`] reads besides the transitions themselves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BatchHeader {
    pub level: usize,
    pub weights_version: u64,
}

/// Validates `msg` against the run's level dimensions (`dims[level]`) and the batch size limit
/// and takes it apart into a [`DecodedBatch`]. The float vectors move over without a copy.
///
/// Checks, in order: the level is in range; `0 < count <= max_count`; every field has the length
/// `count` and the level's dimensions imply; every float is finite; every terminal byte is 0 or
/// 1. The first failure is returned.
pub fn decode_batch(
    msg: pb::TransitionBatch,
    dims: &[LevelDims],
    max_count: usize,
) -> Result<DecodedBatch, WireError> {
    let checked = validate(&msg, dims, max_count)?;
    Ok(DecodedBatch {
        level: checked.header.level,
        weights_version: checked.header.weights_version,
        batch: Batch {
            dims: checked.dims,
            len: checked.len,
            states: msg.states,
            actions: msg.actions,
            rewards: msg.rewards,
            next_states: msg.next_states,
            goals: msg.goals,
            terminals: msg.terminals.iter().map(|&t| f32::from(t)).collect(),
            extra_width: checked.extra_width,
            extra: msg.extra,
        },
    })
}

/// Like [`decode_batch`], but copies into `out`, reusing its allocations (no allocation once
/// `out` has grown to the largest batch seen). On error `out` is left untouched.
pub fn decode_batch_into(
    msg: &pb::TransitionBatch,
    dims: &[LevelDims],
    max_count: usize,
    out: &mut Batch,
) -> Result<BatchHeader, WireError> {
    let checked = validate(msg, dims, max_count)?;
    out.dims = checked.dims;
    out.len = checked.len;
    copy_into(&mut out.states, &msg.states);
    copy_into(&mut out.actions, &msg.actions);
    copy_into(&mut out.rewards, &msg.rewards);
    copy_into(&mut out.next_states, &msg.next_states);
    copy_into(&mut out.goals, &msg.goals);
    out.terminals.clear();
    out.terminals
        .extend(msg.terminals.iter().map(|&t| f32::from(t)));
    out.extra_width = checked.extra_width;
    copy_into(&mut out.extra, &msg.extra);
    Ok(checked.header)
}

/// Packs `batch` for sending as a batch of level `level` produced by weights `weights_version`.
///
/// # Panics
/// If `level`, `batch.len` or a dimension exceed `u32::MAX`. The receiver refuses an empty
/// batch, so callers send only batches with `len > 0`.
pub fn encode_batch(level: usize, weights_version: u64, batch: &Batch) -> pb::TransitionBatch {
    let mut msg = pb::TransitionBatch::default();
    encode_batch_into(&mut msg, level, weights_version, batch);
    msg
}

/// Like [`encode_batch`], but overwrites `out`, reusing its vectors (no allocation once `out`
/// has grown to the largest batch seen).
pub fn encode_batch_into(
    out: &mut pb::TransitionBatch,
    level: usize,
    weights_version: u64,
    batch: &Batch,
) {
    debug_assert_batch_consistent(batch);
    out.level = to_u32(level, "level");
    out.weights_version = weights_version;
    out.count = to_u32(batch.len, "batch length");
    copy_into(&mut out.states, &batch.states);
    copy_into(&mut out.actions, &batch.actions);
    copy_into(&mut out.rewards, &batch.rewards);
    copy_into(&mut out.next_states, &batch.next_states);
    copy_into(&mut out.goals, &batch.goals);
    out.terminals.clear();
    out.terminals
        .extend(batch.terminals.iter().map(|&t| u8::from(t != 0.0)));
    copy_into(&mut out.extra, &batch.extra);
}

/// Moves the vectors of an already valid batch into a message (the actor side of
/// [`IngestItem::Batch`](crate::IngestItem)).
impl From<DecodedBatch> for pb::TransitionBatch {
    fn from(decoded: DecodedBatch) -> Self {
        let batch = decoded.batch;
        debug_assert_batch_consistent(&batch);
        Self {
            level: to_u32(decoded.level, "level"),
            weights_version: decoded.weights_version,
            count: to_u32(batch.len, "batch length"),
            terminals: batch
                .terminals
                .iter()
                .map(|&t| u8::from(t != 0.0))
                .collect(),
            states: batch.states,
            actions: batch.actions,
            rewards: batch.rewards,
            next_states: batch.next_states,
            goals: batch.goals,
            extra: batch.extra,
        }
    }
}

struct Checked {
    header: BatchHeader,
    dims: LevelDims,
    len: usize,
    extra_width: usize,
}

/// The parts of a batch every check looks at, whatever its representation.
struct Fields<'a> {
    level: u32,
    count: u32,
    states: &'a [f32],
    actions: &'a [f32],
    next_states: &'a [f32],
    goals: &'a [f32],
    rewards: &'a [f32],
    terminals: usize,
    extra: &'a [f32],
}

impl Fields<'_> {
    /// Level range, count, every field's length, finite floats; the level's dimensions if all
    /// pass. `extra` must hold the same number of values for each transition; how many the
    /// level stores is for the learner to check (`hac_core::TransitionLimits`).
    fn check(&self, dims: &[LevelDims], max_count: usize) -> Result<LevelDims, WireError> {
        let level_dims =
            dims.get(self.level as usize)
                .copied()
                .ok_or(WireError::LevelOutOfRange {
                    level: self.level,
                    levels: dims.len(),
                })?;
        let count = self.count as usize;
        if count == 0 {
            return Err(WireError::zero("batch.count"));
        }
        if count > max_count {
            return Err(WireError::CountAboveLimit {
                count: self.count,
                limit: max_count,
            });
        }
        let vectors: [(&'static str, &[f32], &'static str, usize); 4] = [
            ("batch.states", self.states, "state", level_dims.state),
            ("batch.actions", self.actions, "action", level_dims.action),
            (
                "batch.next_states",
                self.next_states,
                "state",
                level_dims.state,
            ),
            ("batch.goals", self.goals, "goal", level_dims.goal),
        ];
        for &(field, values, dim_name, dim) in &vectors {
            let expected = count.saturating_mul(dim);
            if values.len() != expected {
                return Err(WireError::WrongLength {
                    field,
                    len: values.len(),
                    expected,
                    count,
                    dim_name,
                    dim,
                });
            }
        }
        for (field, len) in [
            ("batch.rewards", self.rewards.len()),
            ("batch.terminals", self.terminals),
        ] {
            if len != count {
                return Err(WireError::WrongCount { field, len, count });
            }
        }
        if !self.extra.len().is_multiple_of(count) {
            return Err(WireError::ExtraNotPerTransition {
                len: self.extra.len(),
                count,
            });
        }
        // The value scans run branch-free over the whole field so that they vectorise (an early
        // exit does not); the offending index is searched for only once a batch is known to be
        // bad.
        for &(field, values, _, _) in &vectors {
            check_finite(field, values)?;
        }
        check_finite("batch.rewards", self.rewards)?;
        check_finite("batch.extra", self.extra)?;
        Ok(level_dims)
    }
}

/// Validates a batch that did not come through [`decode_batch`] (built in this process, or read
/// in place from shared memory) exactly as [`decode_batch`] validates one from the wire: level
/// range, count, lengths, finite values, terminals 0.0 or 1.0.
pub fn check_batch(
    level: usize,
    batch: BatchRef<'_>,
    dims: &[LevelDims],
    max_count: usize,
) -> Result<(), WireError> {
    let fields = Fields {
        level: u32::try_from(level).unwrap_or(u32::MAX),
        count: u32::try_from(batch.len).unwrap_or(u32::MAX),
        states: batch.states,
        actions: batch.actions,
        next_states: batch.next_states,
        goals: batch.goals,
        rewards: batch.rewards,
        terminals: batch.terminals.len(),
        extra: batch.extra,
    };
    fields.check(dims, max_count)?;
    if let Some(index) = batch.terminals.iter().position(|&t| t != 0.0 && t != 1.0) {
        return Err(WireError::BadTerminal {
            index,
            value: batch.terminals[index],
        });
    }
    Ok(())
}

fn validate(
    msg: &pb::TransitionBatch,
    dims: &[LevelDims],
    max_count: usize,
) -> Result<Checked, WireError> {
    let fields = Fields {
        level: msg.level,
        count: msg.count,
        states: &msg.states,
        actions: &msg.actions,
        next_states: &msg.next_states,
        goals: &msg.goals,
        rewards: &msg.rewards,
        terminals: msg.terminals.len(),
        extra: &msg.extra,
    };
    let level_dims = fields.check(dims, max_count)?;
    if msg.terminals.iter().fold(0, |max, &t| max.max(t)) > 1 {
        let index = msg
            .terminals
            .iter()
            .position(|&t| t > 1)
            .unwrap_or_default();
        return Err(WireError::BadTerminal {
            index,
            value: f32::from(msg.terminals[index]),
        });
    }

    Ok(Checked {
        header: BatchHeader {
            level: msg.level as usize,
            weights_version: msg.weights_version,
        },
        dims: level_dims,
        len: msg.count as usize,
        extra_width: msg.extra.len() / (msg.count as usize),
    })
}

fn check_finite(field: &'static str, values: &[f32]) -> Result<(), WireError> {
    if values.iter().fold(true, |ok, v| ok & v.is_finite()) {
        return Ok(());
    }
    let index = values
        .iter()
        .position(|v| !v.is_finite())
        .unwrap_or_default();
    Err(WireError::NotFinite {
        field,
        index,
        value: values[index],
    })
}

fn copy_into(dst: &mut Vec<f32>, src: &[f32]) {
    dst.clear();
    dst.extend_from_slice(src);
}

fn to_u32(value: usize, what: &str) -> u32 {
    u32::try_from(value).unwrap_or_else(|_| panic!("{what} {value} does not fit the wire's u32"))
}

fn debug_assert_batch_consistent(batch: &Batch) {
    let (d, n) = (batch.dims, batch.len);
    debug_assert_eq!(batch.states.len(), d.state * n, "batch.states length");
    debug_assert_eq!(batch.actions.len(), d.action * n, "batch.actions length");
    debug_assert_eq!(batch.rewards.len(), n, "batch.rewards length");
    debug_assert_eq!(
        batch.next_states.len(),
        d.state * n,
        "batch.next_states length"
    );
    debug_assert_eq!(batch.goals.len(), d.goal * n, "batch.goals length");
    debug_assert_eq!(batch.terminals.len(), n, "batch.terminals length");
    debug_assert_eq!(
        batch.extra.len(),
        batch.extra_width * n,
        "batch.extra length"
    );
    debug_assert!(
        batch.terminals.iter().all(|&t| t == 0.0 || t == 1.0),
        "batch.terminals holds only 0.0 and 1.0"
    );
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;
    use prost::Message;

    use super::*;

    const PENDULUM: LevelDims = LevelDims {
        state: 3,
        goal: 2,
        action: 1,
    };
    const DIMS: [LevelDims; 3] = [
        PENDULUM,
        LevelDims {
            state: 3,
            goal: 2,
            action: 2,
        },
        LevelDims {
            state: 3,
            goal: 2,
            action: 2,
        },
    ];

    fn sample_batch(dims: LevelDims, len: usize) -> Batch {
        let mut batch = Batch::zeros(dims, len);
        for (i, v) in batch.states.iter_mut().enumerate() {
            *v = i as f32 * 0.5;
        }
        batch.terminals[len - 1] = 1.0;
        batch
    }

    /// A valid message of 8 transitions at level 0, for the error tests to break.
    fn valid() -> pb::TransitionBatch {
        encode_batch(0, 7, &sample_batch(PENDULUM, 8))
    }

    fn refused(msg: pb::TransitionBatch) -> WireError {
        let into = decode_batch_into(&msg, &DIMS, 64, &mut Batch::zeros(PENDULUM, 0));
        let err = decode_batch(msg, &DIMS, 64).expect_err("the batch is invalid");
        assert_eq!(
            into.expect_err("the batch is invalid").to_string(),
            err.to_string()
        );
        err
    }

    fn bits(values: &[f32]) -> Vec<u32> {
        values.iter().map(|v| v.to_bits()).collect()
    }

    fn assert_bitwise_eq(a: &Batch, b: &Batch) {
        assert_eq!((a.dims, a.len), (b.dims, b.len));
        assert_eq!(bits(&a.states), bits(&b.states));
        assert_eq!(bits(&a.actions), bits(&b.actions));
        assert_eq!(bits(&a.rewards), bits(&b.rewards));
        assert_eq!(bits(&a.next_states), bits(&b.next_states));
        assert_eq!(bits(&a.goals), bits(&b.goals));
        assert_eq!(bits(&a.terminals), bits(&b.terminals));
    }

    fn finite() -> impl Strategy<Value = f32> {
        use proptest::num::f32;
        f32::POSITIVE | f32::NEGATIVE | f32::NORMAL | f32::SUBNORMAL | f32::ZERO
    }

    fn floats(len: usize) -> impl Strategy<Value = Vec<f32>> {
        proptest::collection::vec(finite(), len)
    }

    fn arb_dims() -> impl Strategy<Value = Vec<LevelDims>> {
        proptest::collection::vec(
            (1usize..9, 1usize..9, 1usize..9).prop_map(|(state, goal, action)| LevelDims {
                state,
                goal,
                action,
            }),
            1..5,
        )
    }

    /// Run dimensions, a level, a weights version and a batch of that level's dimensions.
    fn arb_case() -> impl Strategy<Value = (Vec<LevelDims>, usize, u64, Batch)> {
        (
            arb_dims(),
            any::<prop::sample::Index>(),
            any::<u64>(),
            1usize..65,
            0usize..4,
        )
            .prop_flat_map(|(dims, level, version, len, extra_width)| {
                let level = level.index(dims.len());
                let d = dims[level];
                (
                    floats(d.state * len),
                    floats(d.action * len),
                    floats(len),
                    floats(d.state * len),
                    floats(d.goal * len),
                    proptest::collection::vec(any::<bool>(), len),
                    floats(extra_width * len),
                )
                    .prop_map(
                        move |(states, actions, rewards, next_states, goals, terminals, extra)| {
                            let batch = Batch {
                                dims: d,
                                len,
                                states,
                                actions,
                                rewards,
                                next_states,
                                goals,
                                terminals: terminals.into_iter().map(f32::from).collect(),
                                extra_width,
                                extra,
                            };
                            (dims.clone(), level, version, batch)
                        },
                    )
            })
    }

    proptest! {
        #[test]
        fn round_trip_through_prost_bytes_is_bit_exact((dims, level, version, batch) in arb_case()) {
            let bytes = encode_batch(level, version, &batch).encode_to_vec();
            let msg = pb::TransitionBatch::decode(bytes.as_slice()).expect("prost decodes its own bytes");

            let mut reused = Batch::zeros(LevelDims { state: 9, goal: 1, action: 5 }, 3);
            let header = decode_batch_into(&msg, &dims, batch.len, &mut reused).expect("valid batch");
            prop_assert_eq!(header, BatchHeader { level, weights_version: version });
            assert_bitwise_eq(&reused, &batch);

            let decoded = decode_batch(msg, &dims, batch.len).expect("valid batch");
            prop_assert_eq!((decoded.level, decoded.weights_version), (level, version));
            assert_bitwise_eq(&decoded.batch, &batch);

            let moved = pb::TransitionBatch::from(decoded);
            prop_assert_eq!(moved.encode_to_vec(), bytes);
        }

        #[test]
        fn encode_into_a_used_message_equals_a_fresh_encode(
            (_, level, version, batch) in arb_case(),
            (_, _, _, before) in arb_case(),
        ) {
            let mut msg = encode_batch(1, 1, &before);
            encode_batch_into(&mut msg, level, version, &batch);
            prop_assert_eq!(msg, encode_batch(level, version, &batch));
        }

        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..256)) {
            if let Ok(msg) = pb::TransitionBatch::decode(bytes.as_slice()) {
                let _ = decode_batch(msg, &DIMS, 64);
            }
        }
    }

    #[test]
    fn garbage_bytes_fail_prost_decode() {
        // Field 4 (states) as a length-delimited run longer than the buffer.
        assert!(pb::TransitionBatch::decode(&[0x22, 0x7f, 0x00][..]).is_err());
        // A wire type that does not exist (7).
        assert!(pb::TransitionBatch::decode(&[0x0f, 0x01][..]).is_err());
        let bytes = valid().encode_to_vec();
        assert!(pb::TransitionBatch::decode(&bytes[..bytes.len() - 1]).is_err());
        assert!(pb::IngestRequest::decode(&[0xff; 16][..]).is_err());
    }

    #[test]
    fn a_level_out_of_range_is_refused() {
        let mut msg = valid();
        msg.level = 5;
        let err = refused(msg);
        assert_eq!(err.to_string(), "batch.level 5 out of range (levels 0..3)");
    }

    #[test]
    fn an_empty_batch_is_refused() {
        let mut msg = valid();
        msg.count = 0;
        assert_eq!(refused(msg).to_string(), "batch.count is 0");
    }

    #[test]
    fn a_batch_above_the_limit_is_refused() {
        let mut msg = valid();
        msg.count = 100_000;
        let err = decode_batch(msg, &DIMS, 65_536).unwrap_err();
        assert_eq!(err.to_string(), "batch.count 100000 above the limit 65536");
    }

    #[test]
    fn a_vector_of_the_wrong_length_is_refused() {
        let mut msg = valid();
        msg.states.truncate(22);
        assert_eq!(
            refused(msg).to_string(),
            "batch.states has 22 values, expected 24 (count 8 x state 3)"
        );

        // Level 1 has 2-dimensional actions: the pendulum-sized message no longer fits.
        let mut msg = valid();
        msg.level = 1;
        assert_eq!(
            refused(msg).to_string(),
            "batch.actions has 8 values, expected 16 (count 8 x action 2)"
        );

        for (field, mutate) in [
            (
                "batch.next_states",
                (|m: &mut pb::TransitionBatch| m.next_states.push(0.0)) as fn(&mut _),
            ),
            ("batch.goals", |m| m.goals.clear()),
        ] {
            let mut msg = valid();
            mutate(&mut msg);
            let err = refused(msg);
            assert!(matches!(err, WireError::WrongLength { .. }), "{err}");
            assert!(err.to_string().starts_with(field), "{err}");
        }
    }

    #[test]
    fn per_transition_fields_of_the_wrong_length_are_refused() {
        let mut msg = valid();
        msg.rewards.pop();
        assert_eq!(
            refused(msg).to_string(),
            "batch.rewards has 7 values, expected one per transition (count 8)"
        );
        let mut msg = valid();
        msg.terminals.push(0);
        assert_eq!(
            refused(msg).to_string(),
            "batch.terminals has 9 values, expected one per transition (count 8)"
        );
    }

    #[test]
    fn every_float_field_is_checked_for_finiteness() {
        type Field = fn(&mut pb::TransitionBatch) -> &mut Vec<f32>;
        let fields: [(&str, Field); 5] = [
            ("batch.states", |m| &mut m.states),
            ("batch.actions", |m| &mut m.actions),
            ("batch.rewards", |m| &mut m.rewards),
            ("batch.next_states", |m| &mut m.next_states),
            ("batch.goals", |m| &mut m.goals),
        ];
        for (name, field) in fields {
            for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
                let mut msg = valid();
                field(&mut msg)[3] = bad;
                let err = refused(msg);
                assert_eq!(err.to_string(), format!("{name}[3] is {bad}"));
            }
        }
        let mut msg = valid();
        msg.rewards[3] = f32::NAN;
        assert_eq!(refused(msg).to_string(), "batch.rewards[3] is NaN");
    }

    #[test]
    fn a_terminal_byte_other_than_0_or_1_is_refused() {
        let mut msg = valid();
        msg.terminals[2] = 7;
        assert_eq!(
            refused(msg).to_string(),
            "batch.terminals[2] is 7, expected 0 or 1"
        );
    }

    #[test]
    fn a_refused_batch_leaves_the_target_untouched() {
        let mut out = sample_batch(PENDULUM, 4);
        let before = out.clone();
        let mut msg = valid();
        msg.goals[5] = f32::NAN;
        assert!(decode_batch_into(&msg, &DIMS, 64, &mut out).is_err());
        assert_eq!(out, before);
    }
}
