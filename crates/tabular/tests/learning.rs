//! Tabular HAC learns four-rooms: CI-sized runs with a fixed seed.
//!
//! Thresholds come from 30 seeds of the same run (200 greedy test episodes each): before
//! training at most 0.135 success; after 400 training episodes at least 0.815 with 2 levels
//! (mean 0.87) and at least 0.65 with 3 levels (mean 0.72).

use hac_core::{Env, Rng};
use hac_tabular::{FourRooms, TabularConfig, TabularHac};

fn success_before_and_after(levels: usize, episodes: usize, seed: u64) -> (f32, f32) {
    let mut env = FourRooms::new(10).unwrap();
    let config = env.default_config(levels);
    let mut rng = Rng::seed_from(seed);
    let mut eval_rng = rng.fork();
    let mut learner = TabularHac::new(&env, config, &TabularConfig::default(), &mut rng).unwrap();
    let before = learner.success_rate(&mut env, &mut eval_rng, 200);
    for _ in 0..episodes {
        learner.train_episode(&mut env, &mut rng);
    }
    let after = learner.success_rate(&mut env, &mut eval_rng, 200);
    // With subgoal radius H^i no hindsight subgoal falls outside the tables.
    assert_eq!(learner.agent().skipped(), 0);
    assert!(learner.agent().updates() > 0);
    (before, after)
}

#[test]
fn two_levels_learn_four_rooms_10x10() {
    let (before, after) = success_before_and_after(2, 400, 1);
    println!("2 levels: greedy success {before:.3} before, {after:.3} after 400 episodes");
    assert!(before < 0.2, "before {before}");
    assert!(after > 0.6, "after {after}");
}

#[test]
fn three_levels_learn_four_rooms_10x10() {
    let (before, after) = success_before_and_after(3, 400, 1);
    println!("3 levels: greedy success {before:.3} before, {after:.3} after 400 episodes");
    assert!(before < 0.2, "before {before}");
    assert!(after > 0.45, "after {after}");
}
