//! The packed form of ingest messages and weights snapshots, for shared memory between processes
//! on one host: a fixed header, then every field as a native-endian array at a 4-byte aligned
//! offset. The sender writes a message straight into the memory it sends; the receiver reads it
//! in place ([`unpack_ingest`] borrows every float of a batch from the bytes, no copy, no
//! allocation). Both ends run on the same host, so native endianness is the shared one.
//!
//! # Ingest message
//! ```text
//! offset  size  field
//!      0     4  magic "HACi"
//!      4     1  kind: 1 batch, 2 episode summary, 3 batch with extra values
//!      5     1  success (episodes): 0 or 1
//!      6     2  actor id length in bytes
//!      8     8  incarnation
//!     16     8  sequence
//!     24     8  weights version
//!     32     8  env steps (episodes)
//!     40     4  level (batches)
//!     44     4  count (batches)
//!     48  6 x 4 float counts of states, actions, rewards, next states, goals, terminals
//!     72        actor id (UTF-8), zero-padded to a multiple of 8 bytes
//!      .        the six float arrays, in that order (terminals as 0.0 or 1.0)
//!      .        kind 3 only: the batch's extra values (`Transition::extra`), to the end
//! ```
//! A batch without extra values (every batch of HAC) is kind 1, laid out as before extra values
//! existed, so write-ahead logs written then still read.
//! The batch's dimensions are not checked here: the learner checks them like every batch
//! (`check_batch`), so a packed batch is refused with exactly the error gRPC would give.
//!
//! # Weights snapshot
//! ```text
//!      0     4  magic "HACw"
//!      4     4  number of levels n
//!      8     8  version
//!     16     8  episodes
//!     24     8  run finished: 0 or 1
//!     32     8  learner start (the publishing learner process's random id)
//!     40 n x 8  byte length of each level's network
//!      .        the networks (safetensors), level 0 first
//! ```

use std::borrow::Cow;

use hac_core::BatchRef;

use crate::{IngestItemRef, IngestRef, WeightsSnapshot, WireError, check_actor_id};

const INGEST_MAGIC: [u8; 4] = *b"HACi";
const WEIGHTS_MAGIC: [u8; 4] = *b"HACw";
const KIND_BATCH: u8 = 1;
const KIND_EPISODE: u8 = 2;
const KIND_BATCH_EXTRA: u8 = 3;
/// Bytes before the actor id.
const INGEST_HEADER: usize = 72;
/// Bytes before the level lengths.
const WEIGHTS_HEADER: usize = 40;
/// Where the float counts start in the ingest header.
const FLOAT_COUNTS_AT: usize = 48;

/// The alignment a packed message's buffer needs for [`unpack_ingest`] to read its floats in
/// place (the actor id is padded to keep every array at this alignment or a multiple of 4).
pub const PACKED_ALIGNMENT: usize = 8;

/// Bytes [`pack_ingest`] writes for `msg`.
pub fn packed_ingest_len(msg: &IngestRef<'_>) -> usize {
    let floats: usize = float_arrays(&msg.item).iter().map(|a| a.len()).sum();
    INGEST_HEADER + padded(msg.actor_id.len()) + 4 * (floats + extra(&msg.item).len())
}

/// The largest packed ingest message of an actor with an id of `actor_id_len` bytes, for
/// batches of at most `max_count` transitions with at most `floats_per_transition` floats each
/// (states, actions, reward, next states, goals, terminal, extra values).
pub fn max_packed_ingest_len(
    actor_id_len: usize,
    max_count: usize,
    floats_per_transition: usize,
) -> usize {
    INGEST_HEADER + padded(actor_id_len) + 4 * max_count * floats_per_transition
}

/// Writes `msg` packed into the start of `out` and returns the bytes written
/// ([`packed_ingest_len`]). `out` may have any alignment.
///
/// # Panics
/// If `out` is shorter than [`packed_ingest_len`], the actor id is longer than 65535 bytes, or a
/// level or count does not fit in 32 bits.
pub fn pack_ingest(msg: &IngestRef<'_>, out: &mut [u8]) -> usize {
    let len = packed_ingest_len(msg);
    assert!(
        out.len() >= len,
        "a packed message of {len} bytes does not fit {} bytes",
        out.len()
    );
    let out = &mut out[..len];
    let id = msg.actor_id.as_bytes();
    let (kind, success, env_steps, level, count, weights_version) = match msg.item {
        IngestItemRef::Batch {
            level,
            weights_version,
            batch,
        } => {
            let kind = if batch.extra.is_empty() {
                KIND_BATCH
            } else {
                KIND_BATCH_EXTRA
            };
            (kind, false, 0, level, batch.len, weights_version)
        }
        IngestItemRef::Episode {
            env_steps,
            success,
            weights_version,
        } => (KIND_EPISODE, success, env_steps, 0, 0, weights_version),
    };
    out[0..4].copy_from_slice(&INGEST_MAGIC);
    out[4] = kind;
    out[5] = u8::from(success);
    let id_len = u16::try_from(id.len()).expect("an actor id of at most 65535 bytes");
    out[6..8].copy_from_slice(&id_len.to_ne_bytes());
    out[8..16].copy_from_slice(&msg.incarnation.to_ne_bytes());
    out[16..24].copy_from_slice(&msg.sequence.to_ne_bytes());
    out[24..32].copy_from_slice(&weights_version.to_ne_bytes());
    out[32..40].copy_from_slice(&env_steps.to_ne_bytes());
    let to_u32 = |v: usize, what: &str| {
        u32::try_from(v).unwrap_or_else(|_| panic!("{what} {v} does not fit 32 bits"))
    };
    out[40..44].copy_from_slice(&to_u32(level, "level").to_ne_bytes());
    out[44..48].copy_from_slice(&to_u32(count, "count").to_ne_bytes());
    let arrays = float_arrays(&msg.item);
    for (i, array) in arrays.iter().enumerate() {
        let at = FLOAT_COUNTS_AT + 4 * i;
        out[at..at + 4].copy_from_slice(&to_u32(array.len(), "array length").to_ne_bytes());
    }
    let mut at = INGEST_HEADER;
    out[at..at + id.len()].copy_from_slice(id);
    out[at + id.len()..at + padded(id.len())].fill(0);
    at += padded(id.len());
    for array in arrays.into_iter().chain([extra(&msg.item)]) {
        let bytes: &[u8] = bytemuck::cast_slice(array);
        out[at..at + bytes.len()].copy_from_slice(bytes);
        at += bytes.len();
    }
    debug_assert_eq!(at, len);
    len
}

/// Reads a packed ingest message in place: the actor id and every float array borrow from
/// `bytes`. Checks the framing (magic, kind, lengths against the buffer, UTF-8, alignment) and
/// the identifying fields, with the same errors as [`decode_ingest`](crate::decode_ingest);
/// the batch itself is for the learner to check.
pub fn unpack_ingest(bytes: &[u8]) -> Result<IngestRef<'_>, WireError> {
    if bytes.len() < INGEST_HEADER {
        return Err(packed(format!(
            "{} bytes, shorter than the {INGEST_HEADER}-byte header",
            bytes.len()
        )));
    }
    if bytes[0..4] != INGEST_MAGIC {
        return Err(packed("not an ingest message (wrong magic)"));
    }
    let kind = bytes[4];
    let id_len = usize::from(u16::from_ne_bytes([bytes[6], bytes[7]]));
    let incarnation = u64_at(bytes, 8);
    let sequence = u64_at(bytes, 16);
    let weights_version = u64_at(bytes, 24);
    let env_steps = u64_at(bytes, 32);
    let level = u32_at(bytes, 40) as usize;
    let count = u32_at(bytes, 44) as usize;
    let counts: [usize; 6] =
        std::array::from_fn(|i| u32_at(bytes, FLOAT_COUNTS_AT + 4 * i) as usize);
    let floats_at = INGEST_HEADER + padded(id_len);
    // At most 6 x (2^32 - 1) floats: no overflow in usize on the 64-bit targets iceoryx2 runs on.
    let expected = floats_at + 4 * counts.iter().sum::<usize>();
    // A kind 3 batch's extra values run from there to the end.
    let extra_bytes = if kind == KIND_BATCH_EXTRA {
        bytes.len().saturating_sub(expected)
    } else {
        0
    };
    if extra_bytes % 4 != 0 {
        return Err(packed(format!(
            "{extra_bytes} bytes of extra values, not whole floats"
        )));
    }
    if kind == KIND_BATCH_EXTRA && extra_bytes == 0 {
        return Err(packed(format!(
            "{} bytes: a batch with extra values (kind 3) but none after its {expected} bytes",
            bytes.len()
        )));
    }
    if bytes.len() != expected + extra_bytes {
        return Err(packed(format!(
            "{} bytes, but its header describes {expected}",
            bytes.len()
        )));
    }
    let actor_id = std::str::from_utf8(&bytes[INGEST_HEADER..INGEST_HEADER + id_len])
        .map_err(|_| packed("the actor id is not UTF-8"))?;
    check_actor_id("ingest_request.actor_id", actor_id)?;
    if incarnation == 0 {
        return Err(WireError::missing("ingest_request.incarnation"));
    }
    if sequence == 0 {
        return Err(WireError::missing("ingest_request.sequence"));
    }
    let item = match kind {
        KIND_BATCH | KIND_BATCH_EXTRA => {
            let mut at = floats_at;
            let mut arrays: [&[f32]; 6] = [&[]; 6];
            for (array, &n) in arrays.iter_mut().zip(&counts) {
                *array = bytemuck::try_cast_slice(&bytes[at..at + 4 * n]).map_err(|_| {
                    packed("the float arrays are not 4-byte aligned in shared memory")
                })?;
                at += 4 * n;
            }
            let [states, actions, rewards, next_states, goals, terminals] = arrays;
            let extra: &[f32] = bytemuck::try_cast_slice(&bytes[at..at + extra_bytes])
                .map_err(|_| packed("the float arrays are not 4-byte aligned in shared memory"))?;
            IngestItemRef::Batch {
                level,
                weights_version,
                batch: BatchRef {
                    len: count,
                    states,
                    actions,
                    rewards,
                    next_states,
                    goals,
                    terminals,
                    extra,
                },
            }
        }
        KIND_EPISODE => {
            if counts.iter().any(|&n| n != 0) {
                return Err(packed("an episode summary with float arrays"));
            }
            let success = match bytes[5] {
                0 => false,
                1 => true,
                other => return Err(packed(format!("success byte {other}, expected 0 or 1"))),
            };
            IngestItemRef::Episode {
                env_steps,
                success,
                weights_version,
            }
        }
        0 => return Err(WireError::NoIngestItem),
        other => return Err(packed(format!("unknown item kind {other}"))),
    };
    Ok(IngestRef {
        actor_id,
        incarnation,
        sequence,
        item,
    })
}

/// The actor id, incarnation and sequence of a packed ingest message, read from its header
/// alone (any alignment; the rest is not checked).
pub fn packed_ingest_identity(bytes: &[u8]) -> Result<(&str, u64, u64), WireError> {
    if bytes.len() < INGEST_HEADER || bytes[0..4] != INGEST_MAGIC {
        return Err(packed("not an ingest message"));
    }
    let id_len = usize::from(u16::from_ne_bytes([bytes[6], bytes[7]]));
    let id = bytes
        .get(INGEST_HEADER..INGEST_HEADER + id_len)
        .ok_or_else(|| packed("the actor id runs past the message"))?;
    let actor_id = std::str::from_utf8(id).map_err(|_| packed("the actor id is not UTF-8"))?;
    Ok((actor_id, u64_at(bytes, 8), u64_at(bytes, 16)))
}

/// Bytes [`pack_weights`] writes for `snapshot`.
pub fn packed_weights_len(snapshot: &WeightsSnapshot) -> usize {
    WEIGHTS_HEADER + 8 * snapshot.levels.len() + snapshot.levels.iter().map(Vec::len).sum::<usize>()
}

/// Writes `snapshot` packed into the start of `out`; returns the bytes written
/// ([`packed_weights_len`]).
///
/// # Panics
/// If `out` is too short, or the snapshot has 2^32 levels or more.
pub fn pack_weights(snapshot: &WeightsSnapshot, out: &mut [u8]) -> usize {
    let len = packed_weights_len(snapshot);
    assert!(
        out.len() >= len,
        "a packed snapshot of {len} bytes does not fit {} bytes",
        out.len()
    );
    let levels = u32::try_from(snapshot.levels.len()).expect("fewer than 2^32 levels");
    out[0..4].copy_from_slice(&WEIGHTS_MAGIC);
    out[4..8].copy_from_slice(&levels.to_ne_bytes());
    out[8..16].copy_from_slice(&snapshot.version.to_ne_bytes());
    out[16..24].copy_from_slice(&snapshot.episodes.to_ne_bytes());
    out[24..32].copy_from_slice(&u64::from(snapshot.run_finished).to_ne_bytes());
    out[32..40].copy_from_slice(&snapshot.learner_start.to_ne_bytes());
    let mut at = WEIGHTS_HEADER;
    for level in &snapshot.levels {
        out[at..at + 8].copy_from_slice(&(level.len() as u64).to_ne_bytes());
        at += 8;
    }
    for level in &snapshot.levels {
        out[at..at + level.len()].copy_from_slice(level);
        at += level.len();
    }
    debug_assert_eq!(at, len);
    len
}

/// Reads a packed weights snapshot (copying the networks out: a snapshot outlives the shared
/// memory it came in). The same rules as [`WeightsSnapshot`]'s conversion from the wire: at
/// least one level, none empty.
pub fn unpack_weights(bytes: &[u8]) -> Result<WeightsSnapshot, WireError> {
    if bytes.len() < WEIGHTS_HEADER {
        return Err(packed(format!(
            "{} bytes, shorter than the {WEIGHTS_HEADER}-byte header",
            bytes.len()
        )));
    }
    if bytes[0..4] != WEIGHTS_MAGIC {
        return Err(packed("not a weights snapshot (wrong magic)"));
    }
    let n = u32_at(bytes, 4) as usize;
    if n == 0 {
        return Err(WireError::missing("weights.levels"));
    }
    let run_finished = match u64_at(bytes, 24) {
        0 => false,
        1 => true,
        other => return Err(packed(format!("run finished {other}, expected 0 or 1"))),
    };
    let table_end = n
        .checked_mul(8)
        .and_then(|t| t.checked_add(WEIGHTS_HEADER))
        .filter(|&end| end <= bytes.len())
        .ok_or_else(|| packed(format!("{n} levels do not fit {} bytes", bytes.len())))?;
    let mut at = table_end;
    let mut levels = Vec::with_capacity(n);
    for level in 0..n {
        let len = u64_at(bytes, WEIGHTS_HEADER + 8 * level);
        let end = usize::try_from(len)
            .ok()
            .and_then(|len| at.checked_add(len))
            .filter(|&end| end <= bytes.len())
            .ok_or_else(|| packed(format!("level {level} runs past the end")))?;
        if end == at {
            return Err(WireError::MissingField {
                field: Cow::Owned(format!("weights.levels[{level}].actor_safetensors")),
            });
        }
        levels.push(bytes[at..end].to_vec());
        at = end;
    }
    if at != bytes.len() {
        return Err(packed(format!(
            "{} bytes, but its header describes {at}",
            bytes.len()
        )));
    }
    Ok(WeightsSnapshot {
        version: u64_at(bytes, 8),
        levels,
        episodes: u64_at(bytes, 16),
        run_finished,
        learner_start: u64_at(bytes, 32),
    })
}

fn float_arrays<'a>(item: &IngestItemRef<'a>) -> [&'a [f32]; 6] {
    match *item {
        IngestItemRef::Batch { batch, .. } => [
            batch.states,
            batch.actions,
            batch.rewards,
            batch.next_states,
            batch.goals,
            batch.terminals,
        ],
        IngestItemRef::Episode { .. } => [&[]; 6],
    }
}

fn extra<'a>(item: &IngestItemRef<'a>) -> &'a [f32] {
    match *item {
        IngestItemRef::Batch { batch, .. } => batch.extra,
        IngestItemRef::Episode { .. } => &[],
    }
}

fn padded(len: usize) -> usize {
    len.div_ceil(PACKED_ALIGNMENT) * PACKED_ALIGNMENT
}

fn packed(what: impl Into<Cow<'static, str>>) -> WireError {
    WireError::Packed(what.into())
}

/// The caller has checked that `bytes` holds the header.
fn u64_at(bytes: &[u8], at: usize) -> u64 {
    u64::from_ne_bytes(bytes[at..at + 8].try_into().expect("8 bytes"))
}

fn u32_at(bytes: &[u8], at: usize) -> u32 {
    u32::from_ne_bytes(bytes[at..at + 4].try_into().expect("4 bytes"))
}

#[cfg(test)]
mod tests {
    use hac_core::{Batch, LevelDims};
    use proptest::prelude::*;

    use super::*;
    use crate::{DecodedBatch, IngestItem, IngestMessage};

    const DIMS: LevelDims = LevelDims {
        state: 3,
        goal: 2,
        action: 1,
    };

    /// A buffer at the alignment shared memory gives (8), as bytes.
    fn aligned(len: usize) -> Vec<u64> {
        vec![0u64; len.div_ceil(8)]
    }

    fn batch_message(actor_id: &str, len: usize) -> IngestMessage {
        let mut batch = Batch::zeros(DIMS, len);
        for (i, v) in batch.states.iter_mut().enumerate() {
            *v = i as f32 * 0.25 - 1.0;
        }
        batch.next_states.copy_from_slice(&batch.states);
        batch.actions.fill(0.5);
        batch.goals.fill(-0.125);
        batch.rewards.fill(-1.0);
        batch.terminals[len - 1] = 1.0;
        IngestMessage {
            actor_id: actor_id.into(),
            incarnation: 7,
            sequence: 42,
            item: IngestItem::Batch(DecodedBatch {
                level: 1,
                weights_version: 9,
                batch,
            }),
        }
    }

    fn packed_bytes(msg: &IngestMessage, buffer: &mut Vec<u64>) -> usize {
        let view = msg.view();
        let len = packed_ingest_len(&view);
        *buffer = aligned(len);
        let written = pack_ingest(&view, bytemuck::cast_slice_mut(buffer.as_mut_slice()));
        assert_eq!(written, len);
        len
    }

    fn arb_message() -> impl Strategy<Value = IngestMessage> {
        let finite = proptest::num::f32::NORMAL | proptest::num::f32::ZERO;
        (
            "[a-z0-9-]{1,20}",
            1u64..,
            1u64..,
            any::<u64>(),
            0usize..4,
            1usize..40,
            proptest::collection::vec(finite, 0..400),
            any::<Option<(u64, bool)>>(),
            0usize..3,
        )
            .prop_map(
                |(actor_id, incarnation, sequence, version, level, len, floats, episode, extra)| {
                    let item = match episode {
                        Some((env_steps, success)) => IngestItem::Episode {
                            env_steps,
                            success,
                            weights_version: version,
                        },
                        None => {
                            // Some with extra values (kind 3), some without (kind 1).
                            let mut batch = Batch::zeros_with_extra(DIMS, extra, len);
                            for (v, f) in batch.states.iter_mut().zip(floats.iter().cycle()) {
                                *v = *f;
                            }
                            for (v, f) in batch.extra.iter_mut().zip(floats.iter().rev().cycle()) {
                                *v = *f;
                            }
                            IngestItem::Batch(DecodedBatch {
                                level,
                                weights_version: version,
                                batch,
                            })
                        }
                    };
                    IngestMessage {
                        actor_id,
                        incarnation,
                        sequence,
                        item,
                    }
                },
            )
    }

    proptest! {
        #[test]
        fn ingest_messages_round_trip_bit_exact(msg in arb_message()) {
            let mut buffer = Vec::new();
            let len = packed_bytes(&msg, &mut buffer);
            let bytes: &[u8] = &bytemuck::cast_slice(&buffer)[..len];
            let view = unpack_ingest(bytes).expect("a valid packed message");
            prop_assert_eq!(view, msg.view());
        }

        #[test]
        fn arbitrary_bytes_never_panic(
            words in proptest::collection::vec(any::<u64>(), 0..40),
            cut in 0usize..8,
        ) {
            let bytes: &[u8] = bytemuck::cast_slice(&words);
            let bytes = &bytes[..bytes.len().saturating_sub(cut)];
            let _ = unpack_ingest(bytes);
            let _ = unpack_weights(bytes);
        }

        #[test]
        fn weights_round_trip(
            version in any::<u64>(),
            levels in proptest::collection::vec(
                proptest::collection::vec(any::<u8>(), 1..64),
                1..5,
            ),
            episodes in any::<u64>(),
            run_finished in any::<bool>(),
            learner_start in any::<u64>(),
        ) {
            let snapshot = WeightsSnapshot { version, levels, episodes, run_finished, learner_start };
            let mut out = vec![0u8; packed_weights_len(&snapshot) + 5];
            let len = pack_weights(&snapshot, &mut out);
            prop_assert_eq!(unpack_weights(&out[..len]).expect("valid"), snapshot);
        }
    }

    #[test]
    fn a_batch_is_read_in_place() {
        let msg = batch_message("actor-0", 4);
        let mut buffer = Vec::new();
        let len = packed_bytes(&msg, &mut buffer);
        let bytes: &[u8] = &bytemuck::cast_slice(&buffer)[..len];
        let view = unpack_ingest(bytes).unwrap();
        let IngestItemRef::Batch { batch, .. } = view.item else {
            panic!("a batch")
        };
        let range = bytes.as_ptr_range();
        for array in [batch.states, batch.goals, batch.terminals] {
            assert!(
                range.contains(&array.as_ptr().cast()),
                "borrowed, not copied"
            );
        }
        assert!(range.contains(&view.actor_id.as_ptr()));
        // 72-byte header, "actor-0" padded to 8, then 4 x (3+1+1+3+2+1) floats per transition.
        assert_eq!(len, 72 + 8 + 4 * 4 * 11);
    }

    #[test]
    fn framing_errors_are_precise() {
        let msg = batch_message("a", 2);
        let mut buffer = Vec::new();
        let len = packed_bytes(&msg, &mut buffer);
        let check = |mutate: &dyn Fn(&mut [u8]), cut: usize, expected: &str| {
            let mut copy = buffer.clone();
            let bytes: &mut [u8] = bytemuck::cast_slice_mut(copy.as_mut_slice());
            mutate(bytes);
            let err = unpack_ingest(&bytes[..len - cut]).expect_err(expected);
            assert_eq!(err.to_string(), expected);
        };
        check(
            &|_| {},
            4,
            &format!(
                "packed message: {} bytes, but its header describes {len}",
                len - 4
            ),
        );
        check(
            &|b| b[0] = b'X',
            0,
            "packed message: not an ingest message (wrong magic)",
        );
        check(&|b| b[4] = 9, 0, "packed message: unknown item kind 9");
        check(&|b| b[4] = 0, 0, "ingest request has no item");
        check(
            &|b| b[8..16].fill(0),
            0,
            "missing field ingest_request.incarnation",
        );
        check(
            &|b| b[16..24].fill(0),
            0,
            "missing field ingest_request.sequence",
        );
        check(
            &|b| b[72] = 0xff,
            0,
            "packed message: the actor id is not UTF-8",
        );
        let short = unpack_ingest(&[0u8; 10]).unwrap_err();
        assert_eq!(
            short.to_string(),
            "packed message: 10 bytes, shorter than the 72-byte header"
        );
    }

    #[test]
    fn an_actor_id_above_the_limit_is_refused() {
        let msg = batch_message(&"s".repeat(crate::MAX_ACTOR_ID_BYTES + 1), 2);
        let mut buffer = Vec::new();
        let len = packed_bytes(&msg, &mut buffer);
        let bytes: &[u8] = bytemuck::cast_slice(buffer.as_slice());
        let err = unpack_ingest(&bytes[..len]).expect_err("an id above the limit");
        assert_eq!(
            err.to_string(),
            "ingest_request.actor_id is 257 bytes, above the limit of 256 bytes"
        );
    }

    #[test]
    fn a_misaligned_buffer_is_refused_not_misread() {
        let msg = batch_message("actor-0", 3);
        let mut buffer = Vec::new();
        let len = packed_bytes(&msg, &mut buffer);
        let mut shifted = vec![0u8; len + 1];
        shifted[1..].copy_from_slice(&bytemuck::cast_slice(&buffer)[..len]);
        let err = unpack_ingest(&shifted[1..]).unwrap_err();
        assert_eq!(
            err.to_string(),
            "packed message: the float arrays are not 4-byte aligned in shared memory"
        );
    }

    #[test]
    fn snapshots_need_their_levels() {
        let snapshot = WeightsSnapshot {
            version: 3,
            levels: vec![b"abc".to_vec(), b"de".to_vec()],
            episodes: 10,
            run_finished: false,
            learner_start: 7,
        };
        let mut out = vec![0u8; packed_weights_len(&snapshot)];
        pack_weights(&snapshot, &mut out);
        let mut empty = out.clone();
        empty[48..56].copy_from_slice(&0u64.to_ne_bytes());
        empty.truncate(out.len() - 2);
        assert_eq!(
            unpack_weights(&empty).unwrap_err().to_string(),
            "missing field weights.levels[1].actor_safetensors"
        );
        let mut none = out.clone();
        none[4..8].copy_from_slice(&0u32.to_ne_bytes());
        assert_eq!(
            unpack_weights(&none).unwrap_err().to_string(),
            "missing field weights.levels"
        );
        assert_eq!(
            unpack_weights(&out[..out.len() - 1])
                .unwrap_err()
                .to_string(),
            "packed message: level 1 runs past the end"
        );
    }
}
