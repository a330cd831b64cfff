//! HIRO's off-policy correction of one high-level minibatch in batched forward passes
//! ([`BatchedCorrection::relabel`]) at the reference scale: 100 transitions of `c = 10`
//! low-level steps, 10 candidates each (the stored goal, the achieved displacement and 8 random
//! draws), so 10,000 evaluations of a low-level actor with hidden layers [64, 64, 64]; for
//! pendulum-like dimensions (state 2, goal 2, action 1) and UR5-like ones (state 6, goal 6,
//! action 3). Beside each, the same correction one transition at a time
//! ([`OffPolicyCorrection::relabel`] with [`ActorNet::act`]) for comparison.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use hac_core::hiro::{LowLevelSteps, OffPolicyCorrection};
use hac_core::{Bounds, LevelDims, Rng};
use hac_nn::{ActorNet, BatchedCorrection};

const TRANSITIONS: usize = 100;
const C: usize = 10;
const RANDOM_CANDIDATES: usize = 8;

/// One transition's steps: `C` states, `C + 1` projections, `C` actions.
struct Steps {
    states: Vec<f32>,
    achieved: Vec<f32>,
    actions: Vec<f32>,
}

fn uniform(rng: &mut Rng, len: usize) -> Vec<f32> {
    (0..len).map(|_| rng.uniform(-1.0, 1.0)).collect()
}

fn correction(c: &mut Criterion) {
    let mut group = c.benchmark_group("correction");
    for (name, dims) in [
        (
            "pendulum_state2_goal2_action1",
            LevelDims {
                state: 2,
                goal: 2,
                action: 1,
            },
        ),
        (
            "ur5_state6_goal6_action3",
            LevelDims {
                state: 6,
                goal: 6,
                action: 3,
            },
        ),
    ] {
        let mut rng = Rng::seed_from(1);
        let bounds = Bounds::symmetric(&vec![1.0; dims.action]);
        let actor = ActorNet::new(dims, &bounds, &[64, 64, 64], &mut rng);
        let steps: Vec<Steps> = (0..TRANSITIONS)
            .map(|_| Steps {
                states: uniform(&mut rng, C * dims.state),
                achieved: uniform(&mut rng, (C + 1) * dims.goal),
                actions: uniform(&mut rng, C * dims.action),
            })
            .collect();
        let stored = uniform(&mut rng, TRANSITIONS * dims.goal);
        let mut goals = stored.clone();
        let mut batched =
            BatchedCorrection::new(RANDOM_CANDIDATES, vec![1.0; dims.goal], Vec::new());
        group.bench_function(format!("n100_c10_candidates10_h64x3_{name}"), |b| {
            b.iter(|| {
                goals.copy_from_slice(&stored);
                let view = steps.iter().map(|s| LowLevelSteps {
                    states: &s.states,
                    achieved: &s.achieved,
                    actions: &s.actions,
                });
                black_box(batched.relabel(&actor, &mut goals, view, &mut rng))
            })
        });
        let mut single = OffPolicyCorrection::new(RANDOM_CANDIDATES);
        let mut policy_actor = actor.clone();
        let mut policy = |s: &[f32], g: &[f32], a: &mut [f32]| policy_actor.act(s, g, a);
        let half_range = vec![1.0; dims.goal];
        let mut out = vec![0.0; dims.goal];
        group.bench_function(
            format!("per_sample_n100_c10_candidates10_h64x3_{name}"),
            |b| {
                b.iter(|| {
                    let mut changed = 0;
                    for (t, s) in steps.iter().enumerate() {
                        let view = LowLevelSteps {
                            states: &s.states,
                            achieved: &s.achieved,
                            actions: &s.actions,
                        };
                        let stored = &stored[t * dims.goal..(t + 1) * dims.goal];
                        let index = single.relabel(
                            stored,
                            view,
                            &half_range,
                            &[],
                            &mut rng,
                            &mut policy,
                            &mut out,
                        );
                        changed += usize::from(index != 0);
                    }
                    black_box(changed)
                })
            },
        );
    }
    group.finish();
}

criterion_group!(benches, correction);
criterion_main!(benches);
