//! One HIRO episode through its two levels (Nachum et al., 2018, section 3).
//!
//! Every `c` primitive steps the high level (level 1, conditioned on the end goal) proposes a
//! relative goal `g` in the box `[-r, r]`, `r` the half ranges of the subgoal bounds; between
//! its decisions the goal moves with the state by the goal transition. The low level (level 0)
//! acts on `(s, g)` at every step. Both add Gaussian noise in training episodes (the
//! [`Exploration`] passed in; HIRO has no random actions and no subgoal testing) and act
//! greedily in test episodes.
//!
//! What a training episode stores:
//! - per primitive step, a low-level transition `(s, a, r, s', g)` with the intrinsic reward
//!   `r = -||p(s) + g - p(s')||`; `terminal` only where the environment ended the episode. The
//!   next goal `g' = h(s, g, s')` is not stored: it follows from `s`, `g` and `s'`.
//! - per high-level decision, a [`HighTransition`]: `(s_t, g_t, R, s_{t+c}, end goal)` with `R`
//!   the sum of the task's rewards over its steps (-1 per step, 0 at the step that reaches the
//!   end goal, which ends the episode; or, with [`TaskReward::Distance`], minus each step's
//!   distance to the end goal) and `terminal` when the end goal was reached or the
//!   environment ended the episode; with its low-level states, projections and actions, which
//!   the off-policy correction reads. The last one of an episode may have fewer than `c` steps.
//!
//! No hindsight at either level: that is the difference the HAC paper's comparison measures.

use crate::hiro::{
    LowLevelSteps, StepsShape, TaskReward, distance, goal_radius, goal_transition, intrinsic_reward,
};
use crate::rollout::{EpisodeOutcome, Exploration, Policy};
use crate::{
    Bounds, Env, EnvSpec, Mode, Rng, Transition, TransitionKind, TransitionSink, within_goal,
};

/// A high-level transition with the low-level steps it spanned, borrowed from the rollout.
#[derive(Debug, Clone, Copy)]
pub struct HighTransition<'a> {
    /// `(s_t, g_t, R, s_{t+k}, end goal, terminal)`: the state at the decision, the relative
    /// goal proposed (with exploration noise, clipped to the box), the sum of the task's rewards
    /// over the steps, the state after the last one, the end goal (the high level's goal), and
    /// whether the end goal was reached or the environment ended the episode there (kind
    /// [`TransitionKind::HindsightAction`]: the action taken).
    pub transition: Transition<'a>,
    /// The `k <= c` low-level steps.
    pub steps: LowLevelSteps<'a>,
}

/// Receives what a HIRO training episode produces.
pub trait HiroSink {
    /// A low-level transition (kind [`TransitionKind::HindsightAction`]: the action taken).
    fn push_low(&mut self, transition: &Transition<'_>);
    /// A high-level transition with its steps.
    fn push_high(&mut self, transition: &HighTransition<'_>);
}

/// Runs HIRO episodes; owns every buffer, so that an episode allocates nothing once they have
/// grown to its size.
#[derive(Debug)]
pub struct HiroRollout {
    spec: EnvSpec,
    c: usize,
    task_reward: TaskReward,
    /// The relative goals' box, `[-r, r]`.
    goal_bounds: Bounds,
    /// The subgoal dimensions whose differences are taken along the circle
    /// ([`EnvSpec::relative_goal_angles`]).
    angles: Vec<bool>,
    state: Vec<f32>,
    end_goal: Vec<f32>,
    /// The low level's current goal and the next one.
    goal: Vec<f32>,
    next_goal: Vec<f32>,
    /// `p(s)` and `p(s')`.
    achieved: Vec<f32>,
    next_achieved: Vec<f32>,
    end_projection: Vec<f32>,
    /// The end-goal projection of the episode's first state.
    start_achieved: Vec<f32>,
    action: Vec<f32>,
    segment: Segment,
    /// A high-level transition's steps, packed for [`HiroRollout::run_episode_packed`].
    packed: Vec<f32>,
}

/// The current high-level decision and its steps so far.
#[derive(Debug, Default)]
struct Segment {
    state: Vec<f32>,
    action: Vec<f32>,
    reward: f32,
    states: Vec<f32>,
    achieved: Vec<f32>,
    actions: Vec<f32>,
    len: usize,
}

impl HiroRollout {
    /// A rollout whose high level decides every `c` primitive steps.
    pub fn new(spec: &EnvSpec, c: usize) -> Self {
        assert!(c >= 1, "HIRO's high level needs c >= 1");
        let g = spec.subgoal_dim();
        let radius = goal_radius(spec);
        Self {
            spec: spec.clone(),
            c,
            task_reward: TaskReward::Sparse,
            goal_bounds: Bounds::symmetric(&radius),
            angles: spec.relative_goal_angles(),
            state: vec![0.0; spec.state_dim],
            end_goal: vec![0.0; spec.end_goal_dim],
            goal: vec![0.0; g],
            next_goal: vec![0.0; g],
            achieved: vec![0.0; g],
            next_achieved: vec![0.0; g],
            end_projection: vec![0.0; spec.end_goal_dim],
            start_achieved: vec![0.0; spec.end_goal_dim],
            action: vec![0.0; spec.action_dim()],
            segment: Segment::default(),
            packed: vec![0.0; StepsShape::of(spec, c).width()],
        }
    }

    /// The same rollout with the high level rewarded by `reward` (sparse by default).
    pub fn with_task_reward(mut self, reward: TaskReward) -> Self {
        self.task_reward = reward;
        self
    }

    /// The shape of the high level's packed steps ([`Transition::extra`] of its transitions).
    pub fn steps_shape(&self) -> StepsShape {
        StepsShape::of(&self.spec, self.c)
    }

    /// [`run_episode`](Self::run_episode) into a [`TransitionSink`], as HAC's rollout feeds
    /// one: low-level transitions as level 0's, high-level ones as level 1's with their steps
    /// packed into [`Transition::extra`] ([`LowLevelSteps::pack`]).
    pub fn run_episode_packed(
        &mut self,
        env: &mut dyn Env,
        policy: &mut dyn Policy,
        exploration: &mut dyn Exploration,
        mode: Mode,
        rng: &mut Rng,
        sink: &mut dyn TransitionSink,
    ) -> EpisodeOutcome {
        let shape = self.steps_shape();
        let mut packed = std::mem::take(&mut self.packed);
        let mut packing = Packing {
            sink,
            shape,
            packed: &mut packed,
        };
        let outcome = self.run_episode(env, policy, exploration, mode, rng, &mut packing);
        self.packed = packed;
        outcome
    }

    /// The box of the high level's relative goals (its output bounds).
    pub fn goal_bounds(&self) -> &Bounds {
        &self.goal_bounds
    }

    /// The end goal of the current (or last) episode.
    pub fn end_goal(&self) -> &[f32] {
        &self.end_goal
    }

    /// The end-goal projection of the current (or last) episode's first state.
    pub fn start_achieved(&self) -> &[f32] {
        &self.start_achieved
    }

    /// The end-goal projection of the current (or last) episode's last state.
    pub fn final_achieved(&self) -> &[f32] {
        &self.end_projection
    }

    /// The spec of the environment this rollout was made for.
    pub fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    /// Resets `env`, draws an end goal for `mode` and runs one episode. `policy` answers for
    /// level 1 (state, end goal -> relative goal) and level 0 (state, relative goal -> action);
    /// in `Mode::Train` `exploration` perturbs both and everything goes to `sink`, in
    /// `Mode::Test` both are greedy and nothing is stored.
    pub fn run_episode(
        &mut self,
        env: &mut dyn Env,
        policy: &mut dyn Policy,
        exploration: &mut dyn Exploration,
        mode: Mode,
        rng: &mut Rng,
        sink: &mut dyn HiroSink,
    ) -> EpisodeOutcome {
        env.reset(rng);
        env.sample_end_goal(rng, mode, &mut self.end_goal);
        let train = mode == Mode::Train;
        let (threshold, angles) = self.spec.goal_test(true);
        let subgoal_angles = &self.angles;
        self.state.copy_from_slice(env.state());
        env.project_subgoal(&self.state, &mut self.achieved);
        env.project_end_goal(&self.state, &mut self.start_achieved);
        self.end_projection.copy_from_slice(&self.start_achieved);
        let (mut steps, mut success) = (0, false);
        while steps < self.spec.max_actions {
            if steps % self.c == 0 {
                policy.act(1, &self.state, &self.end_goal, &mut self.goal);
                if train {
                    exploration.explore(1, &self.state, &self.goal_bounds, &mut self.goal);
                }
                self.goal_bounds.clip(&mut self.goal);
                let seg = &mut self.segment;
                seg.state.clone_from(&self.state);
                seg.action.clone_from(&self.goal);
                seg.reward = 0.0;
                seg.len = 0;
                seg.states.clear();
                seg.actions.clear();
                seg.achieved.clear();
                seg.achieved.extend_from_slice(&self.achieved);
            }
            policy.act(0, &self.state, &self.goal, &mut self.action);
            if train {
                exploration.explore(0, &self.state, &self.spec.action_bounds, &mut self.action);
            }
            self.spec.action_bounds.clip(&mut self.action);
            env.step(&self.action);
            steps += 1;
            let next_state = env.state();
            env.project_subgoal(next_state, &mut self.next_achieved);
            env.project_end_goal(next_state, &mut self.end_projection);
            success = within_goal(&self.end_projection, &self.end_goal, threshold, angles);
            let terminated = env.terminated();
            goal_transition(
                &self.achieved,
                &self.goal,
                &self.next_achieved,
                subgoal_angles,
                &mut self.next_goal,
            );
            let seg = &mut self.segment;
            seg.reward += match self.task_reward {
                TaskReward::Sparse if success => 0.0,
                TaskReward::Sparse => -1.0,
                TaskReward::Distance => -distance(&self.end_projection, &self.end_goal, angles),
            };
            seg.states.extend_from_slice(&self.state);
            seg.actions.extend_from_slice(&self.action);
            seg.achieved.extend_from_slice(&self.next_achieved);
            seg.len += 1;
            if train {
                sink.push_low(&Transition {
                    kind: TransitionKind::HindsightAction,
                    state: &self.state,
                    action: &self.action,
                    reward: intrinsic_reward(
                        &self.achieved,
                        &self.goal,
                        &self.next_achieved,
                        subgoal_angles,
                    ),
                    next_state,
                    goal: &self.goal,
                    terminal: terminated,
                    extra: &[],
                });
            }
            let ended = success || terminated || steps >= self.spec.max_actions;
            if train && (ended || seg.len == self.c) {
                sink.push_high(&HighTransition {
                    transition: Transition {
                        kind: TransitionKind::HindsightAction,
                        state: &seg.state,
                        action: &seg.action,
                        reward: seg.reward,
                        next_state,
                        goal: &self.end_goal,
                        terminal: success || terminated,
                        extra: &[],
                    },
                    steps: LowLevelSteps {
                        states: &seg.states,
                        achieved: &seg.achieved,
                        actions: &seg.actions,
                    },
                });
            }
            self.state.copy_from_slice(next_state);
            std::mem::swap(&mut self.achieved, &mut self.next_achieved);
            std::mem::swap(&mut self.goal, &mut self.next_goal);
            if success || terminated {
                break;
            }
        }
        EpisodeOutcome { success, steps }
    }
}

/// Forwards HIRO's transitions to a [`TransitionSink`], packing the high level's steps.
struct Packing<'a> {
    sink: &'a mut dyn TransitionSink,
    shape: StepsShape,
    packed: &'a mut Vec<f32>,
}

impl HiroSink for Packing<'_> {
    fn push_low(&mut self, transition: &Transition<'_>) {
        self.sink.push(0, transition);
    }

    fn push_high(&mut self, high: &HighTransition<'_>) {
        high.steps.pack(self.shape, self.packed);
        self.sink.push(
            1,
            &Transition {
                extra: self.packed,
                ..high.transition
            },
        );
    }
}
