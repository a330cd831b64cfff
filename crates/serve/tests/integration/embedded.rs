//! The embedded run (learner + lockstep actor over the in-process transport) end to end:
//! reproducibility, learning, interrupts.

use std::sync::atomic::{AtomicBool, Ordering};

use hac_agent::{RoundReport, RunConfig};
use hac_learner::LearnerOptions;
use hac_serve::{EmbeddedRun, SavedRun, train_embedded, train_embedded_from};

fn run_config(env: &str, seed: u64, episodes: u64, test_episodes: usize) -> RunConfig {
    let mut agent = hac_envs::make(env).unwrap().default_config(2);
    agent.test_episodes = test_episodes;
    RunConfig {
        env: env.into(),
        levels: 2,
        seed,
        episodes,
        stop_at: None,
        replay_shards: 2,
        max_actions: None,
        subgoal_bounds: None,
        agent,
        tabular: None,
        hiro: None,
        algo: Default::default(),
    }
}

fn weights(run: &EmbeddedRun) -> Vec<Vec<u8>> {
    run.agent
        .levels()
        .iter()
        .map(|l| l.to_safetensors())
        .collect()
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

fn train(config: &RunConfig) -> EmbeddedRun {
    train_embedded(config, &AtomicBool::new(false), |_| {}).unwrap()
}

#[test]
fn same_seed_same_curve_and_weights_bit_for_bit() {
    let config = run_config("mountain-car", 7, 30, 10);
    let a = train(&config);
    let b = train(&config);
    assert_eq!(a.curve.len(), 3, "a test round every 10 episodes");
    assert_eq!(
        a.curve.iter().map(|r| r.episodes).collect::<Vec<_>>(),
        [10, 20, 30]
    );
    // Levels train on their own threads, concurrently with nothing else: timing cannot matter.
    assert_eq!(deterministic_part(&a.curve), deterministic_part(&b.curve));
    assert_eq!(weights(&a), weights(&b));
    // Every transition the actor sent is stored; every episode earned its updates.
    assert_eq!(a.status.episodes, 30);
    assert_eq!(a.status.duplicates, 0);
    assert_eq!(
        a.status.transitions,
        a.status
            .levels
            .iter()
            .map(|l| l.transitions_inserted)
            .sum::<u64>()
    );
    let per_episode = config.agent.updates_per_episode as u64;
    for level in &a.status.levels {
        assert_eq!(
            level.updates,
            level.limiter.credited_episodes * per_episode,
            "{level:?}"
        );
    }
    let other = train(&run_config("mountain-car", 8, 30, 10));
    assert_ne!(weights(&a), weights(&other));
}

#[test]
fn mountain_car_learns_from_nothing() {
    // Seed 0: untrained greedy agents never reach the flag; after 100 training episodes the
    // test success of the last five rounds averages well above 0.15.
    let run = train(&run_config("mountain-car", 0, 100, 100));
    assert_eq!(run.curve.len(), 10);
    let last: Vec<f32> = run
        .curve
        .iter()
        .rev()
        .take(5)
        .map(|r| r.success_rate)
        .collect();
    let mean = last.iter().sum::<f32>() / last.len() as f32;
    assert!(
        mean >= 0.15,
        "mean test success of the last rounds {mean} ({last:?})"
    );
}

#[test]
fn an_interrupt_ends_the_run_after_the_current_episode() {
    let config = run_config("mountain-car", 0, 1000, 2);
    let interrupt = AtomicBool::new(false);
    // Interrupt as the first round is reported: the run stops before another episode starts.
    let run = train_embedded(&config, &interrupt, |_| {
        interrupt.store(true, Ordering::Relaxed)
    })
    .unwrap();
    assert_eq!(run.curve.len(), 1);
    assert_eq!(run.actor.episodes, 10, "one block of exploration episodes");
}

#[test]
fn stop_at_ends_the_run_at_the_first_round_reaching_it() {
    let mut config = run_config("mountain-car", 0, 1000, 2);
    config.stop_at = Some(0.0);
    let run = train(&config);
    assert_eq!(run.curve.len(), 1);
    assert!(run.status.finished);
    assert!(run.actor.run_finished);
}

/// HIRO through the same learner and actor: both levels train (TD3), the high level's
/// transitions arrive with their low-level steps, and a seed gives the same run bit for bit
/// (the correction reads the published low-level policy, not the other trainer's progress).
#[test]
fn hiro_trains_through_the_learner_and_a_seed_gives_the_same_run() {
    use hac_core::hiro::{Algo, HiroConfig};
    let mut config = run_config("pendulum", 3, 6, 2);
    HiroConfig::agent_defaults(&mut config.agent);
    config.agent.exploration_episodes = 3;
    // HIRO's schedule does not read it, but the learner publishes every this many updates:
    // weights published in the middle of a round, at moments timing decides, must not reach
    // the high level's correction.
    config.agent.updates_per_episode = 1;
    config.algo = Algo::Hiro;
    // A twentieth of HIRO's update rate keeps the debug build quick: 50 low-level and 5
    // high-level updates per 1000-step episode.
    config.hiro = Some(HiroConfig {
        updates_per_step: 0.05,
        ..HiroConfig::default()
    });
    config.validate("test").unwrap();
    let a = train(&config);
    let b = train(&config);
    assert_eq!(a.curve.len(), 2, "a test round every 3 episodes");
    assert_eq!(deterministic_part(&a.curve), deterministic_part(&b.curve));
    assert_eq!(weights(&a), weights(&b));
    assert_eq!(a.status.episodes, 6);
    // One low-level transition per primitive action; one high-level transition per c = 10 of
    // them, and one more for an episode that ended between two decisions.
    let [low, high] = &a.status.levels[..] else {
        panic!("two levels");
    };
    assert_eq!(low.transitions_inserted, a.status.env_steps);
    let decisions = low.transitions_inserted / 10;
    assert!(
        (decisions..=decisions + 6).contains(&high.transitions_inserted),
        "{} high-level transitions for {} steps",
        high.transitions_inserted,
        low.transitions_inserted
    );
    // Both levels had a batch (100) after the first episode: their updates for every episode.
    assert_eq!((low.updates, high.updates), (6 * 50, 6 * 5));
    for level in &a.status.levels {
        assert!(level.last.is_some_and(|s| s.critic_loss.is_finite()));
        assert_eq!(level.diverged_updates, 0);
    }
}

fn train_keeping(
    config: &RunConfig,
    from: Option<&SavedRun>,
    interrupt: &AtomicBool,
    interrupt_at_round: Option<usize>,
) -> EmbeddedRun {
    let options = LearnerOptions::for_run(config);
    let mut reported = Vec::new();
    let run = train_embedded_from(config, options, from, true, interrupt, |report| {
        reported.push(report.round);
        if Some(report.round) == interrupt_at_round {
            interrupt.store(true, Ordering::Relaxed);
        }
    })
    .unwrap();
    // Only the rounds this call played are reported, the earlier ones were already.
    let first = from.map_or(1, |saved| saved.checkpoint.curve().len() + 1);
    assert_eq!(reported, (first..=run.curve.len()).collect::<Vec<_>>());
    run
}

fn same_run(a: &EmbeddedRun, b: &EmbeddedRun) {
    assert_eq!(deterministic_part(&a.curve), deterministic_part(&b.curve));
    assert_eq!(weights(a), weights(b));
    assert_eq!(a.status.episodes, b.status.episodes);
    assert_eq!(a.status.env_steps, b.status.env_steps);
    let best = |r: &EmbeddedRun| {
        r.best
            .as_ref()
            .map(|b| (b.round, b.episodes, b.success_rate))
    };
    assert_eq!(best(a), best(b));
    let state = |r: &EmbeddedRun| r.saved.as_ref().map(|s| s.trainer.clone());
    assert_eq!(state(a), state(b));
}

/// A run whose state was kept when it stopped, at the end of its budget or interrupted, and
/// continued from it is the run that was never stopped: the same curve, weights, best round and
/// trainer state, bit for bit. Only the budget and `stop_at` may change on the way.
#[test]
fn a_run_continued_from_its_saved_state_is_the_run_never_stopped() {
    let never = AtomicBool::new(false);
    let longer = run_config("mountain-car", 5, 30, 10);
    let whole = train_keeping(&longer, None, &never, None);
    assert_eq!(whole.curve.len(), 3);

    // Its budget of 20 trained, then raised to 30.
    let first = train_keeping(&run_config("mountain-car", 5, 20, 10), None, &never, None);
    let mut saved = first.saved.clone().expect("the state was kept");
    assert_eq!(saved.checkpoint.completed(), Some("episode budget trained"));
    assert_eq!(saved.trainer.episodes, 20);
    saved.checkpoint.continue_as(&longer).unwrap();
    let rest = train_keeping(&longer, Some(&saved), &never, None);
    same_run(&rest, &whole);

    // Interrupted after its first round, then continued to its own budget.
    let interrupt = AtomicBool::new(false);
    let cut = train_keeping(&longer, None, &interrupt, Some(1));
    assert_eq!(cut.actor.episodes, 10);
    let saved = cut.saved.expect("the state was kept");
    assert_eq!(saved.checkpoint.completed(), None);
    let rest = train_keeping(&longer, Some(&saved), &never, None);
    same_run(&rest, &whole);

    // Anything else that changes is named; a budget already trained, or a target already met,
    // leaves nothing to train.
    let mut other = first.saved.expect("the state was kept").checkpoint;
    let mut seed = longer.clone();
    seed.seed = 6;
    let error = other.continue_as(&seed).unwrap_err().to_string();
    assert!(
        error.contains("`seed` is 5 in the checkpoint, 6 now"),
        "{error}"
    );
    let error = other
        .continue_as(&run_config("mountain-car", 5, 20, 10))
        .unwrap_err()
        .to_string();
    assert!(error.contains("trained 20 episodes already"), "{error}");
    let mut reached = longer.clone();
    reached.stop_at = Some(0.0);
    let error = other.continue_as(&reached).unwrap_err().to_string();
    assert!(error.contains("round 1 (10 episodes) reached"), "{error}");
}
