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
//!   subgoal-testing penalty), HAC's three values;
//! - extra values ([`crate::Transition::extra`]) have the width the level stores: none for HAC.
//!
//! HIRO's levels ([`TransitionLimits::for_hiro_level`]) differ where HIRO does: relative goals,
//! the low level's distance rewards, the high level's sums of `-1` over up to `c` steps, and
//! the high level's low-level steps, whose states, projections and actions are checked like the
//! fields above.
//!
//! Every box is widened by [`MARGIN`] of its width on each side (plus a hair for rounding), so
//! an honest actor whose physics differs in the last bits is never refused. A box the
//! environment leaves empty (unknown) is not checked.

use crate::hiro::{LowLevelSteps, StepsError, StepsShape, TaskReward, goal_radius};
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
    rewards: Rewards,
    extra: Extra,
}

/// The rewards a level produces.
#[derive(Debug, Clone, PartialEq)]
enum Rewards {
    /// HAC: exactly these values.
    OneOf([f32; 3]),
    /// HIRO's high level: whole numbers from `-max` to 0.
    Whole { max: f32 },
    /// HIRO's low level: any value from `-max` to 0.
    Within { max: f32 },
}

/// What a level stores beside each transition.
#[derive(Debug, Clone, PartialEq)]
enum Extra {
    None,
    /// HIRO's high level: its low-level steps, packed; states, projections and actions within
    /// these boxes.
    Steps {
        shape: StepsShape,
        state: Bounds,
        achieved: Bounds,
        action: Bounds,
    },
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
    #[error("batch.rewards[{index}] = {value:e} is not a reward this level produces ({what})")]
    RewardOutside {
        index: usize,
        value: f32,
        what: String,
    },
    #[error(
        "batch.extra has {got} values per transition, this level stores {expected} (HAC's \
         levels none, HIRO's high level its low-level steps)"
    )]
    ExtraWidth { got: usize, expected: usize },
    #[error("batch.extra of transition {index}: {source}")]
    Steps {
        index: usize,
        #[source]
        source: StepsError,
    },
    #[error("low-level steps of transition {index}: {source}")]
    StepOutOfBounds {
        index: usize,
        #[source]
        source: Box<LimitError>,
    },
}

/// Where subgoals come from: the proposing level's output range (`subgoal_bounds`) joined with
/// the achieved ones hindsight relabels with (`achieved_subgoal_bounds`).
fn subgoal_space(spec: &EnvSpec) -> Bounds {
    if spec.achieved_subgoal_bounds.is_empty() {
        spec.subgoal_bounds.clone()
    } else {
        spec.subgoal_bounds.hull(&spec.achieved_subgoal_bounds)
    }
}

/// The length of `b`'s diagonal: the farthest two of its points are apart; unbounded when `b`
/// is empty (unknown).
fn diagonal(b: &Bounds) -> f32 {
    if b.is_empty() {
        return f32::INFINITY;
    }
    (0..b.dim())
        .map(|d| (b.high[d] - b.low[d]).powi(2))
        .sum::<f32>()
        .sqrt()
}

/// `b` widened by [`MARGIN`] (and the rounding hair) on each side; an empty (unknown) box stays
/// empty.
fn widen(b: Bounds) -> Bounds {
    if b.is_empty() {
        b
    } else {
        b.widened(MARGIN, ROUNDING)
    }
}

fn field_meaning(field: &str) -> &'static str {
    match field {
        "states" | "next_states" | "extra.states" => "state",
        "goals" => "goal",
        "extra.achieved" => "subgoal",
        _ => "action",
    }
}

impl TransitionLimits {
    /// The limits of level `level` of `levels` under `spec`, whose penalty is `-horizon`.
    pub fn for_level(spec: &EnvSpec, level: usize, levels: usize, horizon: f32) -> Self {
        let subgoals = subgoal_space(spec);
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
        Self {
            state: widen(spec.state_bounds.clone()),
            goal: widen(goal),
            action: widen(action),
            rewards: Rewards::OneOf([0.0, -1.0, -horizon]),
            extra: Extra::None,
        }
    }

    /// The limits of HIRO's `level` (0 or 1) with the high level deciding every `c` steps:
    ///
    /// - level 1: goals in the end goal space, actions (relative goals) in `[-r, r]` with `r`
    ///   the subgoal bounds' half ranges, rewards whole numbers from `-c` to 0 (with
    ///   [`TaskReward::Distance`]: from `-c` times the end-goal box's diagonal to 0), and each
    ///   transition's packed low-level steps ([`StepsShape`]) with states in the state box,
    ///   projections in the subgoal space and actions in the action box;
    /// - level 0: goals (relative goals moved by the goal transition, which can drift by the
    ///   subgoal space's width within a decision) in `[-(r + w), r + w]`, `w` the width,
    ///   rewards from minus the largest distance such goals allow (`||r + 2w||`) to 0.
    pub fn for_hiro_level(spec: &EnvSpec, level: usize, c: usize, reward: TaskReward) -> Self {
        let subgoals = subgoal_space(spec);
        let radius = goal_radius(spec);
        let width: Vec<f32> = (0..spec.subgoal_dim())
            .map(|d| subgoals.high[d] - subgoals.low[d])
            .collect();
        let state = widen(spec.state_bounds.clone());
        if level == 0 {
            let drift: Vec<f32> = radius.iter().zip(&width).map(|(r, w)| r + w).collect();
            let far: f32 = radius
                .iter()
                .zip(&width)
                .map(|(r, w)| (r + 2.0 * w) * (r + 2.0 * w))
                .sum::<f32>()
                .sqrt();
            Self {
                state,
                goal: widen(Bounds::symmetric(&drift)),
                action: widen(spec.action_bounds.clone()),
                rewards: Rewards::Within {
                    max: far * (1.0 + MARGIN) + ROUNDING,
                },
                extra: Extra::None,
            }
        } else {
            Self {
                state: state.clone(),
                goal: widen(spec.end_goal_bounds.clone()),
                action: widen(Bounds::symmetric(&radius)),
                rewards: match reward {
                    TaskReward::Sparse => Rewards::Whole { max: c as f32 },
                    TaskReward::Distance => Rewards::Within {
                        max: c as f32 * diagonal(&spec.end_goal_bounds) * (1.0 + MARGIN) + ROUNDING,
                    },
                },
                extra: Extra::Steps {
                    shape: StepsShape::of(spec, c),
                    state,
                    achieved: widen(subgoals),
                    action: widen(spec.action_bounds.clone()),
                },
            }
        }
    }

    /// Extra values per transition this level stores.
    pub fn extra_width(&self) -> usize {
        match &self.extra {
            Extra::None => 0,
            Extra::Steps { shape, .. } => shape.width(),
        }
    }

    /// Checks every value of `batch` (whose shape is already checked); the first value out of
    /// range is the error.
    pub fn check(&self, batch: &BatchRef<'_>) -> Result<(), LimitError> {
        check_box("states", batch.states, &self.state)?;
        check_box("next_states", batch.next_states, &self.state)?;
        check_box("goals", batch.goals, &self.goal)?;
        check_box("actions", batch.actions, &self.action)?;
        self.check_rewards(batch.rewards)?;
        self.check_extra(batch)
    }

    fn check_rewards(&self, rewards: &[f32]) -> Result<(), LimitError> {
        let (bad, what): (Option<usize>, _) = match self.rewards {
            Rewards::OneOf([a, b, c]) => {
                if let Some(index) = rewards.iter().position(|&r| r != a && r != b && r != c) {
                    return Err(LimitError::Reward {
                        index,
                        value: rewards[index],
                        penalty: c,
                    });
                }
                return Ok(());
            }
            Rewards::Whole { max } => (
                rewards
                    .iter()
                    .position(|&r| !(-max..=0.0).contains(&r) || r.fract() != 0.0),
                format!("a whole number from {} to 0", -max),
            ),
            Rewards::Within { max } => (
                rewards.iter().position(|&r| !(-max..=0.0).contains(&r)),
                format!("from {:e} to 0", -max),
            ),
        };
        match bad {
            None => Ok(()),
            Some(index) => Err(LimitError::RewardOutside {
                index,
                value: rewards[index],
                what,
            }),
        }
    }

    fn check_extra(&self, batch: &BatchRef<'_>) -> Result<(), LimitError> {
        let expected = self.extra_width();
        let got = batch.extra.len().checked_div(batch.len).unwrap_or(0);
        if got != expected || batch.extra.len() != batch.len * expected {
            return Err(LimitError::ExtraWidth { got, expected });
        }
        let Extra::Steps {
            shape,
            state,
            achieved,
            action,
        } = &self.extra
        else {
            return Ok(());
        };
        for (index, packed) in batch.extra.chunks_exact(expected).enumerate() {
            let steps = LowLevelSteps::unpack(packed, *shape)
                .map_err(|source| LimitError::Steps { index, source })?;
            let inside = check_box("extra.states", steps.states, state)
                .and_then(|()| check_box("extra.achieved", steps.achieved, achieved))
                .and_then(|()| check_box("extra.actions", steps.actions, action));
            if let Err(e) = inside {
                return Err(LimitError::StepOutOfBounds {
                    index,
                    source: Box::new(e),
                });
            }
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
            subgoal_wrapped: Vec::new(),
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
        extra: Vec<f32>,
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
                extra: Vec::new(),
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
                extra: &self.extra,
            }
        }
    }

    #[test]
    fn hac_levels_refuse_extra_values_and_hiro_checks_its_rewards_and_steps() {
        let mut b = Owned::level0();
        b.extra = vec![0.0; 2];
        assert_eq!(
            TransitionLimits::for_level(&spec(), 0, 2, 5.0).check(&b.batch()),
            Err(LimitError::ExtraWidth {
                got: 1,
                expected: 0
            })
        );

        // HIRO's low level: distances, not HAC's three values; goals may drift past the box.
        let low = TransitionLimits::for_hiro_level(&spec(), 0, 3, TaskReward::Sparse);
        let mut b = Owned::level0();
        b.rewards = vec![-0.37, -2.5];
        b.goals = vec![3.0, 1.5, -2.0, 0.5];
        assert_eq!(low.check(&b.batch()), Ok(()));
        b.rewards[1] = 0.1;
        assert!(matches!(
            low.check(&b.batch()),
            Err(LimitError::RewardOutside { index: 1, .. })
        ));

        // HIRO's high level: sums of -1 over up to c steps, and its steps packed beside.
        let high = TransitionLimits::for_hiro_level(&spec(), 1, 3, TaskReward::Sparse);
        let shape = StepsShape {
            c: 3,
            state: 2,
            goal: 2,
            action: 1,
        };
        assert_eq!(high.extra_width(), shape.width());
        let mut packed = vec![0.0; shape.width()];
        LowLevelSteps {
            states: &[0.0, 0.0, 1.0, 0.5],
            achieved: &[0.0, 0.0, 1.0, 0.5, 1.5, 0.2],
            actions: &[0.5, -0.5],
        }
        .pack(shape, &mut packed);
        let mut h = Owned {
            states: vec![0.0, 0.0],
            next_states: vec![1.0, 0.5],
            goals: vec![4.0],
            actions: vec![1.0, -1.0],
            rewards: vec![-2.0],
            terminals: vec![0.0],
            extra: packed.clone(),
        };
        assert_eq!(high.check(&h.batch()), Ok(()));
        h.rewards[0] = -2.5;
        assert!(matches!(
            high.check(&h.batch()),
            Err(LimitError::RewardOutside { index: 0, .. })
        ));
        h.rewards[0] = -4.0;
        assert!(high.check(&h.batch()).is_err(), "more than c steps of -1");
        h.rewards[0] = -3.0;
        h.extra[0] = 5.0;
        assert!(matches!(
            high.check(&h.batch()),
            Err(LimitError::Steps { index: 0, .. })
        ));
        h.extra.clone_from(&packed);
        // The second step's action (at 1 + 3 x 2 + 4 x 2 + 1) far outside the action box.
        h.extra[1 + 6 + 8 + 1] = 30.0;
        let err = high.check(&h.batch()).unwrap_err();
        assert!(
            err.to_string().contains("extra.actions[1]"),
            "the message names the step's field: {err}"
        );
        h.extra.pop();
        assert!(matches!(
            high.check(&h.batch()),
            Err(LimitError::ExtraWidth { .. })
        ));

        // With the dense task reward: any sum of c distances within the end-goal box (diagonal
        // 10 here), not only whole numbers; nothing positive, nothing farther.
        let dense = TransitionLimits::for_hiro_level(&spec(), 1, 3, TaskReward::Distance);
        h.extra.clone_from(&packed);
        h.rewards[0] = -29.5;
        assert_eq!(dense.check(&h.batch()), Ok(()));
        h.rewards[0] = -0.25;
        assert_eq!(dense.check(&h.batch()), Ok(()));
        for bad in [0.5, -34.0] {
            h.rewards[0] = bad;
            assert!(matches!(
                dense.check(&h.batch()),
                Err(LimitError::RewardOutside { index: 0, .. })
            ));
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
