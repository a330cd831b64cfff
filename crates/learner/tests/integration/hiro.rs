//! HIRO in the learner core: its batches are admitted by HIRO's limits (the high level's with
//! their low-level steps, refused without them), both TD3 levels train, and a checkpoint resumes
//! exactly where it was taken.

use hac_agent::RunConfig;
use hac_core::hiro::{Algo, HiroConfig};
use hac_core::{Batch, Env, Episodes, GaussianExploration, Mode, OwnedTransition, Policy, Rng};
use hac_learner::{IngestError, Learner, LearnerCheckpoint, LearnerOptions};
use hac_proto::{ActorRole, DecodedBatch, IngestItem, IngestMessage, Registration};

use crate::common;

use common::{drained, files};

/// A small HIRO pendulum run: 50-action episodes, batches of 4, one hidden layer of 8; 5
/// low-level and 0.5 high-level updates per episode.
fn hiro_run() -> RunConfig {
    let mut run = common::small_run(1000, 1);
    HiroConfig::agent_defaults(&mut run.agent);
    run.agent.batch_size = 4;
    run.agent.hidden_layers = vec![8];
    run.max_actions = Some(50);
    run.algo = Algo::Hiro;
    run.hiro = Some(HiroConfig {
        updates_per_step: 0.1,
        ..HiroConfig::default()
    });
    run.validate("test").unwrap();
    run
}

/// Acts by a fixed rule: HIRO's rollout with exploration noise makes varied transitions of it.
struct Still;

impl Policy for Still {
    fn act(&mut self, _level: usize, state: &[f32], _goal: &[f32], action: &mut [f32]) {
        action.iter_mut().for_each(|a| *a = 0.1 * state[0]);
    }
}

/// An actor playing HIRO episodes into a learner, numbering its messages.
struct Feeder {
    id: String,
    incarnation: u64,
    sequence: u64,
    env: Box<dyn Env>,
    episodes: Episodes,
    exploration: GaussianExploration,
    rng: Rng,
}

impl Feeder {
    fn register(learner: &Learner, run: &RunConfig, id: &str, seed: u64) -> Self {
        let incarnation = learner
            .register(Registration {
                actor_id: id.into(),
                role: ActorRole::Trainer,
                hostname: "localhost".into(),
                transports: vec!["test".into()],
            })
            .unwrap()
            .incarnation;
        let env = run.make_env().unwrap();
        let spec = env.spec().clone();
        let mut rng = Rng::seed_from(seed);
        Self {
            id: id.into(),
            incarnation,
            sequence: 0,
            exploration: GaussianExploration::new(&spec, &run.agent, rng.fork()),
            episodes: Episodes::new(&spec, &run.agent, run.hiro()),
            env,
            rng,
        }
    }

    fn send(&mut self, learner: &Learner, item: IngestItem) -> Result<(), IngestError> {
        self.sequence += 1;
        learner
            .ingest(&IngestMessage {
                actor_id: self.id.clone(),
                incarnation: self.incarnation,
                sequence: self.sequence,
                item,
            })
            .map(|_| ())
    }

    /// Plays one training episode; returns its transitions and how many primitive actions it
    /// took and whether it succeeded.
    fn play(&mut self) -> (Vec<OwnedTransition>, u64, bool) {
        let mut got: Vec<OwnedTransition> = Vec::new();
        let outcome = self.episodes.run_episode(
            self.env.as_mut(),
            &mut Still,
            &mut self.exploration,
            Mode::Train,
            &mut self.rng,
            &mut got,
        );
        (got, outcome.steps as u64, outcome.success)
    }

    /// One training episode: its transitions, one batch per level, then its end.
    fn episode(&mut self, learner: &Learner) {
        let (got, steps, success) = self.play();
        for level in 0..2 {
            let batch = batch_of(learner, level, got.iter().filter(|t| t.level == level));
            self.send(
                learner,
                IngestItem::Batch(DecodedBatch {
                    level,
                    weights_version: 1,
                    batch,
                }),
            )
            .unwrap();
        }
        self.send(
            learner,
            IngestItem::Episode {
                env_steps: steps,
                success,
                weights_version: 1,
            },
        )
        .unwrap();
    }
}

fn batch_of<'a>(
    learner: &Learner,
    level: usize,
    transitions: impl Iterator<Item = &'a OwnedTransition>,
) -> Batch {
    let mut batch = Batch::zeros(learner.dims()[level], 0);
    for t in transitions {
        batch.states.extend_from_slice(&t.state);
        batch.actions.extend_from_slice(&t.action);
        batch.rewards.push(t.reward);
        batch.next_states.extend_from_slice(&t.next_state);
        batch.goals.extend_from_slice(&t.goal);
        batch.terminals.push(f32::from(u8::from(t.terminal)));
        batch.extra_width = t.extra.len();
        batch.extra.extend_from_slice(&t.extra);
        batch.len += 1;
    }
    batch
}

#[test]
fn hiro_batches_are_admitted_by_hiros_limits_and_both_levels_train() {
    let run = hiro_run();
    let learner = Learner::start(run.clone(), LearnerOptions::for_run(&run)).unwrap();
    let mut feeder = Feeder::register(&learner, &run, "a", 3);
    for _ in 0..4 {
        feeder.episode(&learner);
    }
    drained(&learner);
    let status = learner.status();
    // 50 primitive actions per episode, a high-level decision every 10.
    assert_eq!(status.levels[0].transitions_inserted, 200);
    assert_eq!(status.levels[1].transitions_inserted, 20);
    // 5 and 0.5 updates per episode once a level holds a batch (both did after one episode).
    assert_eq!(status.levels[0].updates, 20);
    assert_eq!(status.levels[1].updates, 2);

    // The high level's transitions without their steps: refused by name, nothing stored.
    let (got, _, _) = feeder.play();
    let mut stripped = batch_of(&learner, 1, got.iter().filter(|t| t.level == 1));
    stripped.extra.clear();
    stripped.extra_width = 0;
    let e = feeder
        .send(
            &learner,
            IngestItem::Batch(DecodedBatch {
                level: 1,
                weights_version: 1,
                batch: stripped,
            }),
        )
        .unwrap_err();
    assert!(e.to_string().contains("batch.extra has 0 values"), "{e}");
    // A step count beyond c: refused, naming the transition.
    feeder.sequence -= 1;
    let mut forged = batch_of(&learner, 1, got.iter().filter(|t| t.level == 1));
    forged.extra[forged.extra_width] = 11.0;
    let e = feeder
        .send(
            &learner,
            IngestItem::Batch(DecodedBatch {
                level: 1,
                weights_version: 1,
                batch: forged,
            }),
        )
        .unwrap_err();
    assert!(e.to_string().contains("transition 1"), "{e}");
    assert_eq!(learner.status().levels[1].transitions_inserted, 20);
    learner.shutdown();
}

#[test]
fn a_resumed_hiro_learner_does_exactly_the_updates_the_uninterrupted_one_does() {
    let run = hiro_run();
    let original = Learner::start(run.clone(), LearnerOptions::for_run(&run)).unwrap();
    let mut feeder = Feeder::register(&original, &run, "a", 9);
    for _ in 0..4 {
        feeder.episode(&original);
    }
    drained(&original);
    let saved = original.checkpoint(true).unwrap();
    assert_eq!(saved.updates(), [20, 2]);
    let loaded = LearnerCheckpoint::from_files(&files(&saved)).unwrap();
    let resumed = Learner::resume(run.clone(), LearnerOptions::for_run(&run), &loaded).unwrap();

    // The same next episodes into both: the same replay, random streams, TD3 state and
    // published low-level policy give bit-identical networks.
    let mut again = Feeder::register(&resumed, &run, "a", 0);
    again.rng = feeder.rng.clone();
    again.exploration = feeder.exploration.clone();
    for _ in 0..4 {
        feeder.episode(&original);
        again.episode(&resumed);
        drained(&original);
        drained(&resumed);
    }
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
        assert!(a[file] == b[file], "{file} differs after the same updates");
    }
    assert_eq!(original.status().levels[1].updates, 4);
    original.shutdown();
    resumed.shutdown();
}
