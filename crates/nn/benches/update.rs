//! One full learner update (critic step + actor step) at the reference batch size and network
//! (batch 1024, hidden [64, 64, 64]) for pendulum-like levels and for pick-and-place's widest
//! levels (state 20; level 0 with a 7-wide subgoal and 4 actions, the top level with the 3-wide
//! end goal proposing 7-wide subgoals), the pendulum-like level on two threads, and one greedy
//! single-sample action, and one Adam step over a level's parameters (actor and critic, about
//! 17,600), with ordinary moments and with a dead unit's (decayed to where the plain formula
//! produces subnormal floats), against that plain formula. Target: an update within 2.1 ms on
//! one core of the project's 2-core machine (docs/RESULTS.md);
//! `crates/nn/benches/pytorch_update.py` times the same update in PyTorch.

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

/// Adam's plain formula in `f32` (`m`, `v` and the parameter in that order, every product
/// computed), one step at step count `t`: what `hac_nn::Adam` computed before it skipped the
/// products whose result would be subnormal, for comparison. It runs at the build's baseline
/// (SSE2) where `hac_nn::Adam` picks AVX2 or AVX-512 at run time, so compare each with itself
/// between ordinary and zero gradients.
fn plain_adam_step(t: u64, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]) {
    use hac_nn::adam::{BETA1 as b1, BETA2 as b2, EPSILON as eps};
    let lr = 1e-3f64;
    let step_size = (lr / (1.0 - f64::from(b1).powf(t as f64))) as f32;
    let inv_sqrt_bias2 = (1.0 / (1.0 - f64::from(b2).powf(t as f64)).sqrt()) as f32;
    for (((p, &g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
        *m = b1 * *m + (1.0 - b1) * g;
        *v = b2 * *v + (1.0 - b2) * g * g;
        *p -= step_size * *m / (v.sqrt() * inv_sqrt_bias2 + eps);
    }
}

/// One Adam step over about as many parameters as a pendulum-sized level's actor and critic
/// together (17,600), `hac_nn::Adam`'s and the plain formula's, after a first gradient and then
/// gradients of `scale` times it for `warm_steps` steps. With a scale of 0 (a dead unit's
/// weights) the first moments decay into the subnormal range within 1000 steps, and under the
/// plain formula stay there (0.9 times a few subnormal units rounds back to the same value).
fn adam(c: &mut Criterion) {
    let n = 17_600;
    let mut group = c.benchmark_group("adam");
    for (name, scale, warm_steps) in [
        ("ordinary_gradients", 1.0f32, 10u64),
        ("gradients_zero_for_1000_steps", 0.0, 1000),
    ] {
        let start: Vec<f32> = (0..n).map(|i| ((i % 97) as f32 - 48.0) * 0.01).collect();
        let first: Vec<f32> = (0..n).map(|i| ((i % 13) as f32 - 6.0) * 1e-3).collect();
        let g: Vec<f32> = first.iter().map(|x| x * scale).collect();

        let mut p = start.clone();
        let mut opt = hac_nn::Adam::new(1e-3, [n]);
        opt.step([(&mut p[..], &first[..])]);
        for _ in 0..warm_steps {
            opt.step([(&mut p[..], &g[..])]);
        }
        group.bench_function(format!("params17600_{name}"), |b| {
            b.iter(|| opt.step([(black_box(&mut p[..]), black_box(&g[..]))]))
        });

        let (mut p, mut m, mut v) = (start, vec![0.0; n], vec![0.0; n]);
        let mut t = 1;
        plain_adam_step(t, &mut p, &first, &mut m, &mut v);
        for _ in 0..warm_steps {
            t += 1;
            plain_adam_step(t, &mut p, &g, &mut m, &mut v);
        }
        group.bench_function(format!("params17600_{name}_plain_formula"), |b| {
            b.iter(|| {
                t += 1;
                plain_adam_step(t, black_box(&mut p[..]), black_box(&g[..]), &mut m, &mut v)
            })
        });
    }
}

criterion_group!(benches, update, act, adam);
criterion_main!(benches);
