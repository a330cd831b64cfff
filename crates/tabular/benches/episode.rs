//! One training episode (rollout plus its Q-learning updates) and one greedy test episode of
//! 2-level tabular HAC on the 10 x 10 four-rooms grid, and one training episode of 3 levels on
//! 25 x 25 (the largest default tables, every stretch of the path learned for every goal).
//! Tables and buffers are warmed up first, so an iteration measures the steady state, which
//! should allocate nothing.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use hac_core::{Env, Rng};
use hac_tabular::{FourRooms, TabularConfig, TabularHac};

fn episode(c: &mut Criterion) {
    let mut env = FourRooms::new(10).unwrap();
    let mut rng = Rng::seed_from(0);
    let config = env.default_config(2);
    let mut learner = TabularHac::new(&env, config, &TabularConfig::default(), &mut rng).unwrap();
    for _ in 0..200 {
        learner.train_episode(&mut env, &mut rng);
    }
    c.bench_function("four-rooms/2-level/train_episode", |b| {
        b.iter(|| black_box(learner.train_episode(&mut env, &mut rng)))
    });
    c.bench_function("four-rooms/2-level/test_episode", |b| {
        b.iter(|| black_box(learner.test_episode(&mut env, &mut rng)))
    });

    let mut env = FourRooms::new(25).unwrap();
    let config = env.default_config(3);
    let mut learner = TabularHac::new(&env, config, &TabularConfig::default(), &mut rng).unwrap();
    for _ in 0..200 {
        learner.train_episode(&mut env, &mut rng);
    }
    let mut group = c.benchmark_group("four-rooms-25/3-level");
    group.sample_size(20);
    group.bench_function("train_episode", |b| {
        b.iter(|| black_box(learner.train_episode(&mut env, &mut rng)))
    });
    group.finish();
}

criterion_group!(benches, episode);
criterion_main!(benches);
