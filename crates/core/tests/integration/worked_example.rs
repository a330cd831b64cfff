//! The paper's worked example (section 3.8), rebuilt exactly: two levels, H = 5. Level 1 proposes
//! g0 untested; level 0 acts 5 times with noise and misses. Level 1 then proposes g2 and tests it;
//! level 0 acts greedily 5 times and misses, so level 1 is penalised. Every transition is checked.

use crate::common;

use std::collections::VecDeque;

use common::{PointEnv, ScriptedExploration, ScriptedPolicy, agent_config};
use hac_core::{EpisodeOutcome, Hierarchy, LevelCounts, Mode, OwnedTransition, TransitionKind};

const FLAG: f32 = 100.0;

// One argument per field of the paper's tuple `[s, a, r, s', g, terminal]`, plus level and kind.
#[allow(clippy::too_many_arguments)]
fn t(
    level: usize,
    kind: TransitionKind,
    s: f32,
    a: f32,
    r: f32,
    s2: f32,
    g: f32,
    term: bool,
) -> OwnedTransition {
    OwnedTransition {
        level,
        kind,
        state: vec![s],
        action: vec![a],
        reward: r,
        next_state: vec![s2],
        goal: vec![g],
        terminal: term,
        extra: Vec::new(),
    }
}

/// Runs one training episode of `hierarchy` toward the end goal [`FLAG`] (never reached) and
/// returns its outcome and every transition it stored.
fn train_toward_flag(
    hierarchy: &mut Hierarchy,
    env: &mut PointEnv,
    policy: &mut ScriptedPolicy,
    exploration: &mut ScriptedExploration,
) -> (EpisodeOutcome, Vec<OwnedTransition>) {
    let mut got = Vec::new();
    let outcome =
        hierarchy.run_episode_from(env, &[FLAG], policy, exploration, Mode::Train, &mut got);
    (outcome, got)
}

/// Level `level`'s transitions in `got` whose kind passes `keep`, in order.
fn of_level(
    got: &[OwnedTransition],
    level: usize,
    keep: impl Fn(TransitionKind) -> bool,
) -> Vec<&OwnedTransition> {
    got.iter()
        .filter(|t| t.level == level && keep(t.kind))
        .collect()
}

/// The HER block of one call: every attempt relabelled with each picked achieved goal.
fn her_block(level: usize, attempts: &[(f32, f32, f32)], picks: &[usize]) -> Vec<OwnedTransition> {
    let mut out = Vec::new();
    for &p in picks {
        let goal = attempts[p].2;
        for &(s, a, s2) in attempts {
            let hit = s2 == goal;
            out.push(t(
                level,
                TransitionKind::HindsightGoal,
                s,
                a,
                if hit { 0.0 } else { -1.0 },
                s2,
                goal,
                hit,
            ));
        }
    }
    out
}

#[test]
fn section_3_8_worked_example() {
    use TransitionKind::*;
    // Positions move by the action; 10 primitive actions end the episode after level 1's second
    // attempt, exactly the span the paper walks through.
    let mut env = PointEnv::new(1, 2.0, 1000.0, 0.1, 10);
    let mut config = agent_config(2, 5);
    config.num_replay_goals = 3;
    let mut policy = ScriptedPolicy {
        outputs: vec![
            VecDeque::from([vec![1.0]]),              // level 0: always +1
            VecDeque::from([vec![10.0], vec![20.0]]), // level 1: g0 = 10, then g2 = 20
        ],
    };
    let mut exploration = ScriptedExploration {
        perturbation: vec![vec![0.5], vec![0.0]], // level 0's "noise": +0.5
        tests: vec![VecDeque::new(), VecDeque::from([false, true])],
        // level 0 first call: 1, 3 (+ last); second call: 0, 2 (+ last); level 1: 0 (+ last).
        replay_indices: VecDeque::from([1, 3, 0, 2, 0]),
    };
    let mut hierarchy = Hierarchy::new(&env.spec.clone(), &config);
    let (outcome, got) = train_toward_flag(&mut hierarchy, &mut env, &mut policy, &mut exploration);
    assert_eq!(outcome.steps, 10);
    assert!(!outcome.success);

    let mut want = Vec::new();
    // Level 1, attempt 1: subgoal g0 = 10, untested. Level 0 acts with noise: 1.5 per step.
    let first: Vec<(f32, f32, f32)> = (0..5)
        .map(|j| (1.5 * j as f32, 1.5, 1.5 * (j + 1) as f32))
        .collect();
    for &(s, a, s2) in &first {
        want.push(t(0, HindsightAction, s, a, -1.0, s2, 10.0, false));
    }
    want.extend(her_block(0, &first, &[1, 3, 4]));
    // Level 1 records [s0, s1, -1, s1, flag, no]: the achieved state replaces the missed subgoal.
    want.push(t(1, HindsightAction, 0.0, 7.5, -1.0, 7.5, FLAG, false));
    // Level 1, attempt 2: subgoal g2 = 20, tested. Level 0 acts greedily: +1 per step, misses.
    let second: Vec<(f32, f32, f32)> = (0..5)
        .map(|j| (7.5 + j as f32, 1.0, 8.5 + j as f32))
        .collect();
    for &(s, a, s2) in &second {
        want.push(t(0, HindsightAction, s, a, -1.0, s2, 20.0, false));
    }
    want.extend(her_block(0, &second, &[0, 2, 4]));
    // Hindsight action [s2, s3, -1, s3, flag, no], then the penalty [s2, g2, -H, s3, flag, yes].
    want.push(t(1, HindsightAction, 7.5, 12.5, -1.0, 12.5, FLAG, false));
    want.push(t(1, SubgoalPenalty, 7.5, 20.0, -5.0, 12.5, FLAG, true));
    // Level 1 returns (budget spent); HER over its two attempts: one random pick (0) plus the last.
    want.extend(her_block(1, &[(0.0, 7.5, 7.5), (7.5, 12.5, 12.5)], &[0, 1]));

    assert_eq!(got.len(), want.len(), "transition count");
    for (i, (g, w)) in got.iter().zip(&want).enumerate() {
        assert_eq!(g, w, "transition {i} differs");
    }
    assert!(
        exploration.replay_indices.is_empty(),
        "every scripted replay index was used"
    );
    // Level 0 was called twice and maxed out both times (5 actions each); level 1 made two
    // attempts in one call, tested one subgoal and was penalised for it, and ran out of budget
    // without reaching its goal (not maxed out: 2 of H = 5 attempts).
    assert_eq!(
        *hierarchy.level_counts(0),
        LevelCounts {
            calls: 2,
            reached: 0,
            maxed_out: 2,
            attempts: 10,
            tested: 0,
            penalties: 0,
        }
    );
    assert_eq!(
        *hierarchy.level_counts(1),
        LevelCounts {
            calls: 1,
            reached: 0,
            maxed_out: 0,
            attempts: 2,
            tested: 1,
            penalties: 1,
        }
    );
}

#[test]
fn reached_subgoal_is_its_own_hindsight_action_and_test_passes_without_penalty() {
    use TransitionKind::*;
    // Level 1 proposes 3.0 (tested); level 0 moves +1 greedily and reaches it in 3 attempts.
    let mut env = PointEnv::new(1, 2.0, 1000.0, 0.1, 3);
    let config = agent_config(2, 5);
    let mut policy = ScriptedPolicy {
        outputs: vec![VecDeque::from([vec![1.0]]), VecDeque::from([vec![3.0]])],
    };
    let mut exploration = ScriptedExploration {
        perturbation: vec![vec![0.0], vec![0.0]],
        tests: vec![VecDeque::new(), VecDeque::from([true])],
        replay_indices: VecDeque::from([0, 0, 0]),
    };
    let mut hierarchy = Hierarchy::new(&env.spec.clone(), &config);
    let (_, got) = train_toward_flag(&mut hierarchy, &mut env, &mut policy, &mut exploration);
    let level0_ha = of_level(&got, 0, |k| k == HindsightAction);
    assert_eq!(
        level0_ha.len(),
        3,
        "level 0 returns as soon as its goal is reached"
    );
    assert_eq!(
        *level0_ha[2],
        t(0, HindsightAction, 2.0, 1.0, 0.0, 3.0, 3.0, true)
    );
    let level1 = of_level(&got, 1, |k| k != HindsightGoal);
    assert_eq!(
        level1,
        vec![&t(1, HindsightAction, 0.0, 3.0, -1.0, 3.0, FLAG, false)]
    );
    // The tested subgoal was reached: counted as tested, not penalised.
    let (low, high) = (hierarchy.level_counts(0), hierarchy.level_counts(1));
    assert_eq!(
        (low.calls, low.reached, low.maxed_out, low.attempts),
        (1, 1, 0, 3)
    );
    assert_eq!((high.tested, high.penalties), (1, 0));
    assert_eq!(low.reached_rate(), 1.0);
    assert_eq!(high.penalty_rate(), 0.0);
}

#[test]
fn test_mode_is_greedy_stores_nothing_and_top_level_ignores_horizon() {
    let mut env = PointEnv::new(1, 2.0, 1000.0, 0.1, 37);
    let config = agent_config(2, 5);
    let mut policy = ScriptedPolicy {
        outputs: vec![VecDeque::from([vec![1.0]]), VecDeque::from([vec![500.0]])],
    };
    // Any exploration call would panic: the scripts are empty.
    let mut exploration = ScriptedExploration::default();
    let mut hierarchy = Hierarchy::new(&env.spec.clone(), &config);
    let mut got: Vec<OwnedTransition> = Vec::new();
    let outcome = hierarchy.run_episode_from(
        &mut env,
        &[FLAG],
        &mut policy,
        &mut exploration,
        Mode::Test,
        &mut got,
    );
    assert!(got.is_empty());
    // 37 > H * H = 25: the top level kept proposing subgoals until the budget ran out.
    assert_eq!(outcome.steps, 37);
    assert_eq!(env.x, vec![37.0]);
}

#[test]
fn episode_ends_when_end_goal_reached() {
    let mut env = PointEnv::new(1, 2.0, 1000.0, 0.1, 100);
    let config = agent_config(2, 5);
    let mut policy = ScriptedPolicy {
        outputs: vec![VecDeque::from([vec![1.0]]), VecDeque::from([vec![50.0]])],
    };
    let mut exploration = ScriptedExploration::default();
    let mut hierarchy = Hierarchy::new(&env.spec.clone(), &config);
    let outcome = hierarchy.run_episode_from(
        &mut env,
        &[7.0],
        &mut policy,
        &mut exploration,
        Mode::Test,
        &mut hac_core::NullSink,
    );
    assert!(outcome.success);
    assert_eq!(outcome.steps, 7);
}

#[test]
fn environment_termination_ends_the_episode_and_stops_bootstrapping() {
    use TransitionKind::*;
    // Level 0 moves +1 towards subgoal 10; the environment terminates at x >= 3.
    let mut env = PointEnv::new(1, 2.0, 1000.0, 0.1, 100);
    env.terminate_at = Some(3.0);
    let config = agent_config(2, 5);
    let mut policy = ScriptedPolicy {
        outputs: vec![VecDeque::from([vec![1.0]]), VecDeque::from([vec![10.0]])],
    };
    let mut exploration = ScriptedExploration {
        perturbation: vec![vec![0.0], vec![0.0]],
        tests: vec![VecDeque::new(), VecDeque::from([false])],
        replay_indices: VecDeque::from([0, 0, 0]),
    };
    let mut hierarchy = Hierarchy::new(&env.spec.clone(), &config);
    let (outcome, got) = train_toward_flag(&mut hierarchy, &mut env, &mut policy, &mut exploration);
    assert_eq!(outcome.steps, 3);
    assert!(!outcome.success);
    let level0 = of_level(&got, 0, |k| k == HindsightAction);
    // Missed goal, reward -1; only the step into the terminal state stops bootstrapping.
    assert_eq!(
        level0.iter().map(|t| t.terminal).collect::<Vec<_>>(),
        [false, false, true]
    );
    assert!(level0.iter().all(|t| t.reward == -1.0));
    // HER copies keep the flag of the attempt they copy (or are terminal because reached).
    for t in got.iter().filter(|t| t.kind == HindsightGoal) {
        let reached = t.next_state == t.goal;
        assert_eq!(t.terminal, reached || t.next_state == [3.0], "{t:?}");
    }
    let level1: Vec<_> = got
        .iter()
        .filter(|t| t.level == 1 && t.kind == HindsightAction)
        .collect();
    assert_eq!(
        *level1[0],
        t(1, HindsightAction, 0.0, 3.0, -1.0, 3.0, FLAG, true)
    );
}

#[test]
fn angle_goals_are_reached_one_turn_away() {
    use TransitionKind::*;
    use std::f32::consts::TAU;
    // The point's coordinate read as an angle: level 1 proposes 3 + 2 pi (tested), level 0 moves
    // +1 greedily and reaches it along the circle at 3.0; the end goal 7 - 2 pi is reached at 7.
    let mut env = PointEnv::new(1, 2.0, 1000.0, 0.1, 100);
    env.spec.end_goal_angles = vec![true];
    env.spec.subgoal_angles = vec![true];
    let config = agent_config(2, 5);
    let subgoal = 3.0 + TAU;
    let mut policy = ScriptedPolicy {
        outputs: vec![
            VecDeque::from([vec![1.0]]),
            VecDeque::from([vec![subgoal], vec![subgoal + 4.0]]),
        ],
    };
    let mut exploration = ScriptedExploration {
        perturbation: vec![vec![0.0], vec![0.0]],
        tests: vec![VecDeque::new(), VecDeque::from([true, false])],
        replay_indices: VecDeque::from([0; 8]),
    };
    let mut hierarchy = Hierarchy::new(&env.spec.clone(), &config);
    let mut got: Vec<OwnedTransition> = Vec::new();
    let outcome = hierarchy.run_episode_from(
        &mut env,
        &[7.0 - TAU],
        &mut policy,
        &mut exploration,
        Mode::Train,
        &mut got,
    );
    assert!(outcome.success);
    assert_eq!(outcome.steps, 7);
    let level0 = of_level(&got, 0, |k| k == HindsightAction);
    // The third move reaches the subgoal: reward 0, terminal, and level 0 returns.
    assert_eq!(
        *level0[2],
        t(0, HindsightAction, 2.0, 1.0, 0.0, 3.0, subgoal, true)
    );
    // Level 1: the tested subgoal was reached, so it is its own hindsight action and there is no
    // penalty; the second attempt reaches the end goal.
    let level1 = of_level(&got, 1, |k| k != HindsightGoal);
    assert_eq!(
        level1,
        vec![
            &t(
                1,
                HindsightAction,
                0.0,
                subgoal,
                -1.0,
                3.0,
                7.0 - TAU,
                false
            ),
            &t(
                1,
                HindsightAction,
                3.0,
                subgoal + 4.0,
                0.0,
                7.0,
                7.0 - TAU,
                true
            ),
        ]
    );
    // HER at level 0 of the first call relabels with the achieved 1.0 (pick 0) and 3.0 (last);
    // rewards compare along the circle as well, so nothing else counts as reached.
    let her0: Vec<_> = of_level(&got, 0, |k| k == HindsightGoal)
        .into_iter()
        .filter(|t| t.goal == [3.0])
        .map(|t| t.reward)
        .collect();
    assert_eq!(her0, [-1.0, -1.0, 0.0]);
}

#[test]
fn clip_hindsight_actions_keeps_a_missed_subgoals_hindsight_action_in_the_subgoal_bounds() {
    use TransitionKind::*;
    // Subgoals within +-5; level 1 proposes 4.9, level 0 moves +2 per step and ends at 10 after
    // its 5 attempts, beyond the bounds. By default the hindsight action is the achieved 10 (the
    // paper's); with the key it is clipped to 5, in the HER copies too.
    for (clip, want) in [(false, 10.0), (true, 5.0)] {
        // The environment projects without clipping (its own subgoal box is +-1000); the run's
        // subgoal bounds, which the hierarchy's spec holds, are +-5.
        let mut env = PointEnv::new(1, 2.0, 1000.0, 0.1, 5);
        let mut spec = env.spec.clone();
        spec.subgoal_bounds = hac_core::Bounds::symmetric(&[5.0]);
        let mut config = agent_config(2, 5);
        config.clip_hindsight_actions = clip;
        let mut policy = ScriptedPolicy {
            outputs: vec![VecDeque::from([vec![2.0]]), VecDeque::from([vec![4.9]])],
        };
        let mut exploration = ScriptedExploration {
            perturbation: vec![vec![0.0], vec![0.0]],
            tests: vec![VecDeque::new(), VecDeque::from([false])],
            replay_indices: VecDeque::from([0, 0, 0]),
        };
        let mut hierarchy = Hierarchy::new(&spec, &config);
        let (_, got) = train_toward_flag(&mut hierarchy, &mut env, &mut policy, &mut exploration);
        let level1 = of_level(&got, 1, |_| true);
        assert_eq!(
            level1[0],
            &t(1, HindsightAction, 0.0, want, -1.0, 10.0, FLAG, false),
            "clip_hindsight_actions = {clip}"
        );
        assert!(level1.len() > 1, "HER copies follow");
        assert!(
            level1.iter().all(|t| t.action == [want]),
            "clip_hindsight_actions = {clip}: {level1:?}"
        );
        // Level 0's actions are primitive: never touched.
        assert!(
            of_level(&got, 0, |_| true)
                .iter()
                .all(|t| t.action == [2.0])
        );
    }
}
