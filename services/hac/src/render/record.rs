//! Watching an episode without touching the rollout: [`SubgoalRecorder`] wraps the policy and
//! keeps, for every primitive action, the state and the goal of every level.
//!
//! The rollout hands each level its goal when the level acts: the top level gets the end goal,
//! level `i - 1` gets the subgoal level `i` just proposed (after clipping to the subgoal bounds,
//! which the rollout does between the two calls). Level 0 acts once per primitive action, so a
//! call at level 0 is a moment at which every level's current goal is known.

use hac_core::Policy;

/// One moment of an episode: the state before a primitive action and what every level pursues.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Primitive actions executed before this moment.
    pub step: usize,
    /// The observed state.
    pub state: Vec<f32>,
    /// `goals[i]` is level i's current goal: the end goal for the top level, below it the
    /// subgoal that level `i + 1` proposed.
    pub goals: Vec<Vec<f32>>,
}

impl Frame {
    pub fn end_goal(&self) -> &[f32] {
        self.goals.last().map_or(&[], Vec::as_slice)
    }

    /// The subgoal that level `level` (>= 1) proposed, which level `level - 1` pursues.
    pub fn subgoal(&self, level: usize) -> &[f32] {
        &self.goals[level - 1]
    }
}

/// A [`Policy`] that acts exactly like `inner` and records a [`Frame`] per primitive action.
pub struct SubgoalRecorder<'a> {
    inner: &'a mut dyn Policy,
    goals: Vec<Vec<f32>>,
    frames: Vec<Frame>,
}

impl std::fmt::Debug for SubgoalRecorder<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SubgoalRecorder")
            .field("levels", &self.goals.len())
            .field("frames", &self.frames.len())
            .finish()
    }
}

impl<'a> SubgoalRecorder<'a> {
    /// Records the episodes of a `levels`-level hierarchy acting with `inner`.
    pub fn new(inner: &'a mut dyn Policy, levels: usize) -> Self {
        Self {
            inner,
            goals: vec![Vec::new(); levels],
            frames: Vec::new(),
        }
    }

    /// The frames so far, plus the final one: `final_state` (the state after the last action)
    /// with the goals in force at that last action.
    pub fn finish(mut self, final_state: &[f32]) -> Vec<Frame> {
        self.frames.push(Frame {
            step: self.frames.len(),
            state: final_state.to_vec(),
            goals: self.goals.clone(),
        });
        self.frames
    }
}

impl Policy for SubgoalRecorder<'_> {
    fn act(&mut self, level: usize, state: &[f32], goal: &[f32], action: &mut [f32]) {
        self.inner.act(level, state, goal, action);
        let current = &mut self.goals[level];
        current.clear();
        current.extend_from_slice(goal);
        if level == 0 {
            self.frames.push(Frame {
                step: self.frames.len(),
                state: state.to_vec(),
                goals: self.goals.clone(),
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use hac_core::{Env, GaussianExploration, Hierarchy, Mode, NullSink, Rng};
    use hac_tabular::FourRooms;

    use super::*;

    /// Level 1 proposes a cell two columns to the right of the agent, one row above the grid
    /// (so the rollout clips it); level 0 always moves right. Logs every call.
    #[derive(Default)]
    struct Scripted {
        calls: Vec<(usize, Vec<f32>, Vec<f32>)>,
    }

    impl Policy for Scripted {
        fn act(&mut self, level: usize, state: &[f32], goal: &[f32], action: &mut [f32]) {
            self.calls.push((level, state.to_vec(), goal.to_vec()));
            if level == 0 {
                action[0] = 3.0;
            } else {
                action.copy_from_slice(&[-1.0, state[1] + 2.0]);
            }
        }
    }

    #[test]
    fn records_state_end_goal_and_clipped_subgoal_per_primitive_action() {
        let mut env = FourRooms::new(10).unwrap();
        env.set_physical_state(&[0.0, 0.0]).unwrap();
        let mut config = env.default_config(2);
        config.horizon = 3;
        let spec = env.spec().clone();
        let mut hierarchy = Hierarchy::new(&spec, &config);
        let mut exploration = GaussianExploration::new(&spec, &config, Rng::seed_from(0));
        let mut inner = Scripted::default();
        let mut recorder = SubgoalRecorder::new(&mut inner, 2);
        let end_goal = [9.0, 9.0];
        let outcome = hierarchy.run_episode_from(
            &mut env,
            &end_goal,
            &mut recorder,
            &mut exploration,
            Mode::Test,
            &mut NullSink,
        );
        let frames = recorder.finish(env.state());

        assert_eq!(
            frames.len(),
            outcome.steps + 1,
            "one per action plus the last"
        );
        // Right along row 0 until the wall column at 5 stops the agent at (0, 4).
        assert_eq!(frames[0].state, [0.0, 0.0]);
        assert_eq!(frames[1].state, [0.0, 1.0]);
        assert_eq!(frames.last().unwrap().state, [0.0, 4.0]);
        for (i, f) in frames.iter().enumerate() {
            assert_eq!(f.step, i);
            assert_eq!(f.end_goal(), end_goal);
        }
        // Level 1 proposed [-1, 2] from (0, 0); the rollout clipped it to [0, 2], and level 0
        // pursued that until it got there at step 2.
        assert_eq!(frames[0].subgoal(1), [0.0, 2.0]);
        assert_eq!(frames[1].subgoal(1), [0.0, 2.0]);
        assert_eq!(
            frames[2].subgoal(1),
            [0.0, 4.0],
            "proposed anew from (0, 2)"
        );

        // The wrapper acted exactly like the policy: every level-0 call is a frame.
        let level0: Vec<_> = inner.calls.iter().filter(|c| c.0 == 0).collect();
        assert_eq!(level0.len(), outcome.steps);
        for (frame, (_, state, goal)) in frames.iter().zip(level0) {
            assert_eq!((&frame.state, &frame.goals[0]), (state, goal));
        }
    }
}
