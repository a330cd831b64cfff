//! HIRO's episode on a point moved by its actions (the position is the state, the subgoal
//! projection and the end-goal projection): what the two levels store, step by step.

use crate::common;

use std::collections::VecDeque;

use common::{PointEnv, ScriptedExploration, ScriptedPolicy};
use hac_core::hiro::{HighTransition, HiroRollout, HiroSink, TaskReward};
use hac_core::{Mode, OwnedTransition, Rng, Transition, TransitionSink};

/// What the sink received: low-level transitions, and the high level's as plain vectors.
#[derive(Debug, Default)]
struct Kept {
    low: Vec<OwnedTransition>,
    high: Vec<High>,
}

#[derive(Debug, Clone, PartialEq)]
struct High {
    state: Vec<f32>,
    action: Vec<f32>,
    reward: f32,
    next_state: Vec<f32>,
    goal: Vec<f32>,
    terminal: bool,
    states: Vec<f32>,
    achieved: Vec<f32>,
    actions: Vec<f32>,
}

impl HiroSink for Kept {
    fn push_low(&mut self, t: &Transition<'_>) {
        TransitionSink::push(&mut self.low, 0, t);
    }

    fn push_high(&mut self, h: &HighTransition<'_>) {
        let t = &h.transition;
        self.high.push(High {
            state: t.state.to_vec(),
            action: t.action.to_vec(),
            reward: t.reward,
            next_state: t.next_state.to_vec(),
            goal: t.goal.to_vec(),
            terminal: t.terminal,
            states: h.steps.states.to_vec(),
            achieved: h.steps.achieved.to_vec(),
            actions: h.steps.actions.to_vec(),
        });
    }
}

/// A point starting at 0 that moves +1 per step towards `end_goal`, under a high level that
/// always proposes `high_output` (relative) every `c` steps.
fn run(
    c: usize,
    max_actions: usize,
    end_goal: f32,
    high_output: f32,
    mode: Mode,
) -> (Kept, bool, usize) {
    run_rewarded(
        c,
        max_actions,
        end_goal,
        high_output,
        mode,
        TaskReward::Sparse,
    )
}

/// [`run`] with the high level rewarded by `reward`.
fn run_rewarded(
    c: usize,
    max_actions: usize,
    end_goal: f32,
    high_output: f32,
    mode: Mode,
    reward: TaskReward,
) -> (Kept, bool, usize) {
    let mut env = PointEnv::new(1, 2.0, 10.0, 0.1, max_actions);
    env.start = Some(vec![0.0]);
    env.end_goal = Some(vec![end_goal]);
    let mut rollout = HiroRollout::new(&env.spec, c).with_task_reward(reward);
    let mut policy = ScriptedPolicy {
        outputs: vec![
            VecDeque::from([vec![1.0]]),
            VecDeque::from([vec![high_output]]),
        ],
    };
    let mut exploration = ScriptedExploration {
        perturbation: vec![vec![0.0], vec![0.0]],
        ..ScriptedExploration::default()
    };
    let mut kept = Kept::default();
    let outcome = rollout.run_episode(
        &mut env,
        &mut policy,
        &mut exploration,
        mode,
        &mut Rng::seed_from(0),
        &mut kept,
    );
    (kept, outcome.success, outcome.steps)
}

#[test]
fn the_low_level_is_rewarded_by_the_goal_carried_along() {
    let (kept, success, steps) = run(3, 7, 100.0, 2.0, Mode::Train);
    assert!(!success);
    assert_eq!(steps, 7);
    // (state, goal, reward, next_state): each decision proposes +2 from where it is; the goal
    // moves with the state (2, 1, 0, then 2 again at the next decision).
    let expected = [
        (0.0, 2.0, -1.0, 1.0),
        (1.0, 1.0, 0.0, 2.0),
        (2.0, 0.0, -1.0, 3.0),
        (3.0, 2.0, -1.0, 4.0),
        (4.0, 1.0, 0.0, 5.0),
        (5.0, 0.0, -1.0, 6.0),
        (6.0, 2.0, -1.0, 7.0),
    ];
    assert_eq!(kept.low.len(), expected.len());
    for (t, (s, g, r, s2)) in kept.low.iter().zip(expected) {
        assert_eq!(
            (
                t.state[0],
                t.goal[0],
                t.reward,
                t.next_state[0],
                t.action[0]
            ),
            (s, g, r, s2, 1.0),
            "{t:?}"
        );
        assert!(!t.terminal);
    }
}

#[test]
fn the_high_level_stores_each_decision_with_its_steps() {
    let (kept, _, _) = run(3, 7, 100.0, 2.0, Mode::Train);
    let segment = |start: f32, len: usize| High {
        state: vec![start],
        action: vec![2.0],
        reward: -(len as f32),
        next_state: vec![start + len as f32],
        goal: vec![100.0],
        terminal: false,
        states: (0..len).map(|i| start + i as f32).collect(),
        achieved: (0..=len).map(|i| start + i as f32).collect(),
        actions: vec![1.0; len],
    };
    // The budget of 7 ends the last decision after one step; not reaching the goal is not
    // terminal.
    assert_eq!(
        kept.high,
        vec![segment(0.0, 3), segment(3.0, 3), segment(6.0, 1)]
    );
}

#[test]
fn reaching_the_end_goal_ends_the_episode_with_a_terminal_high_transition() {
    let (kept, success, steps) = run(3, 100, 5.0, 2.0, Mode::Train);
    assert!(success);
    assert_eq!(steps, 5);
    assert_eq!(kept.low.len(), 5);
    assert_eq!(kept.high.len(), 2);
    let last = &kept.high[1];
    // -1 for the step to 4, 0 for the step that reaches 5.
    assert_eq!((last.reward, last.terminal), (-1.0, true));
    assert_eq!(last.next_state, vec![5.0]);
    assert_eq!(last.states, vec![3.0, 4.0]);
    // The low level's transitions are not terminal: the point does not end the episode itself.
    assert!(kept.low.iter().all(|t| !t.terminal));
}

#[test]
fn the_distance_reward_sums_each_steps_distance_to_the_end_goal() {
    let (kept, success, steps) = run_rewarded(3, 100, 5.0, 2.0, Mode::Train, TaskReward::Distance);
    // The same episode as with the sparse reward: success and its end are the goal test's.
    assert!(success);
    assert_eq!(steps, 5);
    let rewards: Vec<(f32, bool)> = kept.high.iter().map(|h| (h.reward, h.terminal)).collect();
    // After the steps to 1, 2, 3: 4 + 3 + 2 left; after those to 4 and 5: 1 + 0.
    assert_eq!(rewards, vec![(-9.0, false), (-1.0, true)]);
    // The low level's intrinsic rewards do not depend on the high level's.
    let (sparse, _, _) = run(3, 100, 5.0, 2.0, Mode::Train);
    assert_eq!(kept.low, sparse.low);
}

#[test]
fn relative_goals_are_clipped_to_the_subgoal_half_range() {
    let (kept, _, _) = run(3, 3, 100.0, 5000.0, Mode::Train);
    // Subgoal bounds [-10, 10]: relative goals in [-10, 10].
    assert_eq!(kept.high[0].action, vec![10.0]);
    assert_eq!(kept.low[0].goal, vec![10.0]);
}

#[test]
fn test_episodes_store_nothing() {
    let (kept, success, steps) = run(3, 100, 5.0, 2.0, Mode::Test);
    assert!(success);
    assert_eq!(steps, 5);
    assert!(kept.low.is_empty() && kept.high.is_empty());
}
