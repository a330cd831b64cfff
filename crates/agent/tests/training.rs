//! The embedded trainer end to end: reproducibility and a learning smoke test.

use std::sync::atomic::{AtomicBool, Ordering};

use hac_agent::{RoundReport, Trainer, TrainerOptions};

fn mountain_car(
    seed: u64,
    threads: usize,
    episodes: u64,
    test_episodes: usize,
) -> (Vec<RoundReport>, Vec<Vec<u8>>) {
    let env = hac_envs::make("mountain-car").unwrap();
    let mut config = env.default_config(2);
    config.test_episodes = test_episodes;
    let options = TrainerOptions {
        seed,
        threads,
        replay_shards: 2,
    };
    let mut trainer = Trainer::new(env, config, options).unwrap();
    let curve = trainer.run(episodes, None, &AtomicBool::new(false), |_| {});
    let weights = trainer
        .agent()
        .levels()
        .iter()
        .map(|l| l.to_safetensors())
        .collect();
    (curve, weights)
}

/// Everything but wall-clock fields.
fn deterministic_part(curve: &[RoundReport]) -> Vec<String> {
    curve
        .iter()
        .map(|r| {
            let row = r.csv_row();
            let fields: Vec<&str> = row.split(',').collect();
            // round, episodes, env_steps, success_rate; then the per-level statistics.
            [&fields[..4], &fields[7..]].concat().join(",")
        })
        .collect()
}

#[test]
fn same_seed_same_curve_and_weights_bit_for_bit() {
    let (curve_a, weights_a) = mountain_car(7, 1, 30, 10);
    let (curve_b, weights_b) = mountain_car(7, 1, 30, 10);
    assert_eq!(deterministic_part(&curve_a), deterministic_part(&curve_b));
    assert_eq!(weights_a, weights_b);
    // Levels update on their own threads from their own random streams: same result.
    let (curve_c, weights_c) = mountain_car(7, 2, 30, 10);
    assert_eq!(deterministic_part(&curve_a), deterministic_part(&curve_c));
    assert_eq!(weights_a, weights_c);
    // A different seed is a different run.
    let (_, weights_d) = mountain_car(8, 1, 30, 10);
    assert_ne!(weights_a, weights_d);
}

#[test]
fn mountain_car_learns_from_nothing() {
    // Seed 0: untrained greedy agents never reach the flag; after 100 training episodes the
    // test success of the last five rounds averages about 0.35 (measured); 0.15 leaves margin.
    let env = hac_envs::make("mountain-car").unwrap();
    let config = env.default_config(2);
    let mut trainer = Trainer::new(env, config, TrainerOptions::default()).unwrap();
    assert_eq!(
        trainer.test(100),
        0.0,
        "an untrained agent should not succeed"
    );
    let curve = trainer.run(100, None, &AtomicBool::new(false), |_| {});
    let last: Vec<f32> = curve.iter().rev().take(5).map(|r| r.success_rate).collect();
    let mean = last.iter().sum::<f32>() / last.len() as f32;
    assert!(
        mean >= 0.15,
        "mean test success of the last rounds {mean} ({last:?})"
    );
}

#[test]
fn an_interrupt_ends_the_run_after_the_current_episode() {
    let env = hac_envs::make("mountain-car").unwrap();
    let mut config = env.default_config(2);
    config.test_episodes = 2;
    let mut trainer = Trainer::new(env, config, TrainerOptions::default()).unwrap();
    let interrupt = AtomicBool::new(false);
    // Interrupt as the first round is reported: the run stops before another episode starts.
    let curve = trainer.run(1000, None, &interrupt, |_| {
        interrupt.store(true, Ordering::Relaxed)
    });
    assert_eq!(curve.len(), 1);
    assert_eq!(trainer.episodes(), 10, "one block of exploration episodes");
}
