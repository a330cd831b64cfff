//! `Env::step` of every registered environment, through the registry's `Box<dyn Env>` as the
//! rollout calls it. One iteration is one primitive action (all its physics steps). For the UR5
//! arm, also one evaluation of its dynamics (what each of its 15 physics steps costs). For
//! pick-and-place, also whole scripted episodes (reset, goal, grasp, carry, hold: the contacts a
//! rollout meets), timed per action.

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use hac_core::{Env, Mode, Rng};
use hac_envs::PickAndPlace;
use hac_envs::pick_and_place::ScriptedGrasp;
use hac_envs::ur5::Ur5Arm;
use nalgebra::Vector3;

fn step(c: &mut Criterion) {
    for name in hac_envs::names() {
        let mut env = hac_envs::make(name).unwrap();
        env.reset(&mut Rng::seed_from(0));
        let high = env.spec().action_bounds.high.clone();
        let mut action = high.clone();
        // Alternate full pushes so the state keeps moving through its whole range.
        let mut sign = 1.0;
        c.bench_function(&format!("{name}/step"), |b| {
            b.iter(|| {
                sign = -sign;
                for (a, h) in action.iter_mut().zip(&high) {
                    *a = sign * h;
                }
                env.step(black_box(&action));
                black_box(env.state()[0])
            })
        });
    }
}

/// Forward kinematics, mass matrix, inverse dynamics and the Cholesky solve of one UR5 physics
/// step, at a moving configuration.
fn ur5_dynamics(c: &mut Criterion) {
    let arm = Ur5Arm::new(9.81);
    let q = Vector3::new(0.7, -0.4, 0.3);
    let qd = Vector3::new(1.0, -2.0, 1.5);
    let tau = Vector3::new(5.0, -20.0, 3.0);
    c.bench_function("ur5-reacher/forward-dynamics", |b| {
        b.iter(|| {
            let pose = arm.pose(black_box(&q));
            arm.forward_dynamics(&pose, black_box(&qd), black_box(&tau))
        })
    });
}

/// Scripted pick-and-place episodes of 60 actions (the grasp, the carry and a hold), timed per
/// action; resets and goal draws are included.
fn pick_and_place_episodes(c: &mut Criterion) {
    const ACTIONS: u64 = 60;
    let mut env = PickAndPlace::new();
    let mut rng = Rng::seed_from(0);
    let mut goal = [0.0f32; 3];
    c.bench_function("pick-and-place/scripted-action", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            let mut done = 0;
            while done < iters {
                let start = Instant::now();
                env.reset(&mut rng);
                env.sample_end_goal(&mut rng, Mode::Train, &mut goal);
                let mut script = ScriptedGrasp::new();
                for _ in 0..ACTIONS {
                    let a = script.act(env.state(), &goal);
                    env.step(black_box(&a));
                }
                total += start.elapsed();
                done += ACTIONS;
            }
            // Time per `iters` actions, whatever the last episode overshot.
            total.mul_f64(iters as f64 / done as f64)
        })
    });
}

criterion_group!(benches, step, ur5_dynamics, pick_and_place_episodes);
criterion_main!(benches);
