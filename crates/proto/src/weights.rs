//! Weights publishing: `pb::Weights` <-> [`WeightsSnapshot`], and the watch request.

use std::borrow::Cow;
use std::sync::Arc;

use crate::{WireError, check_actor_id, pb};

/// A whole-model snapshot: `levels[i]` is level `i`'s actor network in safetensors format.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WeightsSnapshot {
    pub version: u64,
    pub levels: Vec<Vec<u8>>,
    /// Training episodes whose updates every level had completed when this was taken.
    pub episodes: u64,
    /// The run is over; actors stop after this snapshot.
    pub run_finished: bool,
    /// The learner process that published it (random at each start).
    pub learner_start: u64,
}

/// Accepts the levels in any order but requires exactly the levels `0..n`, each once, each with
/// a non-empty network.
impl TryFrom<pb::Weights> for WeightsSnapshot {
    type Error = WireError;

    fn try_from(msg: pb::Weights) -> Result<Self, WireError> {
        let n = msg.levels.len();
        if n == 0 {
            return Err(WireError::missing("weights.levels"));
        }
        let mut slots: Vec<Option<Vec<u8>>> = vec![None; n];
        for (index, entry) in msg.levels.into_iter().enumerate() {
            if entry.actor_safetensors.is_empty() {
                return Err(WireError::MissingField {
                    field: Cow::Owned(format!("weights.levels[{index}].actor_safetensors")),
                });
            }
            // A level >= n leaves a gap below n, reported as the missing level after the loop.
            if let Some(slot) = slots.get_mut(entry.level as usize) {
                if slot.is_some() {
                    return Err(WireError::DuplicateLevel { level: entry.level });
                }
                *slot = Some(entry.actor_safetensors);
            }
        }
        let mut levels = Vec::with_capacity(n);
        for (level, slot) in slots.into_iter().enumerate() {
            levels.push(slot.ok_or(WireError::MissingLevel { level, levels: n })?);
        }
        Ok(Self {
            version: msg.version,
            levels,
            episodes: msg.episodes,
            run_finished: msg.run_finished,
            learner_start: msg.learner_start,
        })
    }
}

impl From<WeightsSnapshot> for pb::Weights {
    fn from(snapshot: WeightsSnapshot) -> Self {
        Self {
            version: snapshot.version,
            levels: snapshot
                .levels
                .into_iter()
                .enumerate()
                .map(|(level, actor_safetensors)| pb::LevelWeights {
                    level: u32::try_from(level).expect("fewer than 2^32 levels"),
                    actor_safetensors,
                })
                .collect(),
            episodes: snapshot.episodes,
            run_finished: snapshot.run_finished,
            learner_start: snapshot.learner_start,
        }
    }
}

/// An actor's request for the weights stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WeightsWatch {
    pub actor_id: String,
    pub incarnation: u64,
    /// Send nothing older than this version; 0 asks for the current version at once.
    pub min_version: u64,
}

impl TryFrom<pb::WatchWeightsRequest> for WeightsWatch {
    type Error = WireError;

    fn try_from(msg: pb::WatchWeightsRequest) -> Result<Self, WireError> {
        check_actor_id("watch_weights_request.actor_id", &msg.actor_id)?;
        if msg.incarnation == 0 {
            return Err(WireError::missing("watch_weights_request.incarnation"));
        }
        Ok(Self {
            actor_id: msg.actor_id,
            incarnation: msg.incarnation,
            min_version: msg.min_version,
        })
    }
}

impl From<WeightsWatch> for pb::WatchWeightsRequest {
    fn from(watch: WeightsWatch) -> Self {
        Self {
            actor_id: watch.actor_id,
            incarnation: watch.incarnation,
            min_version: watch.min_version,
        }
    }
}

/// The weights of the best test round so far.
#[derive(Debug, Clone)]
pub struct BestWeights {
    /// 1-based, as on the learning curve.
    pub round: usize,
    /// Training episodes behind the weights (the curve's x).
    pub episodes: u64,
    pub env_steps: u64,
    pub success_rate: f32,
    pub snapshot: Arc<WeightsSnapshot>,
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;
    use prost::Message;

    use super::*;

    fn entry(level: u32, bytes: &[u8]) -> pb::LevelWeights {
        pb::LevelWeights {
            level,
            actor_safetensors: bytes.to_vec(),
        }
    }

    fn weights(levels: Vec<pb::LevelWeights>) -> pb::Weights {
        pb::Weights {
            version: 4,
            levels,
            ..Default::default()
        }
    }

    proptest! {
        #[test]
        fn snapshots_round_trip(
            version in any::<u64>(),
            levels in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 1..64), 1..5),
            episodes in any::<u64>(),
            run_finished in any::<bool>(),
            learner_start in any::<u64>(),
        ) {
            let snapshot = WeightsSnapshot { version, levels, episodes, run_finished, learner_start };
            let bytes = pb::Weights::from(snapshot.clone()).encode_to_vec();
            let decoded = pb::Weights::decode(bytes.as_slice()).expect("prost decodes its own bytes");
            prop_assert_eq!(WeightsSnapshot::try_from(decoded).expect("valid"), snapshot);
        }
    }

    #[test]
    fn levels_are_ordered_by_level_not_by_position() {
        let msg = weights(vec![entry(2, b"c"), entry(0, b"a"), entry(1, b"b")]);
        let snapshot = WeightsSnapshot::try_from(msg).expect("valid");
        assert_eq!(
            snapshot.levels,
            [b"a".to_vec(), b"b".to_vec(), b"c".to_vec()]
        );
    }

    #[test]
    fn duplicate_levels_are_refused() {
        let err = WeightsSnapshot::try_from(weights(vec![entry(1, b"a"), entry(1, b"b")]))
            .expect_err("duplicate");
        assert_eq!(err.to_string(), "weights.levels has level 1 twice");
    }

    #[test]
    fn missing_levels_are_refused() {
        let err = WeightsSnapshot::try_from(weights(vec![entry(0, b"a"), entry(2, b"c")]))
            .expect_err("gap");
        assert_eq!(
            err.to_string(),
            "weights.levels lacks level 1 (has 2 entries, expected levels 0..2)"
        );
        let err = WeightsSnapshot::try_from(weights(vec![])).expect_err("empty");
        assert_eq!(err.to_string(), "missing field weights.levels");
    }

    #[test]
    fn empty_networks_are_refused() {
        let err = WeightsSnapshot::try_from(weights(vec![entry(0, b"a"), entry(1, b"")]))
            .expect_err("empty network");
        assert_eq!(
            err.to_string(),
            "missing field weights.levels[1].actor_safetensors"
        );
    }

    #[test]
    fn watch_requests_round_trip_and_need_an_actor() {
        let watch = WeightsWatch {
            actor_id: "a".into(),
            incarnation: 2,
            min_version: 0,
        };
        let msg = pb::WatchWeightsRequest::from(watch.clone());
        assert_eq!(WeightsWatch::try_from(msg.clone()).expect("valid"), watch);
        let err = WeightsWatch::try_from(pb::WatchWeightsRequest {
            actor_id: String::new(),
            ..msg.clone()
        })
        .expect_err("no actor");
        assert_eq!(
            err.to_string(),
            "missing field watch_weights_request.actor_id"
        );
        let err = WeightsWatch::try_from(pb::WatchWeightsRequest {
            actor_id: "w".repeat(1 << 20),
            ..msg
        })
        .expect_err("an id above the limit");
        assert_eq!(
            err.to_string(),
            "watch_weights_request.actor_id is 1048576 bytes, above the limit of 256 bytes"
        );
    }
}
