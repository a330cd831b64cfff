//! Properties of the rollout over random seeds, level counts 1..=4 and settings, with a random
//! policy and HAC's own Gaussian exploration on a point environment.

use crate::common;

use common::{PointEnv, RandomPolicy, agent_config};
use hac_core::{
    Env, GaussianExploration, Hierarchy, Mode, OwnedTransition, Rng, TransitionKind, within_goal,
};
use proptest::prelude::*;

struct Run {
    env: PointEnv,
    horizon: usize,
    levels: usize,
    steps: usize,
    transitions: Vec<OwnedTransition>,
}

fn run(
    seed: u64,
    levels: usize,
    horizon: usize,
    max_actions: usize,
    lambda: f32,
    dim: usize,
) -> Run {
    // Small extent and coarse steps so goals are sometimes reached and sometimes missed.
    let mut env = PointEnv::new(dim, 0.5, 2.0, 0.3, max_actions);
    let mut config = agent_config(levels, horizon);
    config.subgoal_test_prob = lambda;
    let spec = env.spec.clone();
    let mut rng = Rng::seed_from(seed);
    let mut policy = RandomPolicy {
        rng: rng.fork(),
        bounds: (0..levels)
            .map(|l| spec.level_action_bounds(l).clone())
            .collect(),
    };
    let mut exploration = GaussianExploration::new(&spec, &config, rng.fork());
    let mut hierarchy = Hierarchy::new(&spec, &config);
    let mut transitions = Vec::new();
    let outcome = hierarchy.run_episode(
        &mut env,
        &mut policy,
        &mut exploration,
        Mode::Train,
        &mut rng,
        &mut transitions,
    );
    Run {
        env,
        horizon,
        levels,
        steps: outcome.steps,
        transitions,
    }
}

/// Splits one level's stream into calls: (attempt transitions, penalties, HER block).
fn calls(
    level_stream: &[&OwnedTransition],
) -> Vec<(Vec<OwnedTransition>, usize, Vec<OwnedTransition>)> {
    let mut out = Vec::new();
    let mut attempts = Vec::new();
    let mut penalties = 0;
    let mut her = Vec::new();
    for t in level_stream {
        match t.kind {
            TransitionKind::HindsightGoal => her.push((*t).clone()),
            _ if !her.is_empty() => {
                out.push((
                    std::mem::take(&mut attempts),
                    penalties,
                    std::mem::take(&mut her),
                ));
                penalties = 0;
                if t.kind == TransitionKind::SubgoalPenalty {
                    penalties += 1;
                } else {
                    attempts.push((*t).clone());
                }
            }
            TransitionKind::SubgoalPenalty => penalties += 1,
            TransitionKind::HindsightAction => attempts.push((*t).clone()),
        }
    }
    out.push((attempts, penalties, her));
    out
}

fn check(r: &Run) -> Result<(), TestCaseError> {
    let spec = r.env.spec().clone();
    let h = r.horizon as f32;
    let top = r.levels - 1;
    prop_assert!(
        r.steps <= spec.max_actions,
        "{} primitive actions > budget",
        r.steps
    );
    let mut calls_per_level = Vec::new();
    for level in 0..r.levels {
        let stream: Vec<&OwnedTransition> =
            r.transitions.iter().filter(|t| t.level == level).collect();
        let (threshold, angles) = spec.goal_test(level == top);
        for t in &stream {
            match t.kind {
                TransitionKind::SubgoalPenalty => {
                    prop_assert!(level > 0, "penalty at level 0");
                    prop_assert_eq!(t.reward, -h);
                    prop_assert!(t.terminal);
                }
                _ => {
                    prop_assert!(t.reward == 0.0 || t.reward == -1.0, "reward {}", t.reward);
                    // The point environment never terminates, so terminal means goal reached.
                    prop_assert_eq!(t.terminal, t.reward == 0.0);
                }
            }
            // Rewards agree with the goal test on the achieved goal of next_state.
            if t.kind != TransitionKind::SubgoalPenalty {
                let mut achieved = vec![0.0; t.goal.len()];
                if level == top {
                    r.env.project_end_goal(&t.next_state, &mut achieved);
                } else {
                    r.env.project_subgoal(&t.next_state, &mut achieved);
                }
                prop_assert_eq!(
                    t.reward == 0.0,
                    within_goal(&achieved, &t.goal, threshold, angles)
                );
            }
            let bounds = spec.level_action_bounds(level);
            prop_assert!(
                bounds.contains(&t.action),
                "level {} action {:?} outside bounds",
                level,
                t.action
            );
        }
        let level_calls = calls(&stream);
        for (attempts, penalties, her) in &level_calls {
            let n = attempts.len();
            // In training every level, the top one included, gets at most H attempts per call.
            prop_assert!(
                (1..=r.horizon).contains(&n),
                "level {} made {} attempts",
                level,
                n
            );
            prop_assert!(*penalties <= n);
            // HER: min(3, n) hindsight goals, each relabelling all n attempts.
            prop_assert_eq!(her.len(), 3.min(n) * n);
            for (g, block) in her.chunks(n).enumerate() {
                let goal = &block[0].goal;
                prop_assert!(block.iter().all(|t| &t.goal == goal));
                for (a, t) in attempts.iter().zip(block) {
                    prop_assert_eq!(&a.state, &t.state);
                    prop_assert_eq!(&a.action, &t.action);
                    prop_assert_eq!(&a.next_state, &t.next_state);
                }
                // The last block's goal is the last attempt's achieved goal.
                if g + 1 == 3.min(n) {
                    let mut achieved = vec![0.0; goal.len()];
                    let last = attempts.last().unwrap();
                    if level == top {
                        r.env.project_end_goal(&last.next_state, &mut achieved);
                    } else {
                        r.env.project_subgoal(&last.next_state, &mut achieved);
                    }
                    prop_assert_eq!(&achieved, goal);
                }
            }
        }
        calls_per_level.push(level_calls);
    }
    // Level i is called once per attempt of level i + 1; the top level once per episode.
    prop_assert_eq!(calls_per_level[top].len(), 1);
    for level in 0..top {
        let attempts_above: usize = calls_per_level[level + 1].iter().map(|c| c.0.len()).sum();
        prop_assert_eq!(calls_per_level[level].len(), attempts_above);
    }
    // Level 0's attempts are the primitive actions.
    let primitive: usize = calls_per_level[0].iter().map(|c| c.0.len()).sum();
    prop_assert_eq!(primitive, r.steps);
    // A penalty at level i follows a call of level i - 1 that used all H attempts and missed.
    for level in 1..r.levels {
        let stream: Vec<&OwnedTransition> =
            r.transitions.iter().filter(|t| t.level == level).collect();
        let lower_calls = &calls_per_level[level - 1];
        let mut attempt = 0usize;
        for t in &stream {
            match t.kind {
                TransitionKind::HindsightAction => attempt += 1,
                TransitionKind::SubgoalPenalty => {
                    let (lower_attempts, _, _) = &lower_calls[attempt - 1];
                    prop_assert_eq!(
                        lower_attempts.len(),
                        r.horizon,
                        "penalty without a maxed-out level below"
                    );
                    prop_assert!(lower_attempts.last().unwrap().reward == -1.0);
                    prop_assert_eq!(
                        &lower_attempts[0].goal,
                        &t.action,
                        "penalty action is the proposed subgoal"
                    );
                }
                TransitionKind::HindsightGoal => {}
            }
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    #[test]
    fn rollout_invariants(
        seed in any::<u64>(),
        levels in 1usize..=4,
        horizon in 1usize..=6,
        max_actions in 1usize..=300,
        lambda in prop_oneof![Just(0.0f32), Just(0.3f32), Just(1.0f32)],
        dim in 1usize..=2,
    ) {
        let r = run(seed, levels, horizon, max_actions, lambda, dim);
        check(&r)?;
        let penalties = r.transitions.iter().filter(|t| t.kind == TransitionKind::SubgoalPenalty).count();
        if lambda == 0.0 {
            prop_assert_eq!(penalties, 0, "penalty without subgoal testing");
        }
    }
}

#[test]
fn penalties_appear_when_testing_everything() {
    // With lambda = 1 and random subgoals, tested subgoals are missed often: penalties must occur.
    let total: usize = (0..20)
        .map(|seed| {
            run(seed, 2, 5, 200, 1.0, 2)
                .transitions
                .iter()
                .filter(|t| t.kind == TransitionKind::SubgoalPenalty)
                .count()
        })
        .sum();
    assert!(total > 0);
}

#[test]
fn same_seed_same_transitions() {
    let a = run(9, 3, 4, 200, 0.3, 2);
    let b = run(9, 3, 4, 200, 0.3, 2);
    assert_eq!(a.transitions, b.transitions);
    assert!(!a.transitions.is_empty());
}
