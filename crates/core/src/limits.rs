//! What a level's transitions can hold, for admitting transitions that come from outside the
//! process (an actor's batches).
//!
//! Shape checks (lengths, finite values, 0/1 terminals) are not enough: a batch of finite but
//! absurd values (3e38 everywhere) passes them and overflows the first forward pass, and every
//! weight it touches becomes NaN. [`TransitionLimits`] checks what the values mean instead:
//!
//! - states and next states lie in the environment's `state_bounds`;
//! - goals lie in the level's goal space: `end_goal_bounds` at the top level, below it the
//!   subgoal space (`subgoal_bounds`, the proposing level's output range, joined with
//!   `achieved_subgoal_bounds`, where hindsight subgoals come from);
//! - actions lie in the level's action space: `action_bounds` at level 0, the subgoal space
//!   above;
//! - rewards are ones the level can produce: `0` (goal reached), `-1` (missed) or `-H` (a
//!   subgoal-testing penalty), HAC's three values.
//!
//! Every box is widened by [`MARGIN`] of its width on each side (plus a hair for rounding), so
//! an honest actor whose physics differs in the last bits is never refused. A box the
//! environment leaves empty (unknown) is not checked.

use crate::{BatchRef, Bounds, EnvSpec};

/// How far outside a box a value may lie, as a fraction of the box's width on each side.
pub const MARGIN: f32 = 0.1;

/// Added to the margin on each side: absorbs rounding at boxes of zero width.
const ROUNDING: f32 = 1e-4;

/// The admissible values of one level's transitions.
#[derive(Debug, Clone, PartialEq)]
pub struct TransitionLimits {
    state: Bounds,
    goal: Bounds,
    action: Bounds,
    rewards: [f32; 3],
}

/// A value outside what the level can produce. The message names the field and the index in
/// the batch's flat array, as the shape errors do.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LimitError {
    #[error(
        "batch.{field}[{index}] = {value:e} is outside [{low}, {high}], the admissible range of \
         {what} dimension {dim} (its box with a {margin}% margin)",
        what = field_meaning(field),
        margin = MARGIN * 100.0
    )]
    OutOfBounds {
        field: &'static str,
        index: usize,
        dim: usize,
        value: f32,
        low: f32,
        high: f32,
    },
    #[error(
        "batch.rewards[{index}] = {value:e} is not a reward this level produces (0, -1 or \
         {penalty})"
    )]
    Reward {
        index: usize,
        value: f32,
        penalty: f32,
    },
}

fn field_meaning(field: &str) -> &'static str {
    match field {
        "states" | "next_states" => "state",
        "goals" => "goal",
        _ => "action",
    }
}

impl TransitionLimits {
    /// The limits of level `level` of `levels` under `spec`, whose penalty is `-horizon`.
    pub fn for_level(spec: &EnvSpec, level: usize, levels: usize, horizon: f32) -> Self {
        let subgoals = if spec.achieved_subgoal_bounds.is_empty() {
            spec.subgoal_bounds.clone()
        } else {
            spec.subgoal_bounds.hull(&spec.achieved_subgoal_bounds)
        };
        let goal = if level + 1 == levels {
            spec.end_goal_bounds.clone()
        } else {
            subgoals.clone()
        };
        let action = if level == 0 {
            spec.action_bounds.clone()
        } else {
            subgoals
        };
        let widen = |b: Bounds| {
            if b.is_empty() {
                b
            } else {
                b.widened(MARGIN, ROUNDING)
            }
        };
        Self {
            state: widen(spec.state_bounds.clone()),
            goal: widen(goal),
            action: widen(action),
            rewards: [0.0, -1.0, -horizon],
        }
    }

    /// Checks every value of `batch` (whose shape is already checked); the first value out of
    /// range is the error.
    pub fn check(&self, batch: &BatchRef<'_>) -> Result<(), LimitError> {
        check_box("states", batch.states, &self.state)?;
        check_box("next_states", batch.next_states, &self.state)?;
        check_box("goals", batch.goals, &self.goal)?;
        check_box("actions", batch.actions, &self.action)?;
        let [a, b, c] = self.rewards;
        if let Some(index) = batch
            .rewards
            .iter()
            .position(|&r| r != a && r != b && r != c)
        {
            return Err(LimitError::Reward {
                index,
                value: batch.rewards[index],
                penalty: c,
            });
        }
        Ok(())
    }
}

/// Checks `values`, samples of `bounds.dim()` values each, against `bounds`.
fn check_box(field: &'static str, values: &[f32], bounds: &Bounds) -> Result<(), LimitError> {
    let dim = bounds.dim();
    if dim == 0 {
        return Ok(());
    }
    // One pass that only compares; the position is looked for once something is out.
    let inside = values.chunks_exact(dim).all(|sample| {
        sample
            .iter()
            .zip(&bounds.low)
            .zip(&bounds.high)
            .all(|((v, lo), hi)| *lo <= *v && *v <= *hi)
    });
    if inside {
        return Ok(());
    }
    let index = values
        .iter()
        .enumerate()
        .position(|(i, v)| !(bounds.low[i % dim]..=bounds.high[i % dim]).contains(v))
        .unwrap_or_default();
    let d = index % dim;
    Err(LimitError::OutOfBounds {
        field,
        index,
        dim: d,
        value: values[index],
        low: bounds.low[d],
        high: bounds.high[d],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> EnvSpec {
        EnvSpec {
            name: "t".into(),
            description: String::new(),
            state_dim: 2,
            action_bounds: Bounds::symmetric(&[1.0]),
            end_goal_dim: 1,
            end_goal_thresholds: vec![0.1],
            subgoal_bounds: Bounds::symmetric(&[1.0, 1.0]),
            subgoal_thresholds: vec![0.1, 0.1],
            end_goal_angles: Vec::new(),
            subgoal_angles: Vec::new(),
            state_bounds: Bounds::symmetric(&[10.0, 1.0]),
            end_goal_bounds: Bounds::symmetric(&[5.0]),
            achieved_subgoal_bounds: Bounds::symmetric(&[2.0, 0.5]),
            max_actions: 10,
            physics_steps_per_action: 1,
        }
    }

    struct Owned {
        states: Vec<f32>,
        next_states: Vec<f32>,
        goals: Vec<f32>,
        actions: Vec<f32>,
        rewards: Vec<f32>,
        terminals: Vec<f32>,
    }

    impl Owned {
        /// Two level-0 transitions of a 2-level hierarchy, every value admissible.
        fn level0() -> Self {
            Self {
                states: vec![0.0, 0.0, 10.0, -1.0],
                next_states: vec![1.0, 0.5, -10.0, 1.0],
                goals: vec![1.0, 1.0, -2.0, 0.5],
                actions: vec![1.0, -1.0],
                rewards: vec![0.0, -1.0],
                terminals: vec![1.0, 0.0],
            }
        }

        fn batch(&self) -> BatchRef<'_> {
            BatchRef {
                len: self.rewards.len(),
                states: &self.states,
                actions: &self.actions,
                rewards: &self.rewards,
                next_states: &self.next_states,
                goals: &self.goals,
                terminals: &self.terminals,
            }
        }
    }

    #[test]
    fn honest_values_pass_and_the_margin_is_a_tenth_of_the_width() {
        let limits = TransitionLimits::for_level(&spec(), 0, 2, 5.0);
        let mut b = Owned::level0();
        assert_eq!(limits.check(&b.batch()), Ok(()));
        // State dimension 0 spans 20: 2 more on each side pass, a little beyond does not.
        b.states[0] = 12.0;
        assert_eq!(limits.check(&b.batch()), Ok(()));
        b.states[0] = 12.01;
        assert!(matches!(
            limits.check(&b.batch()),
            Err(LimitError::OutOfBounds {
                field: "states",
                index: 0,
                dim: 0,
                ..
            })
        ));
    }

    #[test]
    fn an_absurd_finite_value_in_any_field_is_refused_with_its_place() {
        let limits = TransitionLimits::for_level(&spec(), 0, 2, 5.0);
        for (field, index) in [
            ("states", 3),
            ("next_states", 2),
            ("goals", 1),
            ("actions", 1),
        ] {
            let mut b = Owned::level0();
            let values = match field {
                "states" => &mut b.states,
                "next_states" => &mut b.next_states,
                "goals" => &mut b.goals,
                _ => &mut b.actions,
            };
            values[index] = 3e38;
            let e = limits.check(&b.batch()).unwrap_err();
            assert!(
                matches!(e, LimitError::OutOfBounds { field: f, index: i, value, .. }
                    if f == field && i == index && value == 3e38),
                "{field}: {e:?}"
            );
            let message = e.to_string();
            assert!(
                message.contains(&format!("batch.{field}[{index}]")),
                "{message}"
            );
        }
    }

    #[test]
    fn rewards_are_zero_minus_one_or_the_penalty() {
        let limits = TransitionLimits::for_level(&spec(), 1, 2, 5.0);
        let mut b = Owned::level0();
        b.actions = vec![0.0, 0.0, 0.0, 0.0];
        b.goals = vec![0.0, 0.0];
        b.rewards = vec![-5.0, 0.0];
        assert_eq!(limits.check(&b.batch()), Ok(()));
        b.rewards[1] = -1e20;
        assert_eq!(
            limits.check(&b.batch()),
            Err(LimitError::Reward {
                index: 1,
                value: -1e20,
                penalty: -5.0
            })
        );
        b.rewards[1] = -2.0;
        assert!(limits.check(&b.batch()).is_err());
    }

    #[test]
    fn goal_and_action_spaces_follow_the_level() {
        let spec = spec();
        // Top level of 2: goals are end goals (+-5), actions subgoals (the hull: +-2, +-1).
        let top = TransitionLimits::for_level(&spec, 1, 2, 5.0);
        let mut b = Owned::level0();
        b.goals = vec![5.0, -5.0];
        b.actions = vec![2.0, 1.0, -2.0, -1.0];
        assert_eq!(top.check(&b.batch()), Ok(()));
        b.actions[0] = 2.9;
        assert!(top.check(&b.batch()).is_err());
        // Level 0 of 2: goals are subgoals (the hull), so +-5 is out.
        let bottom = TransitionLimits::for_level(&spec, 0, 2, 5.0);
        let mut b = Owned::level0();
        b.goals = vec![5.0, 0.0, 0.0, 0.0];
        assert!(bottom.check(&b.batch()).is_err());
    }

    #[test]
    fn unknown_boxes_are_not_checked() {
        let mut spec = spec();
        spec.state_bounds = Bounds::default();
        let limits = TransitionLimits::for_level(&spec, 0, 2, 5.0);
        let mut b = Owned::level0();
        b.states[0] = 1e30;
        assert_eq!(limits.check(&b.batch()), Ok(()));
    }
}
