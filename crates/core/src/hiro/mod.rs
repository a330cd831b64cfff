//! HIRO's goal arithmetic (Nachum, Gu, Lee and Levine, *Data-Efficient Hierarchical
//! Reinforcement Learning*, NeurIPS 2018), the baseline of the HAC paper's Figure 4: everything
//! about its two levels that involves no learning.
//!
//! HIRO's high level proposes a *relative* goal every `c` primitive steps: an offset in the
//! subgoal space from where the state is (the projection `p` HAC's level 1 uses). Between its
//! decisions the goal moves with the state so that it keeps naming the same absolute target
//! ([`goal_transition`]); the low level is rewarded by how close it came
//! ([`intrinsic_reward`]). When the high level learns from an old transition, the goal it stored
//! may no longer be the one that makes today's low level act as it did then; the off-policy
//! correction ([`OffPolicyCorrection`]) replaces it by the candidate under which the stored
//! low-level actions are the most likely.
//!
//! [`HiroRollout`] plays one episode through the two levels with them.
//!
//! Angles: dimensions flagged in `angles` (radians; empty: none) are compared along the circle,
//! as in HAC's goal test ([`crate::within_goal`]): every difference of two angles is wrapped to
//! `[-pi, pi]`, so an offset names the shorter turn.

use crate::bounds::angle_difference;
use crate::{EnvSpec, Rng};

mod config;
mod rollout;

pub use config::{Algo, CriticLoss, HiroConfig, TaskReward};
pub use rollout::{HighTransition, HiroRollout, HiroSink};

/// `r`: the half ranges of `spec`'s subgoal bounds, per dimension. HIRO's relative goals lie in
/// `[-r, r]`.
pub fn goal_radius(spec: &EnvSpec) -> Vec<f32> {
    (0..spec.subgoal_dim())
        .map(|d| spec.subgoal_bounds.half_range(d))
        .collect()
}

/// `to - from` per dimension, wrapped to `[-pi, pi]` on the dimensions flagged in `angles`.
pub fn displacement(from: &[f32], to: &[f32], angles: &[bool], out: &mut [f32]) {
    debug_assert_eq!(from.len(), to.len());
    debug_assert_eq!(from.len(), out.len());
    debug_assert!(angles.is_empty() || angles.len() == out.len());
    for (d, o) in out.iter_mut().enumerate() {
        *o = wrapped(to[d] - from[d], angles, d);
    }
}

/// The goal transition `h(s, g, s') = p(s) + g - p(s')`: the relative goal that names, from
/// `p(s')`, the target that `goal` named from `p(s)`. `achieved` is `p(s)`, `next_achieved` is
/// `p(s')`.
pub fn goal_transition(
    achieved: &[f32],
    goal: &[f32],
    next_achieved: &[f32],
    angles: &[bool],
    out: &mut [f32],
) {
    debug_assert_eq!(achieved.len(), goal.len());
    debug_assert_eq!(next_achieved.len(), goal.len());
    debug_assert_eq!(out.len(), goal.len());
    for (d, o) in out.iter_mut().enumerate() {
        *o = wrapped(achieved[d] + goal[d] - next_achieved[d], angles, d);
    }
}

/// The low level's reward `-||p(s) + g - p(s')||_2`: minus the distance between the target the
/// goal named and where the step arrived.
pub fn intrinsic_reward(
    achieved: &[f32],
    goal: &[f32],
    next_achieved: &[f32],
    angles: &[bool],
) -> f32 {
    debug_assert_eq!(achieved.len(), goal.len());
    debug_assert_eq!(next_achieved.len(), goal.len());
    -wrapped_norm(goal.len(), angles, |d| {
        achieved[d] + goal[d] - next_achieved[d]
    })
}

/// `||to - from||_2`, differences wrapped to `[-pi, pi]` on the dimensions flagged in `angles`:
/// the dense task reward's distance ([`TaskReward::Distance`]) from an end-goal projection to
/// the end goal.
pub fn distance(from: &[f32], to: &[f32], angles: &[bool]) -> f32 {
    debug_assert_eq!(from.len(), to.len());
    wrapped_norm(to.len(), angles, |d| to[d] - from[d])
}

/// The Euclidean norm of the `dims` differences `diff(d)`, each wrapped to `[-pi, pi]` on the
/// dimensions flagged in `angles`.
fn wrapped_norm(dims: usize, angles: &[bool], diff: impl Fn(usize) -> f32) -> f32 {
    (0..dims)
        .map(|d| wrapped(diff(d), angles, d).powi(2))
        .sum::<f32>()
        .sqrt()
}

fn wrapped(diff: f32, angles: &[bool], d: usize) -> f32 {
    if angles.get(d).copied().unwrap_or(false) {
        angle_difference(diff)
    } else {
        diff
    }
}

/// HIRO's off-policy correction of a high-level transition, with its buffers (no allocation
/// after the first use at given sizes).
///
/// Candidates, in this order: the stored goal; the displacement the `c` steps achieved,
/// `p(s_c) - p(s_0)`; and [`random`](Self::random) draws from a Gaussian centred on that
/// displacement with a standard deviation of half the goal box's half range per dimension,
/// clipped to the box `[-r, r]` (HIRO's 10 candidates with the default 8). The chosen one
/// maximises `-1/2 sum_i ||a_i - mu(s_i, g_i)||^2` over the stored low-level steps, where `mu`
/// is the current low-level policy and `g_i` is the candidate carried to step `i` by the goal
/// transition (`p(s_0) + g - p(s_i)`). Ties go to the earlier candidate, so the stored goal is
/// kept when nothing explains the actions better.
#[derive(Debug, Clone)]
pub struct OffPolicyCorrection {
    random: usize,
    candidates: Vec<f32>,
    goal: Vec<f32>,
    action: Vec<f32>,
}

/// One high-level transition's stored low-level steps, as the correction reads them.
#[derive(Debug, Clone, Copy)]
pub struct LowLevelSteps<'a> {
    /// `c` states `s_0 .. s_{c-1}`, one after another (`state_dim` each).
    pub states: &'a [f32],
    /// `c` subgoal projections `p(s_0) .. p(s_{c-1})`, then `p(s_c)` (`goal_dim` each).
    pub achieved: &'a [f32],
    /// The `c` primitive actions taken (`action_dim` each).
    pub actions: &'a [f32],
}

/// The shape of a level's packed [`LowLevelSteps`]: at most `c` steps of a state, a subgoal
/// projection and a primitive action of these widths.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepsShape {
    pub c: usize,
    pub state: usize,
    pub goal: usize,
    pub action: usize,
}

impl StepsShape {
    /// The steps of HIRO's high level on `spec` deciding every `c` primitive steps: full states,
    /// subgoal projections, primitive actions.
    pub fn of(spec: &EnvSpec, c: usize) -> Self {
        Self {
            c,
            state: spec.state_dim,
            goal: spec.subgoal_dim(),
            action: spec.action_dim(),
        }
    }

    /// Floats per packed transition: the step count, then `c` states, `c + 1` projections and
    /// `c` actions, each block zero-padded to its full length.
    pub fn width(&self) -> usize {
        1 + self.c * self.state + (self.c + 1) * self.goal + self.c * self.action
    }
}

/// Why packed low-level steps could not be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StepsError {
    #[error("{got} values of low-level steps, the level stores {expected}")]
    Width { got: usize, expected: usize },
    #[error("a step count of {0}, not a whole number from 1 to the level's c = {1}")]
    Count(f32, usize),
}

impl<'a> LowLevelSteps<'a> {
    /// The number of steps, `k`.
    pub fn count(&self, state_dim: usize) -> usize {
        self.states.len() / state_dim.max(1)
    }

    /// Writes the steps into `out` ([`StepsShape::width`] values): `k`, then the states, the
    /// projections and the actions, each block padded with zeros to `c` (`c + 1`) entries. This
    /// is the form HIRO's high-level transitions travel and are stored in
    /// ([`crate::Transition::extra`]).
    ///
    /// Panics if `out` is not `shape.width()` long or the steps do not fit the shape.
    pub fn pack(&self, shape: StepsShape, out: &mut [f32]) {
        assert_eq!(out.len(), shape.width(), "packed steps of another shape");
        let k = self.count(shape.state);
        assert!(
            k >= 1
                && k <= shape.c
                && self.states.len() == k * shape.state
                && self.achieved.len() == (k + 1) * shape.goal
                && self.actions.len() == k * shape.action,
            "low-level steps do not fit the shape"
        );
        out.fill(0.0);
        out[0] = k as f32;
        let mut at = 1;
        for (block, full) in [
            (self.states, shape.c * shape.state),
            (self.achieved, (shape.c + 1) * shape.goal),
            (self.actions, shape.c * shape.action),
        ] {
            out[at..at + block.len()].copy_from_slice(block);
            at += full;
        }
    }

    /// Reads what [`pack`](Self::pack) wrote, borrowing from `packed`.
    pub fn unpack(packed: &'a [f32], shape: StepsShape) -> Result<Self, StepsError> {
        if packed.len() != shape.width() {
            return Err(StepsError::Width {
                got: packed.len(),
                expected: shape.width(),
            });
        }
        let count = packed[0];
        if !(count >= 1.0 && count <= shape.c as f32 && count.fract() == 0.0) {
            return Err(StepsError::Count(count, shape.c));
        }
        let k = count as usize;
        let states_at = 1;
        let achieved_at = states_at + shape.c * shape.state;
        let actions_at = achieved_at + (shape.c + 1) * shape.goal;
        Ok(Self {
            states: &packed[states_at..states_at + k * shape.state],
            achieved: &packed[achieved_at..achieved_at + (k + 1) * shape.goal],
            actions: &packed[actions_at..actions_at + k * shape.action],
        })
    }
}

impl OffPolicyCorrection {
    /// A correction that draws `random` Gaussian candidates beside the stored goal and the
    /// achieved displacement (HIRO: 8).
    pub fn new(random: usize) -> Self {
        Self {
            random,
            candidates: Vec::new(),
            goal: Vec::new(),
            action: Vec::new(),
        }
    }

    /// How many random candidates are drawn.
    pub fn random(&self) -> usize {
        self.random
    }

    /// Fills the candidate list for a transition whose stored goal is `stored` and whose low
    /// level went from `first` = `p(s_0)` to `last` = `p(s_c)`; returns them one after another
    /// (`2 + random` of `stored.len()` values each).
    pub fn candidates(
        &mut self,
        stored: &[f32],
        first: &[f32],
        last: &[f32],
        half_range: &[f32],
        angles: &[bool],
        rng: &mut Rng,
    ) -> &[f32] {
        let dim = stored.len();
        debug_assert_eq!(half_range.len(), dim);
        self.candidates.clear();
        self.candidates.extend_from_slice(stored);
        let start = self.candidates.len();
        self.candidates.resize(start + dim, 0.0);
        displacement(first, last, angles, &mut self.candidates[start..]);
        for _ in 0..self.random {
            for (d, &r) in half_range.iter().enumerate() {
                let centre = self.candidates[start + d];
                let draw = centre + 0.5 * r * rng.normal();
                self.candidates.push(draw.clamp(-r, r));
            }
        }
        &self.candidates
    }

    /// Chooses the goal for a stored high-level transition: fills `out` with the candidate
    /// under which `policy` (the current low level: state, goal, action out) most likely took
    /// `steps.actions`, and returns its index in [`candidates`](Self::candidates)' order (0: the
    /// stored goal kept).
    #[allow(clippy::too_many_arguments)]
    pub fn relabel(
        &mut self,
        stored: &[f32],
        steps: LowLevelSteps<'_>,
        half_range: &[f32],
        angles: &[bool],
        rng: &mut Rng,
        policy: &mut impl FnMut(&[f32], &[f32], &mut [f32]),
        out: &mut [f32],
    ) -> usize {
        let dim = stored.len();
        let c = steps.achieved.len() / dim - 1;
        debug_assert_eq!(steps.achieved.len(), (c + 1) * dim);
        debug_assert!(c > 0 && steps.states.len().is_multiple_of(c));
        debug_assert!(steps.actions.len().is_multiple_of(c));
        let state_dim = steps.states.len() / c;
        let action_dim = steps.actions.len() / c;
        let first = &steps.achieved[..dim];
        let last = &steps.achieved[c * dim..];
        self.candidates(stored, first, last, half_range, angles, rng);
        self.goal.resize(dim, 0.0);
        self.action.resize(action_dim, 0.0);
        let (mut best, mut best_log_likelihood) = (0, f32::NEG_INFINITY);
        for k in 0..self.candidates.len() / dim {
            let candidate = &self.candidates[k * dim..(k + 1) * dim];
            let mut log_likelihood = 0.0f32;
            for i in 0..c {
                let achieved = &steps.achieved[i * dim..(i + 1) * dim];
                goal_transition(first, candidate, achieved, angles, &mut self.goal);
                policy(
                    &steps.states[i * state_dim..(i + 1) * state_dim],
                    &self.goal,
                    &mut self.action,
                );
                let taken = &steps.actions[i * action_dim..(i + 1) * action_dim];
                log_likelihood -= 0.5
                    * self
                        .action
                        .iter()
                        .zip(taken)
                        .map(|(a, t)| (a - t) * (a - t))
                        .sum::<f32>();
            }
            if log_likelihood > best_log_likelihood {
                (best, best_log_likelihood) = (k, log_likelihood);
            }
        }
        out.copy_from_slice(&self.candidates[best * dim..(best + 1) * dim]);
        best
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn low_level_steps_round_trip_through_their_packed_form() {
        let shape = StepsShape {
            c: 3,
            state: 2,
            goal: 1,
            action: 1,
        };
        assert_eq!(shape.width(), 1 + 6 + 4 + 3);
        let (states, achieved, actions) = ([1.0, 2.0, 3.0, 4.0], [0.5, 0.6, 0.7], [-1.0, 1.0]);
        let steps = LowLevelSteps {
            states: &states,
            achieved: &achieved,
            actions: &actions,
        };
        let mut packed = vec![9.0; shape.width()];
        steps.pack(shape, &mut packed);
        assert_eq!(
            packed,
            [
                2.0, 1.0, 2.0, 3.0, 4.0, 0.0, 0.0, 0.5, 0.6, 0.7, 0.0, -1.0, 1.0, 0.0
            ]
        );
        let back = LowLevelSteps::unpack(&packed, shape).expect("valid");
        assert_eq!(
            (back.states, back.achieved, back.actions),
            (&states[..], &achieved[..], &actions[..])
        );
        assert_eq!(
            LowLevelSteps::unpack(&packed[1..], shape).unwrap_err(),
            StepsError::Width {
                got: 13,
                expected: 14
            }
        );
        for bad in [0.0, 4.0, 1.5, f32::NAN] {
            packed[0] = bad;
            assert!(matches!(
                LowLevelSteps::unpack(&packed, shape),
                Err(StepsError::Count(..))
            ));
        }
    }

    use super::*;
    use std::f32::consts::PI;

    #[test]
    fn the_goal_transition_keeps_naming_the_same_absolute_target() {
        // From p(s) = (1, 2) the goal (0.5, -1) names (1.5, 1); after a step to (1.2, 1.5) the
        // goal that names it is (0.3, -0.5).
        let mut out = [0.0; 2];
        goal_transition(&[1.0, 2.0], &[0.5, -1.0], &[1.2, 1.5], &[], &mut out);
        assert!(
            (out[0] - 0.3).abs() < 1e-6 && (out[1] + 0.5).abs() < 1e-6,
            "{out:?}"
        );
        // Reaching the target leaves a zero goal, and a zero reward.
        goal_transition(&[1.0, 2.0], &[0.5, -1.0], &[1.5, 1.0], &[], &mut out);
        assert_eq!(out, [0.0, 0.0]);
        assert_eq!(
            intrinsic_reward(&[1.0, 2.0], &[0.5, -1.0], &[1.5, 1.0], &[]),
            0.0
        );
    }

    #[test]
    fn angles_move_along_the_circle() {
        // The pole at 3.0 rad is asked to turn +0.2 (to 3.2, that is -3.083); it arrives at
        // -3.1: 0.017 short, not 6.1 beyond.
        let angles = [true, false];
        let mut out = [0.0; 2];
        goal_transition(&[3.0, 0.0], &[0.2, 0.0], &[-3.1, 0.0], &angles, &mut out);
        let expected = 3.0 + 0.2 - (-3.1) - 2.0 * PI;
        assert!((out[0] - expected).abs() < 1e-5, "{out:?}");
        assert!(out[0].abs() < 0.05);
        let r = intrinsic_reward(&[3.0, 0.0], &[0.2, 0.0], &[-3.1, 0.0], &angles);
        assert!((r + expected.abs()).abs() < 1e-5, "{r}");
        // Without the flag the same numbers are far apart.
        assert!(intrinsic_reward(&[3.0, 0.0], &[0.2, 0.0], &[-3.1, 0.0], &[]) < -6.0);
        // The achieved displacement of the same step is the short turn.
        displacement(&[3.0, 0.0], &[-3.1, 0.5], &angles, &mut out);
        assert!(
            (out[0] - (2.0 * PI - 6.1)).abs() < 1e-5 && out[1] == 0.5,
            "{out:?}"
        );
    }

    #[test]
    fn the_intrinsic_reward_is_minus_the_euclidean_miss() {
        let r = intrinsic_reward(&[0.0, 0.0], &[3.0, 4.0], &[0.0, 0.0], &[]);
        assert!((r + 5.0).abs() < 1e-6, "{r}");
        let closer = intrinsic_reward(&[0.0, 0.0], &[3.0, 4.0], &[2.0, 3.0], &[]);
        assert!(closer > r);
    }

    #[test]
    fn candidates_are_the_stored_goal_the_achieved_displacement_and_clipped_draws() {
        let mut correction = OffPolicyCorrection::new(8);
        let mut rng = Rng::seed_from(3);
        let half_range = [1.0, 0.1];
        let c = correction
            .candidates(
                &[0.9, -0.05],
                &[0.0, 0.0],
                &[0.4, 0.2],
                &half_range,
                &[],
                &mut rng,
            )
            .to_vec();
        assert_eq!(c.len(), 10 * 2);
        assert_eq!(&c[..2], &[0.9, -0.05]);
        // The achieved displacement is not clipped (0.2 is beyond the box's 0.1).
        assert_eq!(&c[2..4], &[0.4, 0.2]);
        for draw in c[4..].chunks(2) {
            assert!((-1.0..=1.0).contains(&draw[0]) && (-0.1..=0.1).contains(&draw[1]));
        }
        // Draws differ from one another and from the centre.
        assert!(c[4..].chunks(2).any(|d| d[0] != 0.4));
        assert_ne!(&c[4..6], &c[6..8]);
    }

    /// A scripted low level whose action is the goal's first coordinate scaled: it reveals the
    /// goal it was given.
    fn scripted(_state: &[f32], goal: &[f32], action: &mut [f32]) {
        action[0] = 0.5 * goal[0];
    }

    #[test]
    fn the_correction_picks_the_goal_that_explains_the_actions() {
        // The low level was really given the absolute target 0.6 (relative 0.6 from p(s_0) =
        // 0), moved along the line and took the actions the scripted policy takes for that goal.
        // The stored goal is a stale 0.1 from an old high level.
        let c = 5;
        let mut achieved = Vec::new();
        let mut actions = Vec::new();
        let mut states = Vec::new();
        let true_goal = 0.6f32;
        for i in 0..=c {
            let position = 0.08 * i as f32;
            achieved.push(position);
            if i < c {
                states.push(position);
                let mut a = [0.0];
                scripted(&[position], &[true_goal - position], &mut a);
                actions.push(a[0]);
            }
        }
        let steps = LowLevelSteps {
            states: &states,
            achieved: &achieved,
            actions: &actions,
        };
        let mut correction = OffPolicyCorrection::new(8);
        let mut policy = scripted;
        // Among the ten candidates, the draws around the achieved displacement 0.4 with std 0.5
        // over many seeds: the chosen one is always the closest to 0.6 of the ten.
        let mut rng = Rng::seed_from(11);
        let mut picked_draw = 0;
        for _ in 0..50 {
            let mut probe = rng.clone();
            let candidates = correction
                .candidates(
                    &[0.1],
                    &achieved[..1],
                    &achieved[c..],
                    &[1.0],
                    &[],
                    &mut probe,
                )
                .to_vec();
            let closest = candidates
                .iter()
                .enumerate()
                .min_by(|a, b| (a.1 - true_goal).abs().total_cmp(&(b.1 - true_goal).abs()))
                .unwrap()
                .0;
            let mut out = [0.0];
            let index =
                correction.relabel(&[0.1], steps, &[1.0], &[], &mut rng, &mut policy, &mut out);
            assert_eq!(index, closest, "{candidates:?}");
            assert_eq!(out[0], candidates[index]);
            assert_ne!(index, 0, "the stale goal explains nothing");
            picked_draw += usize::from(index >= 2);
        }
        // Some of the time a random draw is closer to the truth than the displacement.
        assert!(picked_draw > 0);

        // With the true goal stored, it is kept (no candidate explains the actions better).
        let mut out = [0.0];
        let index = correction.relabel(
            &[true_goal],
            steps,
            &[1.0],
            &[],
            &mut rng,
            &mut policy,
            &mut out,
        );
        assert_eq!((index, out[0]), (0, true_goal));
    }
}
