//! The best weights: the snapshot behind the best test round, kept through checkpoints.

use std::collections::BTreeMap;
use std::sync::Arc;

use hac_agent::RunConfig;
use hac_learner::{Learner, LearnerCheckpoint, LearnerOptions, RECENT_SNAPSHOTS};
use hac_proto::{ActorRole, Evaluation, Registration};

use crate::common;

fn run() -> RunConfig {
    common::small_run(1000, 2)
}

fn start(run: &RunConfig) -> Learner {
    Learner::start(run.clone(), LearnerOptions::for_run(run)).unwrap()
}

fn evaluator(learner: &Learner) -> u64 {
    learner
        .register(Registration {
            actor_id: "e".into(),
            role: ActorRole::Evaluator,
            hostname: "localhost".into(),
            transports: vec!["grpc".into()],
        })
        .unwrap()
        .incarnation
}

fn report(learner: &Learner, incarnation: u64, weights_version: u64, successes: u32) {
    learner
        .report_evaluation(&Evaluation {
            actor_id: "e".into(),
            incarnation,
            weights_version,
            learner_start: 0,
            episodes: 10,
            successes,
        })
        .unwrap();
}

#[test]
fn the_best_round_keeps_the_snapshot_it_evaluated_and_the_first_of_equals_wins() {
    let learner = start(&run());
    let e = evaluator(&learner);
    assert!(learner.best().latest().is_none(), "no round yet");
    let mut published = BTreeMap::new();
    let mut publish = || {
        let version = learner.republish();
        published.insert(version, learner.weights().latest().unwrap());
        version
    };
    let v2 = publish();
    let v3 = publish();
    let v4 = publish();
    // Rounds: 30% of v2, 80% of v3 (the best), 80% of v4 (no better), 50% of v4.
    report(&learner, e, v2, 3);
    assert_eq!(learner.best().latest().unwrap().round, 1);
    report(&learner, e, v3, 8);
    report(&learner, e, v4, 8);
    report(&learner, e, v4, 5);
    let best = learner.best().latest().unwrap();
    assert_eq!((best.round, best.success_rate), (2, 0.8));
    assert_eq!(best.snapshot.version, v3);
    assert!(
        Arc::ptr_eq(&best.snapshot, &published[&v3]),
        "the very snapshot published as v3"
    );
    let finished = learner.shutdown();
    assert_eq!(finished.best.unwrap().snapshot.version, v3);
}

#[test]
fn a_round_of_weights_no_longer_kept_leaves_the_best_as_it_was() {
    let learner = start(&run());
    let e = evaluator(&learner);
    let old = learner.republish();
    report(&learner, e, old, 2);
    for _ in 0..RECENT_SNAPSHOTS {
        learner.republish();
    }
    // `old` is still on the curve's version map but its snapshot was let go.
    report(&learner, e, old, 9);
    assert_eq!(learner.curve().len(), 2, "the round is on the curve");
    let best = learner.best().latest().unwrap();
    assert_eq!(
        (best.round, best.snapshot.version),
        (1, old),
        "the earlier best stays"
    );
    // A recent version can still become the best.
    let recent = learner.republish();
    report(&learner, e, recent, 9);
    assert_eq!(learner.best().latest().unwrap().snapshot.version, recent);
    learner.shutdown();
}

#[test]
fn checkpoints_carry_the_best_weights_into_a_resumed_learner() {
    let config = run();
    let learner = start(&config);
    let e = evaluator(&learner);
    let v = learner.republish();
    report(&learner, e, v, 7);
    learner.republish();
    report(&learner, e, learner.republish(), 4);
    learner.finish("interrupted");
    let checkpoint = learner.shutdown().checkpoint(false);
    let files: BTreeMap<String, Vec<u8>> = checkpoint.to_files().into_iter().collect();
    assert!(files.contains_key("best-level0.safetensors"));
    assert!(files.contains_key("best-level1.safetensors"));
    let read = LearnerCheckpoint::from_files(&files).unwrap();
    let best = read.best().unwrap();
    assert_eq!((best.round, best.success_rate), (1, 0.7));
    assert_eq!(best.snapshot.version, v);

    let resumed = Learner::resume(config.clone(), LearnerOptions::for_run(&config), &read).unwrap();
    let restored = resumed.best().latest().unwrap();
    assert_eq!(restored.snapshot.levels, best.snapshot.levels);
    assert_eq!(restored.round, 1);
    // A worse round after the resume does not replace it; a better one does.
    let e = evaluator(&resumed);
    report(&resumed, e, resumed.republish(), 6);
    assert_eq!(resumed.best().latest().unwrap().round, 1);
    report(&resumed, e, resumed.republish(), 10);
    assert_eq!(resumed.best().latest().unwrap().round, 4);
    resumed.shutdown();

    // A checkpoint naming best weights without their files is refused by name.
    let mut missing = files.clone();
    missing.remove("best-level1.safetensors");
    let e = LearnerCheckpoint::from_files(&missing).unwrap_err();
    assert!(e.to_string().contains("best-level1.safetensors"), "{e}");
}
