//! [`LearnerOptions`]: how the learner runs (not the algorithm's hyperparameters), and their
//! checks. No state, no locks.

use std::time::Duration;

use hac_agent::RunConfig;

use crate::WalOptions;
use crate::turns::TURN_LEASE;

/// How the learner runs (not part of the algorithm's hyperparameters).
#[derive(Debug, Clone, PartialEq)]
pub struct LearnerOptions {
    /// Largest batch accepted, in transitions; actors learn it at registration.
    pub max_batch_transitions: usize,
    /// A level offers fresh weights for publication every this many updates (besides whenever it
    /// has caught up with the episodes ingested). Default: one episode's worth of updates.
    pub publish_every_updates: u64,
    /// Longest time fresh weights of some levels wait for the others before being published.
    pub max_publish_delay: Duration,
    /// Handed to actors: they refuse to act on weights more than this many versions behind the
    /// newest the learner has published.
    pub max_weights_lag: u64,
    /// The rate limiter's error buffer, in episodes' worth of updates: how far ingest may run
    /// ahead of training before actors are held back. At least 1.
    pub error_buffer_episodes: f64,
    /// Most ingest messages per second taken from one actor (see [`Learner::throttle`]); `None`
    /// for no limit.
    pub max_actor_messages_per_second: Option<f64>,
    /// Episode turns: at most this many training episodes played or waiting to be trained on
    /// at once, over all actors (see [`Learner::await_turn`]); 0 for no turns (every trainer
    /// plays whenever its previous episode is acknowledged).
    pub episodes_in_flight: u32,
    /// How long a granted turn is held for its actor without its episode arriving: an actor
    /// that dies or stalls with a turn delays the others by at most this much.
    pub turn_lease: Duration,
    /// An actor not heard from for this long is dropped from the registry (and status); if it
    /// comes back, it registers again (its link does so on `unknown_actor`).
    pub forget_actors_after: Duration,
    /// The write-ahead log of stored messages ([`wal`]), which makes them durable between
    /// checkpoints; `None`: no log, and a message is durable as soon as it is stored (acked),
    /// which holds only as long as the process lives.
    pub wal: Option<WalOptions>,
    /// Threads for updating the networks, shared among the levels (see [`level_threads`]),
    /// which still update in parallel, each on its trainer thread and the workers of its share.
    /// The weights do not depend on it. Default: the cores available to the process.
    pub learner_threads: usize,
}

/// The most [`LearnerOptions::learner_threads`] accepted.
pub const MAX_LEARNER_THREADS: usize = 1024;

/// The threads available to this process (at least 1): the default
/// [`LearnerOptions::learner_threads`].
pub fn available_threads() -> usize {
    std::thread::available_parallelism().map_or(1, std::num::NonZero::get)
}

/// How a budget of `threads` update threads is shared among `levels` levels: evenly, the
/// remainder to the lowest levels, and at least one each (a level always updates on its own
/// trainer thread, so a budget below the number of levels is exceeded). No level gets more
/// than [`hac_nn::GRADIENT_CHUNKS`], the most an update can use.
pub fn level_threads(threads: usize, levels: usize) -> Vec<usize> {
    (0..levels)
        .map(|level| {
            let share = threads / levels + usize::from(level < threads % levels);
            share.clamp(1, hac_nn::GRADIENT_CHUNKS)
        })
        .collect()
}

/// The default [`LearnerOptions::forget_actors_after`].
pub const FORGET_ACTORS_AFTER: Duration = Duration::from_secs(600);

impl LearnerOptions {
    /// Defaults for `run`.
    pub fn for_run(run: &RunConfig) -> Self {
        Self {
            max_batch_transitions: 4096,
            publish_every_updates: run.agent.updates_per_episode.max(1) as u64,
            max_publish_delay: Duration::from_millis(100),
            max_weights_lag: 16,
            error_buffer_episodes: 2.0,
            max_actor_messages_per_second: None,
            episodes_in_flight: 0,
            turn_lease: TURN_LEASE,
            forget_actors_after: FORGET_ACTORS_AFTER,
            wal: None,
            learner_threads: available_threads(),
        }
    }

    /// Checks every option against its range. The daemon's flags, `HAC_*` variables and config
    /// file keys are checked by their own parsers before this runs; this guards every other way
    /// of building options (the embedded run, tests, library users).
    pub fn validate(&self) -> Result<(), InvalidOption> {
        if self.max_batch_transitions == 0 || self.max_batch_transitions > 1 << 20 {
            return Err(InvalidOption::MaxBatchTransitions(
                self.max_batch_transitions,
            ));
        }
        if self.publish_every_updates == 0 {
            return Err(InvalidOption::PublishEveryUpdates);
        }
        if !(self.error_buffer_episodes.is_finite() && self.error_buffer_episodes >= 1.0) {
            return Err(InvalidOption::ErrorBufferEpisodes(
                self.error_buffer_episodes,
            ));
        }
        if self.episodes_in_flight > 1024 {
            return Err(InvalidOption::EpisodesInFlight(self.episodes_in_flight));
        }
        if self.turn_lease.is_zero() {
            return Err(InvalidOption::TurnLease);
        }
        if self.forget_actors_after.is_zero() {
            return Err(InvalidOption::ForgetActorsAfter);
        }
        if self.learner_threads == 0 || self.learner_threads > MAX_LEARNER_THREADS {
            return Err(InvalidOption::LearnerThreads(self.learner_threads));
        }
        if let Some(rate) = self.max_actor_messages_per_second
            && !(rate.is_finite() && rate > 0.0)
        {
            return Err(InvalidOption::MaxActorMessagesPerSecond(rate));
        }
        Ok(())
    }
}

/// A [`LearnerOptions`] field outside its range, one variant per field.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InvalidOption {
    #[error("invalid value for `max_batch_transitions`: must be 1 to 1048576, got {0}")]
    MaxBatchTransitions(usize),
    #[error("invalid value for `publish_every_updates`: must be at least 1")]
    PublishEveryUpdates,
    #[error("invalid value for `error_buffer_episodes`: must be at least 1, got {0}")]
    ErrorBufferEpisodes(f64),
    #[error("invalid value for `episodes_in_flight`: must be 0 (no turns) to 1024, got {0}")]
    EpisodesInFlight(u32),
    #[error("invalid value for `turn_lease`: must be above 0 seconds")]
    TurnLease,
    #[error("invalid value for `forget_actors_after`: must be above 0 seconds")]
    ForgetActorsAfter,
    #[error(
        "invalid value for `max_actor_messages_per_second`: must be a positive number of messages \
         per second, got {0}"
    )]
    MaxActorMessagesPerSecond(f64),
    #[error("invalid value for `learner_threads`: must be 1 to 1024, got {0}")]
    LearnerThreads(usize),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn level_threads_share_the_budget_and_give_each_level_one() {
        assert_eq!(level_threads(2, 2), [1, 1]);
        assert_eq!(level_threads(2, 1), [2]);
        assert_eq!(level_threads(5, 2), [3, 2]);
        assert_eq!(level_threads(7, 3), [3, 2, 2]);
        assert_eq!(level_threads(1, 3), [1, 1, 1]);
        assert_eq!(level_threads(64, 1), [hac_nn::GRADIENT_CHUNKS]);
    }

    #[test]
    fn learner_threads_must_be_1_to_1024() {
        let run = RunConfig {
            env: "pendulum".into(),
            levels: 2,
            seed: 0,
            episodes: 1,
            stop_at: None,
            replay_shards: 1,
            max_actions: None,
            subgoal_bounds: None,
            agent: hac_envs::make("pendulum").unwrap().default_config(2),
            tabular: None,
            hiro: None,
            algo: Default::default(),
        };
        let mut options = LearnerOptions::for_run(&run);
        assert!(options.learner_threads >= 1);
        for (threads, ok) in [(0, false), (1, true), (1024, true), (1025, false)] {
            options.learner_threads = threads;
            assert_eq!(
                options.validate(),
                if ok {
                    Ok(())
                } else {
                    Err(InvalidOption::LearnerThreads(threads))
                }
            );
        }
    }
}
