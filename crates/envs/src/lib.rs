//! HAC built-in environments: pure-Rust dynamics that describe themselves completely through
//! [`hac_core::Env`] (spaces, projections, goal distributions, default hyperparameters).
//!
//! - [`pendulum`]: the paper's inverted-pendulum swing-up, integrated directly from its rigid-body
//!   model (what the reference simulated in MuJoCo).
//! - [`ur5`]: the paper's three-joint UR5 reacher, a serial chain integrated with rigid-body
//!   dynamics (composite rigid body + recursive Newton-Euler).
//! - [`cartpole`]: a cart-pole swing-up (cart on a free slider, uniform rod on a hinge), the
//!   two-body model integrated directly from its Lagrangian equations of motion.
//! - [`mountain_car`]: the continuous mountain car with the PyTorch port's settings as its preset.
//! - [`pick_and_place`]: a two-finger gripper picks a block up and puts it at a goal, with contact
//!   and friction simulated by rapier3d.
//! - This file: the registry ([`make`], [`names`]) and what the environments share: the error for
//!   a bad physical state, angle wrapping, and the horizon rule for deep hierarchies.
//!
//! Every environment is deterministic for a seed (all randomness comes from the [`hac_core::Rng`]
//! passed to `reset`), and `step` allocates nothing (pick-and-place: nothing beyond what rapier's
//! step itself does in the buffers it reuses). Each one also offers a constructor with physics
//! overrides (for tests) and implements `Env::set_physical_state` (for tools that start from a
//! chosen state).

#![forbid(unsafe_code)]

pub mod cartpole;
pub mod mountain_car;
pub mod pendulum;
pub mod pick_and_place;
pub mod ur5;

use std::f64::consts::{PI, TAU};

use hac_core::Env;

pub use cartpole::{CartPole, CartPolePhysics};
pub use mountain_car::{MountainCar, MountainCarPhysics};
pub use pendulum::{Pendulum, PendulumPhysics};
pub use pick_and_place::{PickAndPlace, PickAndPlacePhysics};
pub use ur5::{Ur5Physics, Ur5Reacher};

/// Names accepted by [`make`], in the order tools should list them.
pub fn names() -> &'static [&'static str] {
    &[
        Pendulum::NAME,
        Ur5Reacher::NAME,
        MountainCar::NAME,
        CartPole::NAME,
        PickAndPlace::NAME,
    ]
}

/// A fresh environment with its standard physics, by registry name.
pub fn make(name: &str) -> Result<Box<dyn Env>, UnknownEnv> {
    match name {
        Pendulum::NAME => Ok(Box::new(Pendulum::new())),
        Ur5Reacher::NAME => Ok(Box::new(Ur5Reacher::new())),
        MountainCar::NAME => Ok(Box::new(MountainCar::new())),
        CartPole::NAME => Ok(Box::new(CartPole::new())),
        PickAndPlace::NAME => Ok(Box::new(PickAndPlace::new())),
        _ => Err(UnknownEnv {
            name: name.to_string(),
        }),
    }
}

/// A name [`make`] does not know; the message lists the known ones.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown environment `{name}` (known: {})", names().join(", "))]
pub struct UnknownEnv {
    pub name: String,
}

/// A task's H for `levels` levels: the whole episode budget for the flat agent, the task's own
/// `two` and `three` for 2 and 3 levels, and for deeper hierarchies the smallest H whose
/// `H^levels` covers the budget. A run's own budget moves the flat H and the deeper ones, not
/// the task's stated two.
fn stated_horizon(levels: usize, max_actions: usize, [two, three]: [usize; 2]) -> usize {
    match levels {
        1 => max_actions,
        2 => two,
        3 => three,
        k => hac_core::horizon_covering(max_actions, k),
    }
}

/// A physical state that `set_physical_state` refuses (defined in core, beside the trait).
pub use hac_core::StateError;

/// Checks a physical state's length and per-value ranges (`ranges[i] = (low, high)`).
fn check_physical_state(
    env: &'static str,
    values: &[f64],
    ranges: &[(f64, f64)],
) -> Result<(), StateError> {
    if values.len() != ranges.len() {
        return Err(StateError::WrongLength {
            env,
            expected: ranges.len(),
            got: values.len(),
        });
    }
    for (index, (&value, &(low, high))) in values.iter().zip(ranges).enumerate() {
        if !(low..=high).contains(&value) {
            return Err(StateError::OutOfRange {
                env,
                index,
                value,
                low,
                high,
            });
        }
    }
    Ok(())
}

/// Wraps an angle into (-pi, pi], the convention of every angle in states and goals.
fn wrap_angle(a: f64) -> f64 {
    // Integration moves an angle by far less than a turn per step, so the common case is a
    // comparison, not a division.
    if a > -PI && a <= PI {
        return a;
    }
    let r = a.rem_euclid(TAU);
    if r > PI { r - TAU } else { r }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Largest `|value| / bound` of a state dimension over `episodes` episodes of bang-bang or
    /// uniform random control, per dimension; checks every observation, end goal and
    /// projection against the spec's boxes on the way.
    fn explore_bounds(name: &str, episodes: u64) -> Vec<f32> {
        let mut env = make(name).unwrap();
        let spec = env.spec().clone();
        let (mut end_goal, mut subgoal) =
            (vec![0.0; spec.end_goal_dim], vec![0.0; spec.subgoal_dim()]);
        let mut action = vec![0.0; spec.action_dim()];
        let mut peak = vec![0f32; spec.state_dim];
        for seed in 0..episodes {
            let mut rng = hac_core::Rng::seed_from(seed);
            env.reset(&mut rng);
            env.sample_end_goal(&mut rng, hac_core::Mode::Train, &mut end_goal);
            assert!(
                spec.end_goal_bounds.contains(&end_goal),
                "{name}: {end_goal:?}"
            );
            let bang_bang = seed % 2 == 0;
            // Bang-bang controls hold each extreme for a while, which is what spins things up.
            let hold = 1 + (seed as usize % 7) * 5;
            for t in 0..spec.max_actions {
                if t % hold == 0 {
                    for (d, a) in action.iter_mut().enumerate() {
                        let (lo, hi) = (spec.action_bounds.low[d], spec.action_bounds.high[d]);
                        *a = if bang_bang {
                            if rng.bernoulli(0.5) { lo } else { hi }
                        } else {
                            rng.uniform(lo, hi)
                        };
                    }
                }
                env.step(&action);
                let state = env.state();
                assert!(
                    spec.state_bounds.contains(state),
                    "{name} seed {seed} step {t}: {state:?} outside {:?}",
                    spec.state_bounds
                );
                for (d, p) in peak.iter_mut().enumerate() {
                    *p = p.max(state[d].abs() / spec.state_bounds.high[d].abs());
                }
                env.project_end_goal(state, &mut end_goal);
                assert!(
                    spec.end_goal_bounds.contains(&end_goal),
                    "{name}: {end_goal:?}"
                );
                env.project_subgoal(state, &mut subgoal);
                assert!(
                    spec.achieved_subgoal_bounds.contains(&subgoal),
                    "{name}: {subgoal:?}"
                );
                if env.terminated() {
                    break;
                }
            }
        }
        peak
    }

    #[test]
    fn episodes_stay_inside_the_specs_boxes() {
        for name in names() {
            let spec = make(name).unwrap().spec().clone();
            assert_eq!(spec.state_bounds.dim(), spec.state_dim, "{name}");
            assert_eq!(spec.end_goal_bounds.dim(), spec.end_goal_dim, "{name}");
            assert_eq!(
                spec.achieved_subgoal_bounds.dim(),
                spec.subgoal_dim(),
                "{name}"
            );
            explore_bounds(name, 6);
        }
    }

    #[test]
    fn ur5_joint_speeds_stay_far_below_their_bound() {
        // The bound is 50 rad/s; the documented claim is that random control stays below 15.
        let peak = explore_bounds(Ur5Reacher::NAME, 10);
        for (d, p) in peak[3..].iter().enumerate() {
            assert!(p * 50.0 < 15.0, "joint {d}: {} rad/s", p * 50.0);
        }
    }

    #[test]
    fn registry_makes_every_listed_env_under_its_name() {
        for name in names() {
            let env = make(name).unwrap();
            assert_eq!(env.spec().name, *name);
        }
    }

    #[test]
    fn unknown_name_lists_the_known_ones() {
        let err = make("acrobot").err().unwrap();
        assert_eq!(err.name, "acrobot");
        let msg = err.to_string();
        for name in names() {
            assert!(msg.contains(name), "{msg}");
        }
    }

    #[test]
    fn default_configs_validate_for_every_level_count() {
        for name in names() {
            let env = make(name).unwrap();
            let spec = env.spec();
            for levels in 1..=8 {
                let config = env.default_config(levels);
                assert_eq!(config.levels, levels);
                config
                    .validate(spec.action_dim(), spec.subgoal_dim())
                    .unwrap_or_else(|e| panic!("{name} with {levels} levels: {e}"));
            }
        }
    }

    #[test]
    fn wrap_angle_lands_in_half_open_interval() {
        assert_eq!(wrap_angle(PI), PI);
        assert_eq!(wrap_angle(-PI), PI);
        assert_eq!(wrap_angle(0.5), 0.5);
        assert!((wrap_angle(3.0 * PI + 0.25) - (-PI + 0.25)).abs() < 1e-12);
        assert!((wrap_angle(-7.0 * PI - 0.25) - (PI - 0.25)).abs() < 1e-12);
        for i in -1000..1000 {
            let w = wrap_angle(f64::from(i) * 0.037);
            assert!(w > -PI && w <= PI, "{w}");
        }
    }

    #[test]
    fn state_check_rejects_length_range_and_nan() {
        let ranges = [(-1.0, 1.0), (f64::NEG_INFINITY, f64::INFINITY)];
        assert!(check_physical_state("t", &[0.0, 5.0], &ranges).is_ok());
        assert!(matches!(
            check_physical_state("t", &[0.0], &ranges),
            Err(StateError::WrongLength {
                expected: 2,
                got: 1,
                ..
            })
        ));
        assert!(matches!(
            check_physical_state("t", &[2.0, 0.0], &ranges),
            Err(StateError::OutOfRange { index: 0, .. })
        ));
        assert!(matches!(
            check_physical_state("t", &[0.0, f64::NAN], &ranges),
            Err(StateError::OutOfRange { index: 1, .. })
        ));
    }
}
