//! One full learner update (critic step + actor step) at the reference batch size and network
//! (batch 1024, hidden [64, 64, 64]) for pendulum-like levels and for pick-and-place's widest
//! levels (state 20; level 0 with a 7-wide subgoal and 4 actions, the top level with the 3-wide
//! end goal proposing 7-wide subgoals), the pendulum-like level on two threads, and one greedy
//! single-sample action. Target: an update within 2.1 ms on one core of the project's 2-core
//! machine (docs/RESULTS.md); `crates/nn/benches/pytorch_update.py` times the same update in
//! PyTorch.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use hac_core::{Batch, Bounds, LevelDims, Rng};
use hac_nn::{LearnerConfig, LevelLearner};

const BATCH: usize = 1024;

fn config(action: usize) -> LearnerConfig {
    config_of(LevelDims {
        state: 3,
        goal: 2,
        action,
    })
}

fn config_of(dims: LevelDims) -> LearnerConfig {
    let action = dims.action;
    LearnerConfig {
        dims,
        action_bounds: Bounds::symmetric(&vec![2.0; action]),
        horizon: 20.0,
        gamma: 0.98,
        hidden: vec![64, 64, 64],
        actor_lr: 1e-3,
        critic_lr: 1e-3,
        target_tau: None,
        actor_preactivation_l2: 0.0,
        exact_critic_slope: false,
        saturating_tanh: false,
    }
}

fn batch(dims: LevelDims, rng: &mut Rng) -> Batch {
    let mut b = Batch::zeros(dims, BATCH);
    let fields = [
        &mut b.states,
        &mut b.next_states,
        &mut b.goals,
        &mut b.actions,
    ];
    for field in fields {
        field.iter_mut().for_each(|v| *v = rng.uniform(-1.0, 1.0));
    }
    for (r, t) in b.rewards.iter_mut().zip(&mut b.terminals) {
        let reached = rng.bernoulli(0.2);
        (*r, *t) = if reached { (0.0, 1.0) } else { (-1.0, 0.0) };
    }
    b
}

fn update(c: &mut Criterion) {
    let mut group = c.benchmark_group("update");
    for action in [1, 2] {
        let mut rng = Rng::seed_from(1);
        let mut learner = LevelLearner::new(config(action), &mut rng);
        let batch = batch(learner.config().dims, &mut rng);
        group.bench_function(
            format!("batch1024_h64x3_state3_goal2_action{action}"),
            |b| b.iter(|| black_box(learner.update(black_box(&batch)))),
        );
    }
    // The same level's update shared among two threads (the caller's and one worker); the
    // weights are the same as on one.
    {
        let mut rng = Rng::seed_from(1);
        let mut learner = LevelLearner::new(config(1), &mut rng);
        learner.set_threads(2);
        let batch = batch(learner.config().dims, &mut rng);
        group.bench_function("batch1024_h64x3_state3_goal2_action1_threads2", |b| {
            b.iter(|| black_box(learner.update(black_box(&batch))))
        });
    }
    for (name, dims) in [
        (
            "level0",
            LevelDims {
                state: 20,
                goal: 7,
                action: 4,
            },
        ),
        (
            "top",
            LevelDims {
                state: 20,
                goal: 3,
                action: 7,
            },
        ),
    ] {
        let mut rng = Rng::seed_from(1);
        let mut learner = LevelLearner::new(config_of(dims), &mut rng);
        let batch = batch(dims, &mut rng);
        group.bench_function(format!("batch1024_h64x3_pick_and_place_{name}"), |b| {
            b.iter(|| black_box(learner.update(black_box(&batch))))
        });
    }
    group.finish();
}

fn act(c: &mut Criterion) {
    // Rollouts hold a copy of the actor, as here.
    let mut actor = LevelLearner::new(config(1), &mut Rng::seed_from(2))
        .actor()
        .clone();
    let (state, goal) = ([0.1, -0.2, 0.3], [0.5, -0.5]);
    let mut out = [0.0];
    c.bench_function("act/h64x3_state3_goal2_action1", |b| {
        b.iter(|| {
            actor.act(black_box(&state), black_box(&goal), &mut out);
            black_box(out[0])
        })
    });
}

criterion_group!(benches, update, act);
criterion_main!(benches);
