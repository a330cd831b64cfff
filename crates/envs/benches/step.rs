//! `Env::step` of every registered environment, through the registry's `Box<dyn Env>` as the
//! rollout calls it. One iteration is one primitive action (all its physics steps).

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use hac_core::Rng;

fn step(c: &mut Criterion) {
    for name in hac_envs::names() {
        let mut env = hac_envs::make(name).unwrap();
        env.reset(&mut Rng::seed_from(0));
        let high = env.spec().action_bounds.high[0];
        // Alternate full pushes so the state keeps moving through its whole range.
        let mut sign = 1.0;
        c.bench_function(&format!("{name}/step"), |b| {
            b.iter(|| {
                sign = -sign;
                env.step(black_box(&[sign * high]));
                black_box(env.state()[0])
            })
        });
    }
}

criterion_group!(benches, step);
criterion_main!(benches);
