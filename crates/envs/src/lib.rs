//! HAC built-in environments: pure-Rust dynamics that describe themselves completely through
//! [`hac_core::Env`] (spaces, projections, goal distributions, default hyperparameters).
//!
//! - [`pendulum`]: the paper's inverted-pendulum swing-up, integrated directly from its rigid-body
//!   model (what the reference simulated in MuJoCo).
//! - [`ur5`]: the paper's three-joint UR5 reacher, a serial chain integrated with rigid-body
//!   dynamics (composite rigid body + recursive Newton-Euler).
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

pub mod mountain_car;
pub mod pendulum;
pub mod pick_and_place;
pub mod ur5;

use std::f64::consts::{PI, TAU};

use hac_core::Env;

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
        PickAndPlace::NAME,
    ]
}

/// A fresh environment with its standard physics, by registry name.
pub fn make(name: &str) -> Result<Box<dyn Env>, UnknownEnv> {
    match name {
        Pendulum::NAME => Ok(Box::new(Pendulum::new())),
        Ur5Reacher::NAME => Ok(Box::new(Ur5Reacher::new())),
        MountainCar::NAME => Ok(Box::new(MountainCar::new())),
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

    #[test]
    fn registry_makes_every_listed_env_under_its_name() {
        for name in names() {
            let env = make(name).unwrap();
            assert_eq!(env.spec().name, *name);
        }
    }

    #[test]
    fn unknown_name_lists_the_known_ones() {
        let err = make("cartpole").err().unwrap();
        assert_eq!(err.name, "cartpole");
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
