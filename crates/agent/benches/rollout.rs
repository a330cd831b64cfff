//! Rollout speed of a 2- and 3-level pendulum and cartpole agent: whole episodes (actor forward
//! passes at every level, exploration, goal checks, all three transition kinds into per-level
//! replay). Episodes vary in length, so each measurement runs whole episodes until it has covered
//! its share of primitive steps and reports the time per 1000 steps: criterion's throughput is env
//! steps per second on one core.

use std::time::Instant;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use hac_agent::Agent;
use hac_core::{GaussianExploration, Hierarchy, Mode, NullSink, Rng};
use hac_replay::Replay;

/// Steps per reported iteration.
const STEPS: u64 = 1000;

fn rollout(c: &mut Criterion) {
    let mut group = c.benchmark_group("rollout");
    group.throughput(Throughput::Elements(STEPS));
    for (env_name, levels) in [
        ("pendulum", 2),
        ("pendulum", 3),
        ("cartpole", 2),
        ("cartpole", 3),
    ] {
        let mut env = hac_envs::make(env_name).unwrap();
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
        for mode in [Mode::Train, Mode::Test] {
            let name = format!("{env_name}_{levels}_levels_{mode:?}").to_lowercase();
            group.bench_function(name, |b| {
                b.iter_custom(|iters| {
                    let target = iters * STEPS;
                    let (mut steps, start) = (0u64, Instant::now());
                    while steps < target {
                        let outcome = match mode {
                            Mode::Train => hierarchy.run_episode(
                                env.as_mut(),
                                &mut agent,
                                &mut exploration,
                                mode,
                                &mut rng,
                                &mut &replay,
                            ),
                            Mode::Test => hierarchy.run_episode(
                                env.as_mut(),
                                &mut agent,
                                &mut exploration,
                                mode,
                                &mut rng,
                                &mut NullSink,
                            ),
                        };
                        steps += outcome.steps as u64;
                    }
                    // Time per `target` steps, whatever the last episode overshot.
                    start.elapsed().mul_f64(target as f64 / steps as f64)
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, rollout);
criterion_main!(benches);
