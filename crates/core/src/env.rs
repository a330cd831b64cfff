//! What an environment is to HAC: its spaces, projections, goal distributions and dynamics.

use serde::{Deserialize, Serialize};

use crate::{AgentConfig, Bounds, Rng};

/// Training episodes draw from the training end-goal distribution and explore; test episodes use
/// the test distribution and act greedily.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    Train,
    Test,
}

/// Everything static an environment says about itself (docs/ENVIRONMENTS.md lists each task's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EnvSpec {
    /// Registry name, e.g. `pendulum`.
    pub name: String,
    /// One-line human description.
    pub description: String,
    /// Dimension of the observed state vector.
    pub state_dim: usize,
    /// Bounds of the primitive action (level 0's output).
    pub action_bounds: Bounds,
    /// Dimension of the end-goal space (the top level's goal).
    pub end_goal_dim: usize,
    /// Per-dimension threshold for reaching an end goal.
    pub end_goal_thresholds: Vec<f32>,
    /// Bounds of the subgoal space (the output of every level above 0).
    pub subgoal_bounds: Bounds,
    /// Per-dimension threshold for reaching a subgoal.
    pub subgoal_thresholds: Vec<f32>,
    /// End-goal dimensions that are angles in radians, compared along the circle (see
    /// [`crate::within_goal`]); empty when none is.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub end_goal_angles: Vec<bool>,
    /// Subgoal dimensions that are angles in radians, compared along the circle; empty when none
    /// is.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub subgoal_angles: Vec<bool>,
    /// Subgoal dimensions that the projection wraps to (-pi, pi] (angles in radians) but that
    /// the goal test compares as plain numbers (not in `subgoal_angles`; the pendulum's angle,
    /// as in the reference's goal test). Differences of two projections, HIRO's relative goals,
    /// are still taken along the circle on them ([`EnvSpec::relative_goal_angles`]). Empty when
    /// none is.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub subgoal_wrapped: Vec<bool>,
    /// A box that every observation of an episode started by `reset` stays in (each
    /// environment derives its own). Not used by the agent: transitions that come from outside
    /// the process (an actor's batches) are checked against it ([`crate::TransitionLimits`]).
    /// Empty: unknown, nothing is checked.
    #[serde(default, skip_serializing_if = "Bounds::is_empty")]
    pub state_bounds: Bounds,
    /// A box that holds every end goal the environment draws and every end-goal projection of
    /// a state in `state_bounds`. Empty: unknown.
    #[serde(default, skip_serializing_if = "Bounds::is_empty")]
    pub end_goal_bounds: Bounds,
    /// A box that holds every subgoal projection of a state in `state_bounds` (a hindsight
    /// subgoal). It stays the environment's own when a run replaces `subgoal_bounds`. Empty:
    /// unknown.
    #[serde(default, skip_serializing_if = "Bounds::is_empty")]
    pub achieved_subgoal_bounds: Bounds,
    /// Episode budget in primitive actions.
    pub max_actions: usize,
    /// Physics integration steps per primitive action.
    pub physics_steps_per_action: usize,
}

impl EnvSpec {
    pub fn action_dim(&self) -> usize {
        self.action_bounds.dim()
    }

    pub fn subgoal_dim(&self) -> usize {
        self.subgoal_bounds.dim()
    }

    /// Input/output dimensions of level `level` in a hierarchy of `levels` levels.
    pub fn level_dims(&self, level: usize, levels: usize) -> LevelDims {
        debug_assert!(level < levels);
        LevelDims {
            state: self.state_dim,
            goal: if level + 1 == levels {
                self.end_goal_dim
            } else {
                self.subgoal_dim()
            },
            action: if level == 0 {
                self.action_dim()
            } else {
                self.subgoal_dim()
            },
        }
    }

    /// The goal test of the top level (`end_goal`) or of a level below it: per-dimension
    /// thresholds and angle flags, as [`crate::within_goal`] takes them.
    pub fn goal_test(&self, end_goal: bool) -> (&[f32], &[bool]) {
        if end_goal {
            (&self.end_goal_thresholds, &self.end_goal_angles)
        } else {
            (&self.subgoal_thresholds, &self.subgoal_angles)
        }
    }

    /// The subgoal dimensions on which differences of two projections (HIRO's relative goals,
    /// goal transition and intrinsic reward) are wrapped to `[-pi, pi]`: those of
    /// `subgoal_angles` and of `subgoal_wrapped`. Empty when none is.
    pub fn relative_goal_angles(&self) -> Vec<bool> {
        let dims = self.subgoal_angles.len().max(self.subgoal_wrapped.len());
        let flag = |flags: &[bool], d: usize| flags.get(d).copied().unwrap_or(false);
        let angles: Vec<bool> = (0..dims)
            .map(|d| flag(&self.subgoal_angles, d) || flag(&self.subgoal_wrapped, d))
            .collect();
        if angles.contains(&true) {
            angles
        } else {
            Vec::new()
        }
    }

    /// The bounds of level `level`'s output.
    pub fn level_action_bounds(&self, level: usize) -> &Bounds {
        if level == 0 {
            &self.action_bounds
        } else {
            &self.subgoal_bounds
        }
    }
}

/// The smallest H with `H^levels >= max_actions`, i.e. `ceil(max_actions^(1/levels))` computed
/// exactly: the horizon at which the top level's H attempts can just cover the episode budget
/// (the rule that gives the paper's pendulum H = 1000 / 32 / 10). Environments use it for the
/// level counts a task gives no H for, the grid worlds for all.
pub fn horizon_covering(max_actions: usize, levels: usize) -> usize {
    let levels = u32::try_from(levels.max(1)).unwrap_or(u32::MAX);
    (1..max_actions)
        .find(|h| h.checked_pow(levels).is_none_or(|p| p >= max_actions))
        .unwrap_or(max_actions)
}

/// Sizes of one level's inputs and outputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct LevelDims {
    pub state: usize,
    pub goal: usize,
    pub action: usize,
}

/// A built-in environment. Deterministic for a given seed: all randomness comes from the `Rng`
/// passed in. `step` must not allocate (it is the hottest loop of the system).
pub trait Env: Send + std::fmt::Debug {
    fn spec(&self) -> &EnvSpec;

    /// Sets the episode budget, `spec().max_actions` (a run's `max_actions` key); where the
    /// environment derives an H from the budget, [`Env::default_config`] follows it. Callers
    /// pass at least 1.
    fn set_max_actions(&mut self, max_actions: usize);

    /// Replaces the subgoal bounds, `spec().subgoal_bounds` (a run's `subgoal_bounds` key): the
    /// box the actors of levels above 0 output in, which also scales their relative noise and
    /// bounds their random subgoals. Callers pass `spec().subgoal_dim()` dimensions.
    fn set_subgoal_bounds(&mut self, bounds: Bounds);

    /// The recommended hyperparameters for a hierarchy of `levels` levels (docs/ENVIRONMENTS.md).
    fn default_config(&self, levels: usize) -> AgentConfig;

    /// Draws an initial state from the initial-state distribution.
    fn reset(&mut self, rng: &mut Rng);

    /// The current observation (`spec().state_dim` values).
    fn state(&self) -> &[f32];

    /// Applies one primitive action (clipped to the action bounds by the caller) for
    /// `physics_steps_per_action` integration steps.
    fn step(&mut self, action: &[f32]);

    /// Whether the environment itself ended the episode (most tasks never do).
    fn terminated(&self) -> bool {
        false
    }

    /// Projects a state into the end-goal space.
    fn project_end_goal(&self, state: &[f32], out: &mut [f32]);

    /// Projects a state into the subgoal space; the result must lie in `subgoal_bounds`.
    fn project_subgoal(&self, state: &[f32], out: &mut [f32]);

    /// Draws an end goal from the training or test distribution.
    fn sample_end_goal(&self, rng: &mut Rng, mode: Mode, out: &mut [f32]);

    /// Puts the environment into a chosen physical state (for tools and tests; each environment
    /// documents its layout, e.g. pendulum `[q, qdot]`). f64 so that values such as a threshold
    /// position are represented exactly.
    fn set_physical_state(&mut self, state: &[f64]) -> Result<(), StateError> {
        let _ = state;
        Err(StateError::Unsupported {
            env: "this environment",
        })
    }
}

/// A physical state that `Env::set_physical_state` refuses.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StateError {
    #[error("{env} physical state needs {expected} values, got {got}")]
    WrongLength {
        env: &'static str,
        expected: usize,
        got: usize,
    },
    /// Also covers NaN, which lies in no range.
    #[error("{env} physical state value {index} is {value}, outside [{low}, {high}]")]
    OutOfRange {
        env: &'static str,
        index: usize,
        value: f64,
        low: f64,
        high: f64,
    },
    #[error("{env} cannot be set to a physical state")]
    Unsupported { env: &'static str },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn horizon_covering_is_exact_ceil_root() {
        assert_eq!(horizon_covering(1000, 1), 1000);
        assert_eq!(horizon_covering(1000, 2), 32);
        assert_eq!(horizon_covering(1000, 3), 10);
        assert_eq!(horizon_covering(1000, 4), 6);
        assert_eq!(horizon_covering(1000, 5), 4);
        assert_eq!(horizon_covering(1000, 8), 3);
        assert_eq!(horizon_covering(1000, 0), 1000);
        assert_eq!(horizon_covering(60, 2), 8);
        assert_eq!(horizon_covering(60, 3), 4);
    }
}
