//! Rollout speed of a 2-level pendulum agent: full training episodes (actor forward passes at
//! every level, exploration, goal checks, all three transition kinds into per-level replay).
//! An untrained agent never reaches the goal, so every episode is exactly `max_actions` steps and
//! criterion's throughput is primitive env steps per second on one core.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use hac_agent::Agent;
use hac_core::{GaussianExploration, Hierarchy, Mode, NullSink, Rng};
use hac_replay::Replay;

fn rollout(c: &mut Criterion) {
    let mut group = c.benchmark_group("rollout");
    for levels in [2, 3] {
        let mut env = hac_envs::make("pendulum").unwrap();
        let spec = env.spec().clone();
        let config = env.default_config(levels);
        let mut rng = Rng::seed_from(1);
        let mut agent = Agent::new(&spec, &config, &mut rng);
        let mut exploration = GaussianExploration::new(&spec, &config, rng.fork());
        let mut hierarchy = Hierarchy::new(&spec, &config);
        // A small replay keeps memory flat; rings overwrite, so inserts cost the same throughout.
        let mut small = config.clone();
        small.replay_capacity_max = 100_000;
        let replay = Replay::for_agent(&spec, &small, 1);
        let steps = spec.max_actions as u64;
        group.throughput(Throughput::Elements(steps));
        group.bench_function(format!("pendulum_{levels}_levels_train_episode"), |b| {
            b.iter(|| {
                let outcome = hierarchy.run_episode(
                    env.as_mut(),
                    &mut agent,
                    &mut exploration,
                    Mode::Train,
                    &mut rng,
                    &mut &replay,
                );
                assert_eq!(outcome.steps as u64, steps, "episode ended early");
            })
        });
        group.bench_function(format!("pendulum_{levels}_levels_test_episode"), |b| {
            b.iter(|| {
                let outcome = hierarchy.run_episode(
                    env.as_mut(),
                    &mut agent,
                    &mut exploration,
                    Mode::Test,
                    &mut rng,
                    &mut NullSink,
                );
                assert_eq!(outcome.steps as u64, steps, "episode ended early");
            })
        });
    }
    group.finish();
}

criterion_group!(benches, rollout);
criterion_main!(benches);
