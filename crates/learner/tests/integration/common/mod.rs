//! What the learner's tests share: a small pendulum run that trains in milliseconds.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use hac_agent::RunConfig;
use hac_learner::{Learner, LearnerCheckpoint, RejectReason};

/// Pendulum, 2 levels, seed 1, batches of 4, 3 updates per episode, one hidden layer of 8.
pub fn small_run(episodes: u64, replay_shards: usize) -> RunConfig {
    let mut agent = hac_envs::make("pendulum").unwrap().default_config(2);
    agent.batch_size = 4;
    agent.updates_per_episode = 3;
    agent.hidden_layers = vec![8];
    RunConfig {
        env: "pendulum".into(),
        levels: 2,
        seed: 1,
        episodes,
        stop_at: None,
        replay_shards,
        max_actions: None,
        subgoal_bounds: None,
        agent,
        tabular: None,
        hiro: None,
        algo: Default::default(),
    }
}

/// Waits until every level has done every update owed so far.
#[allow(dead_code)] // not every test file waits
pub fn drained(learner: &Learner) {
    let started = Instant::now();
    loop {
        let status = learner.status();
        if status
            .levels
            .iter()
            .all(|l| l.limiter.deficit < 1.0 && l.limiter.updates == l.updates)
        {
            return;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "trainers never caught up: {:?}",
            status.levels
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// A checkpoint's files by name, as on disk.
#[allow(dead_code)] // not every test file takes checkpoints
pub fn files(checkpoint: &LearnerCheckpoint) -> BTreeMap<String, Vec<u8>> {
    checkpoint.to_files().into_iter().collect()
}

/// How many messages the learner refused for `reason` (every reason has a counter).
pub fn rejected(learner: &Learner, reason: RejectReason) -> u64 {
    learner
        .status()
        .rejected
        .iter()
        .find(|(r, _)| *r == reason)
        .map(|&(_, n)| n)
        .unwrap()
}
