//! `Episodes::moved_end_goal`: whether an episode's last state achieves a different end goal
//! than its first (beyond the end goal's thresholds), for HAC's hierarchy and HIRO's rollout.

use crate::common;

use std::collections::VecDeque;

use common::{PointEnv, ScriptedExploration, ScriptedPolicy, agent_config};
use hac_core::hiro::HiroConfig;
use hac_core::{Episodes, Mode, NullSink, Rng};

/// A point on a line from 0, threshold 0.1, 4 actions per episode, an end goal it never reaches.
fn env() -> PointEnv {
    let mut env = PointEnv::new(1, 0.05, 1.0, 0.1, 4);
    env.start = Some(vec![0.0]);
    env.end_goal = Some(vec![0.9]);
    env
}

/// Plays one greedy episode in which level 0 always outputs `step` (and, for HIRO, level 1 a
/// relative goal of 0); returns the rollout.
fn play(hiro: bool, step: &[f32]) -> Episodes {
    let mut env = env();
    let (levels, hiro) = if hiro {
        (
            2,
            Some(HiroConfig {
                c: 2,
                ..HiroConfig::default()
            }),
        )
    } else {
        (1, None)
    };
    let config = agent_config(levels, 4);
    let mut rollout = Episodes::new(&env.spec, &config, hiro.as_ref());
    let mut outputs = vec![VecDeque::from(vec![step.to_vec()])];
    if levels == 2 {
        outputs.push(VecDeque::from(vec![vec![0.0]]));
    }
    let mut policy = ScriptedPolicy { outputs };
    let mut exploration = ScriptedExploration::default();
    let outcome = rollout.run_episode(
        &mut env,
        &mut policy,
        &mut exploration,
        Mode::Test,
        &mut Rng::seed_from(1),
        &mut NullSink,
    );
    assert_eq!(outcome.steps, 4);
    assert!(!outcome.success);
    rollout
}

#[test]
fn an_episode_that_moves_the_end_goals_measure_past_its_threshold_is_counted() {
    for hiro in [false, true] {
        let moved = play(hiro, &[0.05]);
        assert_eq!(moved.start_achieved(), &[0.0]);
        assert!(
            (moved.final_achieved()[0] - 0.2).abs() < 1e-6,
            "hiro {hiro}"
        );
        assert!(moved.moved_end_goal(), "hiro {hiro}: 0.2 from the start");

        let still = play(hiro, &[0.02]);
        assert!(
            (still.final_achieved()[0] - 0.08).abs() < 1e-6,
            "hiro {hiro}"
        );
        assert!(!still.moved_end_goal(), "hiro {hiro}: 0.08 is within 0.1");

        let back = play(hiro, &[-0.05]);
        assert!(back.moved_end_goal(), "hiro {hiro}: either direction");
    }
}
