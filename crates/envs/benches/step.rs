//! `Env::step` of every registered environment, through the registry's `Box<dyn Env>` as the
//! rollout calls it. One iteration is one primitive action (all its physics steps). For the UR5
//! arm, also one evaluation of its dynamics (what each of its 15 physics steps costs).

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use hac_core::Rng;
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

criterion_group!(benches, step, ur5_dynamics);
criterion_main!(benches);
