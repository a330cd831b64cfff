//! Rollout speed of 2- and 3-level agents: whole episodes (actor forward passes at every level,
//! exploration, goal checks, all three transition kinds into per-level replay). Episodes vary in
//! length, so each measurement runs whole episodes until it has covered its share of primitive
//! steps and reports the time per `steps` steps: criterion's throughput is env steps per second
//! on one core. Pendulum and cartpole step in well under a microsecond, so the agent's own work
//! dominates; pick-and-place (contact physics, about 0.3 ms per action) is measured in its own
//! group with fewer samples, to show what an actor process spends per episode there.

use std::time::Instant;

use criterion::measurement::WallTime;
use criterion::{BenchmarkGroup, Criterion, Throughput, criterion_group, criterion_main};
use hac_agent::Agent;
use hac_core::{GaussianExploration, Hierarchy, Mode, NullSink, Rng};
use hac_replay::Replay;

fn rollout(c: &mut Criterion) {
    let mut group = c.benchmark_group("rollout");
    for (env_name, levels) in [
        ("pendulum", 2),
        ("pendulum", 3),
        ("cartpole", 2),
        ("cartpole", 3),
    ] {
        bench_env(&mut group, env_name, levels, 1000);
    }
    group.finish();
    // One episode's budget (200 actions) per iteration; 10 samples take about 10 s per case.
    let mut group = c.benchmark_group("rollout_contacts");
    group.sample_size(10);
    for levels in [2, 3] {
        bench_env(&mut group, "pick-and-place", levels, 200);
    }
    group.finish();
}

fn bench_env(group: &mut BenchmarkGroup<'_, WallTime>, env_name: &str, levels: usize, steps: u64) {
    group.throughput(Throughput::Elements(steps));
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
    let replay = Replay::for_agent(&spec, &small, 1, &[]);
    for mode in [Mode::Train, Mode::Test] {
        let name = format!("{env_name}_{levels}_levels_{mode:?}").to_lowercase();
        group.bench_function(name, |b| {
            b.iter_custom(|iters| {
                let target = iters * steps;
                let (mut done, start) = (0u64, Instant::now());
                while done < target {
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
                    done += outcome.steps as u64;
                }
                // Time per `target` steps, whatever the last episode overshot.
                start.elapsed().mul_f64(target as f64 / done as f64)
            })
        });
    }
}

criterion_group!(benches, rollout);
criterion_main!(benches);
