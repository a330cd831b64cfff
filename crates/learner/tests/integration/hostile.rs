//! Ingest under hostile input: random messages (any level, count, field lengths, values from
//! ordinary to 3e38, NaN and infinity, any actor, incarnation and sequence) mixed with an honest
//! actor's. Whatever arrives, the learner does not panic, stores exactly what it accepted, and
//! its published weights stay finite while it trains on what it stored.
//!
//! 16 cases of 300 hostile messages by default; `HAC_FUZZ_CASES=N` runs N (3,334 cases are a
//! million hostile messages: `HAC_FUZZ_CASES=3334 cargo test --release -p hac-learner --test
//! hostile`).

use std::time::Duration;

use hac_core::{Batch, LevelDims};
use hac_learner::{Learner, LearnerOptions, Stored};
use hac_proto::{ActorRole, DecodedBatch, IngestItem, IngestMessage, Registration};
use proptest::prelude::*;

use crate::common;

/// Values an attacker or a buggy client might send, most of them plausible.
fn value() -> impl Strategy<Value = f32> {
    prop_oneof![
        6 => -1.5f32..1.5,
        1 => Just(3e38f32),
        1 => Just(-1e30f32),
        1 => Just(f32::NAN),
        1 => Just(f32::INFINITY),
        1 => Just(-32.0f32),
        1 => any::<f32>(),
    ]
}

#[derive(Debug, Clone)]
struct Raw {
    actor: u8,
    incarnation_offset: u8,
    sequence: u64,
    level: usize,
    count: usize,
    /// Per field: how many values it holds beyond (or short of) what `count` asks.
    skew: [i8; 7],
    values: Vec<f32>,
    episode: Option<(u64, bool)>,
}

fn raw() -> impl Strategy<Value = Raw> {
    (
        0u8..3,
        0u8..2,
        0u64..6,
        0usize..3,
        0usize..12,
        prop::array::uniform7(prop_oneof![8 => Just(0i8), 1 => -2i8..3]),
        prop::collection::vec(value(), 400),
        prop::option::weighted(0.2, (0u64..2000, any::<bool>())),
    )
        .prop_map(
            |(actor, incarnation_offset, sequence, level, count, skew, values, episode)| Raw {
                actor,
                incarnation_offset,
                sequence,
                level,
                count,
                skew,
                values,
                episode,
            },
        )
}

fn field(values: &mut impl Iterator<Item = f32>, n: usize, skew: i8) -> Vec<f32> {
    let n = n.saturating_add_signed(skew as isize);
    values.by_ref().take(n).collect()
}

fn message(raw: &Raw, dims: &[LevelDims], incarnations: &[u64]) -> IngestMessage {
    let actor = raw.actor as usize;
    let item = match raw.episode {
        Some((env_steps, success)) => IngestItem::Episode {
            env_steps,
            success,
            weights_version: 1,
        },
        None => {
            let d = dims.get(raw.level).copied().unwrap_or(dims[0]);
            let n = raw.count;
            let mut v = raw.values.iter().copied().cycle();
            let s = raw.skew;
            IngestItem::Batch(DecodedBatch {
                level: raw.level,
                weights_version: 1,
                batch: Batch {
                    dims: d,
                    len: n,
                    states: field(&mut v, n * d.state, s[0]),
                    actions: field(&mut v, n * d.action, s[1]),
                    rewards: field(&mut v, n, s[2]),
                    next_states: field(&mut v, n * d.state, s[3]),
                    goals: field(&mut v, n * d.goal, s[4]),
                    terminals: field(&mut v, n, s[5])
                        .into_iter()
                        .map(|t| if t > 0.0 { 1.0 } else { 0.0 })
                        .collect(),
                    // A HAC learner's levels store no extra values: any is refused.
                    extra_width: 0,
                    extra: field(&mut v, 0, s[6]),
                },
            })
        }
    };
    IngestMessage {
        actor_id: format!("actor-{actor}"),
        incarnation: incarnations[actor % incarnations.len()] + u64::from(raw.incarnation_offset),
        sequence: raw.sequence,
        item,
    }
}

/// Cases to run: `HAC_FUZZ_CASES`, or 16.
fn cases() -> u32 {
    std::env::var("HAC_FUZZ_CASES")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(16)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: cases(), ..ProptestConfig::default() })]

    #[test]
    fn hostile_ingest_stores_what_it_accepted_and_weights_stay_finite(
        raws in prop::collection::vec(raw(), 300),
    ) {
        let config = common::small_run(1000, 2);
        let options = LearnerOptions::for_run(&config);
        let learner = Learner::start(config, options).unwrap();
        let honest = learner
            .register(Registration {
                actor_id: "honest".into(),
                role: ActorRole::Trainer,
                hostname: "fuzz".into(),
                transports: vec!["grpc".into()],
            })
            .unwrap()
            .incarnation;
        let incarnations: Vec<u64> = (0..3)
            .map(|i| {
                learner
                    .register(Registration {
                        actor_id: format!("actor-{i}"),
                        role: ActorRole::Trainer,
                        hostname: "fuzz".into(),
                        transports: vec!["grpc".into()],
                    })
                    .unwrap()
                    .incarnation
            })
            .collect();
        let dims = learner.dims().to_vec();
        let mut accepted = 0u64;
        let mut honest_sequence = 0;
        for (i, raw) in raws.iter().enumerate() {
            let msg = message(raw, &dims, &incarnations);
            if let Ok(Stored::New) = learner.ingest(&msg)
                && let IngestItem::Batch(b) = &msg.item
            {
                accepted += b.batch.len as u64;
            }
            // An honest actor keeps sending between the hostile messages, so that the trainers
            // have something to train on.
            if i % 3 == 0 {
                honest_sequence += 1;
                let item = if i % 24 == 0 {
                    IngestItem::Episode { env_steps: 100, success: false, weights_version: 1 }
                } else {
                    let level = i % 2;
                    let mut batch = Batch::zeros(dims[level], 8);
                    for (j, s) in batch.states.iter_mut().enumerate() {
                        *s = ((i + j) % 5) as f32 * 0.2 - 0.4;
                    }
                    batch.rewards.fill(-1.0);
                    accepted += 8;
                    IngestItem::Batch(DecodedBatch { level, weights_version: 1, batch })
                };
                let msg = IngestMessage {
                    actor_id: "honest".into(),
                    incarnation: honest,
                    sequence: honest_sequence,
                    item,
                };
                prop_assert_eq!(learner.ingest(&msg).unwrap(), Stored::New);
            }
        }
        let status = learner.status();
        prop_assert_eq!(status.transitions, accepted);
        let inserted: u64 = status.levels.iter().map(|l| l.transitions_inserted).sum();
        prop_assert_eq!(inserted, accepted);
        // Give the trainers a moment on whatever was stored, then look at what is published.
        std::thread::sleep(Duration::from_millis(20));
        let weights = learner.weights().latest().unwrap();
        for level in &weights.levels {
            let actor = hac_nn::ActorNet::from_safetensors(level).unwrap();
            prop_assert!(actor.mlp().tensors().flatten().all(|v| v.is_finite()));
        }
        let diverged: u64 = status.levels.iter().map(|l| l.diverged_updates).sum();
        prop_assert_eq!(diverged, 0, "admitted data never makes an update diverge");
        learner.shutdown();
    }
}
