//! The pick-and-place physics at full size: the scripted grasp over 200 random episodes (each
//! allowed 100 actions), a block dropped from 0.2 m (rest height, then drift over 5 s), a held
//! block shaken by 200 full-speed moves (its largest displacement in the hand), the pads' sinking
//! under the squeeze, and the speed of all of it on one core.
//!
//! `cargo run --release -p hac-envs --example pick_and_place_grasp`

use std::time::Instant;

use hac_core::{Env, Mode, Rng};
use hac_envs::pick_and_place::{PickAndPlace, ScriptedGrasp};

const EPISODES: usize = 200;
const ACTIONS_PER_EPISODE: usize = 100;

fn main() {
    let mut env = PickAndPlace::new();
    let threshold = env.spec().end_goal_thresholds.clone();
    let mut rng = Rng::seed_from(0);
    let mut goal = [0.0f32; 3];
    let (mut successes, mut actions_to_success, mut actions) = (0, 0, 0);
    let started = Instant::now();
    for _ in 0..EPISODES {
        env.reset(&mut rng);
        env.sample_end_goal(&mut rng, Mode::Train, &mut goal);
        let mut script = ScriptedGrasp::new();
        for t in 1..=ACTIONS_PER_EPISODE {
            let a = script.act(env.state(), &goal);
            env.step(&a);
            actions += 1;
            let s = env.state();
            if (0..3).all(|i| (s[4 + i] - goal[i]).abs() <= threshold[i]) {
                successes += 1;
                actions_to_success += t;
                break;
            }
        }
    }
    let rate = actions as f64 / started.elapsed().as_secs_f64();
    println!(
        "scripted grasp: {successes}/{EPISODES} episodes reach the goal within \
         {ACTIONS_PER_EPISODE} actions (mean {:.1} actions when they do); {actions} actions at \
         {rate:.0} actions/s",
        actions_to_success as f64 / successes.max(1) as f64
    );

    // Dropped from 0.2 m with the hand out of the way.
    env.set_physical_state(&[0.2, 0.2, 0.35, 0.1, 0.0, 0.0, 0.2])
        .expect("a valid state");
    let open = [0.0, 0.0, 0.0, 1.0];
    for _ in 0..25 {
        env.step(&open);
    }
    let rest: Vec<f32> = env.state()[4..7].to_vec();
    let mut drift = 0.0f32;
    for _ in 0..125 {
        env.step(&open);
        drift = drift.max(distance(&env.state()[4..7], &rest));
    }
    println!(
        "drop from 0.2 m: at rest at z = {:.5} m after 1 s; largest drift over the next 5 s \
         {:.3} mm",
        rest[2],
        drift * 1e3
    );

    // Grasped at the table's centre, lifted, then shaken.
    env.set_physical_state(&[0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.025])
        .expect("a valid state");
    let close = [0.0, 0.0, 0.0, -1.0];
    for _ in 0..5 {
        env.step(&close);
    }
    let penetration = env.pad_penetration();
    for _ in 0..2 {
        env.step(&[0.0, 0.0, 1.0, -1.0]);
    }
    let offset = in_hand(env.state());
    let (mut worst, mut asymmetry) = (0.0f32, 0.0f32);
    let mut rng = Rng::seed_from(1);
    for _ in 0..200 {
        let mut a = close;
        a[rng.below(3)] = if rng.bernoulli(0.5) { 1.0 } else { -1.0 };
        env.step(&a);
        worst = worst.max(distance(&in_hand(env.state()), &offset));
        let [p, q] = env.pad_offsets();
        asymmetry = asymmetry.max((p + q).abs());
    }
    println!(
        "squeeze: the pads sink {:.3} mm into the block; held block over 200 full-speed moves: \
         at most {:.3} mm from its place in the hand, pads at most {:.3} mm off-centre",
        penetration * 1e3,
        worst * 1e3,
        asymmetry * 1e3
    );
}

/// The block's position minus the hand's.
fn in_hand(state: &[f32]) -> [f32; 3] {
    [0, 1, 2].map(|i| state[4 + i] - state[i])
}

fn distance(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).powi(2))
        .sum::<f32>()
        .sqrt()
}
