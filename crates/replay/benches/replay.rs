//! Replay hot paths at pendulum size (state 3, goal 2, action 1): inserting one transition into a
//! full table (the steady state, overwriting the oldest row), and sampling a training batch of
//! 1024 from a table of one million transitions.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use hac_core::{Batch, LevelDims, Rng, Transition, TransitionKind};
use hac_replay::ReplayTable;

const DIMS: LevelDims = LevelDims {
    state: 3,
    goal: 2,
    action: 1,
};
const CAPACITY: usize = 1 << 20;

fn transition(x: f32) -> ([f32; 3], [f32; 1], [f32; 3], [f32; 2]) {
    ([x, x, x], [x], [x + 1.0, x, x], [x, x])
}

fn full_table(shards: usize) -> ReplayTable {
    let table = ReplayTable::new(DIMS, CAPACITY, shards);
    for i in 0..CAPACITY {
        let (state, action, next_state, goal) = transition(i as f32);
        table.insert(&Transition {
            kind: TransitionKind::HindsightAction,
            state: &state,
            action: &action,
            reward: -1.0,
            next_state: &next_state,
            goal: &goal,
            terminal: false,
            extra: &[],
        });
    }
    table
}

fn bench(c: &mut Criterion) {
    for shards in [1, 4] {
        let table = full_table(shards);
        let (state, action, next_state, goal) = transition(0.5);
        let t = Transition {
            kind: TransitionKind::HindsightAction,
            state: &state,
            action: &action,
            reward: -1.0,
            next_state: &next_state,
            goal: &goal,
            terminal: true,
            extra: &[],
        };

        let mut group = c.benchmark_group(format!("replay_{shards}_shards"));
        group.throughput(Throughput::Elements(1));
        group.bench_function("insert", |b| b.iter(|| table.insert(black_box(&t))));

        let mut batch = Batch::zeros(DIMS, 1024);
        let mut rng = Rng::seed_from(1);
        group.throughput(Throughput::Elements(batch.len as u64));
        group.bench_function("sample_1024_of_1m", |b| {
            b.iter(|| {
                table.sample(&mut rng, &mut batch).unwrap();
                black_box(&batch);
            })
        });
        group.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
