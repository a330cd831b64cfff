//! The unchanged core rollout driven by the tabular agent and its exploration on a tiny grid:
//! every transition is one of HAC's three kinds with the rewards and cells they must have.

use hac_core::{Env, Hierarchy, Mode, OwnedTransition, Rng, TransitionKind};
use hac_tabular::{FourRooms, TabularAgent, TabularConfig};
use proptest::prelude::*;

/// Runs `episodes` training episodes of `levels` levels on the 5 x 5 grid, with the agent
/// learning between episodes; returns every transition and the total number of moves.
fn rollout(levels: usize, seed: u64, episodes: usize) -> (Vec<OwnedTransition>, usize, usize) {
    let mut env = FourRooms::new(5).unwrap();
    let config = env.default_config(levels);
    let mut rng = Rng::seed_from(seed);
    let tabular = TabularConfig::default();
    let mut agent = TabularAgent::new(env.grid(), &config, &tabular, rng.fork()).unwrap();
    let mut exploration = agent.exploration(&config, rng.fork());
    let mut hierarchy = Hierarchy::new(env.spec(), &config);
    let (mut all, mut steps) = (Vec::new(), 0);
    for _ in 0..episodes {
        let mut episode: Vec<OwnedTransition> = Vec::new();
        let outcome = hierarchy.run_episode(
            &mut env,
            &mut agent,
            &mut exploration,
            Mode::Train,
            &mut rng,
            &mut episode,
        );
        steps += outcome.steps;
        for t in &episode {
            let tr = hac_core::Transition {
                kind: t.kind,
                state: &t.state,
                action: &t.action,
                reward: t.reward,
                next_state: &t.next_state,
                goal: &t.goal,
                terminal: t.terminal,
                extra: &[],
            };
            assert!(agent.update(t.level, &tr), "no table slot for {t:?}");
        }
        all.extend(episode);
    }
    (all, steps, config.horizon)
}

fn check(transitions: &[OwnedTransition], steps: usize, horizon: usize, levels: usize) {
    let grid = FourRooms::new(5).unwrap().grid().clone();
    let free = |x: &[f32]| grid.index_of_point(x).is_some() && x.iter().all(|v| v.fract() == 0.0);
    let h = horizon as f32;
    for t in transitions {
        assert!(t.level < levels);
        assert!([-1.0, 0.0, -h].contains(&t.reward), "{t:?}");
        assert!(
            free(&t.state) && free(&t.next_state) && free(&t.goal),
            "{t:?}"
        );
        match t.kind {
            TransitionKind::HindsightAction | TransitionKind::HindsightGoal => {
                // Reward 0 and terminal exactly when the next cell is the goal cell.
                let reached = t.next_state == t.goal;
                assert_eq!(t.reward == 0.0, reached, "{t:?}");
                assert_eq!(t.terminal, reached, "{t:?}");
                if t.level == 0 {
                    assert!([0.0, 1.0, 2.0, 3.0].contains(&t.action[0]), "{t:?}");
                } else {
                    // The subgoal if it was reached, else the cell achieved: the next cell.
                    assert_eq!(t.action, t.next_state, "{t:?}");
                }
            }
            TransitionKind::SubgoalPenalty => {
                assert!(t.level > 0, "{t:?}");
                assert_eq!(t.reward, -h);
                assert!(t.terminal);
                assert!(free(&t.action), "{t:?}");
                assert_ne!(t.action, t.next_state, "a penalty for a missed subgoal");
            }
        }
    }
    let moves = transitions
        .iter()
        .filter(|t| t.level == 0 && t.kind == TransitionKind::HindsightAction)
        .count();
    assert_eq!(moves, steps, "one hindsight action transition per move");
}

#[test]
fn every_kind_appears_at_the_right_levels() {
    for levels in 1..=3 {
        let (transitions, steps, horizon) = rollout(levels, 11, 60);
        check(&transitions, steps, horizon, levels);
        let kinds = |kind| transitions.iter().filter(move |t| t.kind == kind);
        assert!(kinds(TransitionKind::HindsightAction).count() > 0);
        assert!(kinds(TransitionKind::HindsightGoal).count() > 0);
        let penalties = kinds(TransitionKind::SubgoalPenalty).count();
        assert_eq!(
            penalties > 0,
            levels > 1,
            "{levels} levels: {penalties} penalties"
        );
        for level in 0..levels {
            assert!(
                transitions
                    .iter()
                    .any(|t| t.level == level && t.reward == 0.0)
            );
            assert!(
                transitions
                    .iter()
                    .any(|t| t.level == level && t.reward == -1.0)
            );
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn transitions_keep_their_invariants(seed in any::<u64>(), levels in 1usize..=3) {
        let (transitions, steps, horizon) = rollout(levels, seed, 10);
        check(&transitions, steps, horizon, levels);
    }
}

#[test]
fn same_seed_same_transitions() {
    assert_eq!(rollout(3, 5, 20), rollout(3, 5, 20));
}
