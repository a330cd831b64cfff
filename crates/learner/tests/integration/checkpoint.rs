//! Checkpoints of the learner core: a resumed learner continues exactly where the checkpoint was
//! taken (networks, optimiser, random streams, replay, counters, curve, versions), and
//! checkpoints that do not fit the run are refused by name.

use std::time::{Duration, Instant};

use hac_agent::RunConfig;
use hac_core::{Batch, Rng};
use hac_learner::{CheckpointError, Learner, LearnerCheckpoint, LearnerOptions, StartError};
use hac_proto::{ActorRole, DecodedBatch, Evaluation, IngestItem, IngestMessage, Registration};

use crate::common;

use common::{drained, files};

fn run(episodes: u64, shards: usize) -> RunConfig {
    common::small_run(episodes, shards)
}

fn options(run: &RunConfig) -> LearnerOptions {
    LearnerOptions::for_run(run)
}

/// An actor feeding a learner: varied batches (so that which rows are sampled matters) and
/// episode ends, numbered in sequence.
struct Feeder {
    id: String,
    incarnation: u64,
    sequence: u64,
    data: Rng,
}

impl Feeder {
    fn register(learner: &Learner, id: &str, seed: u64) -> Self {
        let incarnation = learner
            .register(Registration {
                actor_id: id.into(),
                role: ActorRole::Trainer,
                hostname: "localhost".into(),
                transports: vec!["test".into()],
            })
            .unwrap()
            .incarnation;
        Self {
            id: id.into(),
            incarnation,
            sequence: 0,
            data: Rng::seed_from(seed),
        }
    }

    fn send(&mut self, learner: &Learner, item: IngestItem) {
        self.sequence += 1;
        learner
            .ingest(&IngestMessage {
                actor_id: self.id.clone(),
                incarnation: self.incarnation,
                sequence: self.sequence,
                item,
            })
            .unwrap();
    }

    /// One episode: a batch of `len` transitions per level, then the episode's end.
    fn episode(&mut self, learner: &Learner, len: usize) {
        for level in 0..learner.dims().len() {
            let mut batch = Batch::zeros(learner.dims()[level], len);
            for field in [
                &mut batch.states,
                &mut batch.next_states,
                &mut batch.goals,
                &mut batch.actions,
            ] {
                field
                    .iter_mut()
                    .for_each(|v| *v = self.data.uniform(-1.0, 1.0));
            }
            // Rewards a level produces (the learner admits no others): 0 or -1.
            batch
                .rewards
                .iter_mut()
                .for_each(|r| *r = if self.data.unit() < 0.5 { 0.0 } else { -1.0 });
            self.send(
                learner,
                IngestItem::Batch(DecodedBatch {
                    level,
                    weights_version: 1,
                    batch,
                }),
            );
        }
        self.send(
            learner,
            IngestItem::Episode {
                env_steps: len as u64,
                success: false,
                weights_version: 1,
            },
        );
    }
}

fn evaluate(learner: &Learner, feeder: &Feeder, successes: u32) {
    let version = learner.weights().latest().unwrap().version;
    learner
        .report_evaluation(&Evaluation {
            actor_id: feeder.id.clone(),
            incarnation: feeder.incarnation,
            weights_version: version,
            episodes: 4,
            successes,
            learner_start: 0,
        })
        .unwrap();
}

#[test]
fn a_resumed_learner_does_exactly_the_updates_the_uninterrupted_one_does() {
    // One shard: an actor's batches then go to the same place in both learners.
    let config = run(1000, 1);
    let original = Learner::start(config.clone(), options(&config)).unwrap();
    let mut feeder = Feeder::register(&original, "a", 7);
    for _ in 0..4 {
        feeder.episode(&original, 5);
    }
    drained(&original);
    evaluate(&original, &feeder, 1);
    let saved = original.checkpoint(true).unwrap();
    assert!(saved.has_replay());
    assert_eq!(
        saved.updates(),
        [12, 12],
        "3 updates for each of 4 episodes"
    );
    assert_eq!(saved.episodes(), 4);
    assert_eq!(saved.curve().len(), 1);

    // Through the files, as on disk.
    let loaded = LearnerCheckpoint::from_files(&files(&saved)).unwrap();
    assert_eq!(loaded, saved);
    let resumed = Learner::resume(config.clone(), options(&config), &loaded).unwrap();
    assert!(
        resumed.weights().latest().unwrap().version > saved.weights_version(),
        "versions continue above the checkpoint's"
    );
    let status = resumed.status();
    assert_eq!(status.episodes, 4);
    assert_eq!(status.transitions, 40);
    assert_eq!(status.levels[0].updates, 12);
    assert_eq!(status.levels[0].replay_len, 20);
    assert_eq!(resumed.curve(), original.curve());

    // The same next episode: both learners train on the same replay with the same random
    // streams and optimiser state, so they end up with bit-identical networks.
    let mut again = Feeder::register(&resumed, "a", 0);
    again.data = feeder.data.clone();
    feeder.episode(&original, 5);
    again.episode(&resumed, 5);
    drained(&original);
    drained(&resumed);
    let (a, b) = (
        files(&original.checkpoint(true).unwrap()),
        files(&resumed.checkpoint(true).unwrap()),
    );
    for file in [
        "level0.safetensors",
        "level1.safetensors",
        "replay-level0.safetensors",
        "replay-level1.safetensors",
    ] {
        assert!(a[file] == b[file], "{file} differs after the same update");
    }
    let (first, second) = (original.shutdown(), resumed.shutdown());
    assert_eq!(first.status.levels[1].updates, 15);
    assert_eq!(second.status.levels[1].updates, 15);
}

#[test]
fn without_its_replay_a_resumed_learner_refills_it_before_training_again() {
    let config = run(1000, 2);
    let original = Learner::start(config.clone(), options(&config)).unwrap();
    let mut feeder = Feeder::register(&original, "a", 3);
    for _ in 0..3 {
        feeder.episode(&original, 4);
    }
    drained(&original);
    let saved = original.checkpoint(false).unwrap();
    assert!(!saved.has_replay());
    assert!(!files(&saved).keys().any(|f| f.starts_with("replay")));
    original.shutdown();

    let resumed = Learner::resume(config.clone(), options(&config), &saved).unwrap();
    let mut feeder = Feeder::register(&resumed, "a", 4);
    let before = resumed.status();
    assert_eq!(before.levels[0].replay_len, 0);
    assert_eq!(before.levels[0].updates, saved.updates()[0]);
    // Less than a batch (4) in the table: the episode earns nothing yet.
    feeder.episode(&resumed, 3);
    drained(&resumed);
    assert_eq!(resumed.status().levels[0].updates, saved.updates()[0]);
    feeder.episode(&resumed, 3);
    drained(&resumed);
    let status = resumed.status();
    assert_eq!(status.levels[0].updates, saved.updates()[0] + 3);
    assert_eq!(status.episodes, saved.episodes() + 2);
    resumed.shutdown();
}

#[test]
fn an_interrupted_run_resumes_from_its_final_state_and_a_complete_one_does_not() {
    let config = run(1000, 2);
    let learner = Learner::start(config.clone(), options(&config)).unwrap();
    let mut feeder = Feeder::register(&learner, "a", 5);
    for _ in 0..2 {
        feeder.episode(&learner, 4);
    }
    drained(&learner);
    evaluate(&learner, &feeder, 2);
    learner.finish("interrupted");
    assert!(matches!(
        learner.checkpoint(false),
        Err(CheckpointError::Finished)
    ));
    let finished = learner.shutdown();
    let last = finished.checkpoint(false);
    assert_eq!(last.completed(), None);
    assert_eq!(last.updates(), [6, 6]);
    assert_eq!(last.curve(), finished.curve.as_slice());
    let resumed = Learner::resume(config.clone(), options(&config), &last).unwrap();
    assert_eq!(resumed.status().episodes, 2);
    resumed.shutdown();

    // A run that reached its budget is complete.
    let short = run(1, 2);
    let learner = Learner::start(short.clone(), options(&short)).unwrap();
    let mut feeder = Feeder::register(&learner, "a", 6);
    feeder.episode(&learner, 4);
    let deadline = Instant::now() + Duration::from_secs(60);
    while !learner.is_finished() {
        assert!(
            Instant::now() < deadline,
            "the budget never finished the run"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    let done = learner.shutdown().checkpoint(false);
    assert!(done.completed().is_some());
    let e = Learner::resume(short.clone(), options(&short), &done).unwrap_err();
    assert!(e.to_string().contains("complete"), "{e}");
}

#[test]
fn checkpoints_of_another_run_or_with_missing_files_are_refused_by_name() {
    let config = run(1000, 2);
    let learner = Learner::start(config.clone(), options(&config)).unwrap();
    let saved = learner.checkpoint(false).unwrap();
    learner.shutdown();

    let mut other = config.clone();
    other.seed = 2;
    other.agent.gamma = 0.9;
    let e = Learner::resume(other.clone(), options(&other), &saved).unwrap_err();
    assert!(matches!(
        e,
        StartError::Checkpoint(CheckpointError::ConfigMismatch { .. })
    ));
    let e = e.to_string();
    assert!(
        e.contains("`seed` is 1 in the checkpoint, 2 now") && e.contains("`agent.gamma`"),
        "{e}"
    );

    let mut missing = files(&saved);
    missing.remove("level1.safetensors");
    let e = LearnerCheckpoint::from_files(&missing).unwrap_err();
    assert_eq!(e.to_string(), "level1.safetensors is missing");
    let mut garbage = files(&saved);
    garbage.insert("learner.json".into(), b"{ not json".to_vec());
    let e = LearnerCheckpoint::from_files(&garbage).unwrap_err();
    assert!(e.to_string().starts_with("learner.json: "), "{e}");
    // Files that parse but hold other networks (here: another level's).
    let mut swapped = files(&saved);
    let level0 = swapped["level0.safetensors"].clone();
    swapped.insert("level1.safetensors".into(), level0);
    let swapped = LearnerCheckpoint::from_files(&swapped).unwrap();
    let e = Learner::resume(config.clone(), options(&config), &swapped).unwrap_err();
    assert!(e.to_string().contains("level1.safetensors"), "{e}");
}
