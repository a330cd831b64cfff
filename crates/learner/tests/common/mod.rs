//! What the learner's tests share: a small pendulum run that trains in milliseconds.

use hac_agent::RunConfig;

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
