//! Status: an operator's snapshot of the learner ([`LearnerStatus`] and its parts), assembled
//! from every part's own state.
//!
//! # Locks
//! [`Shared::status`] takes, one after another and never two parts' at once except as noted:
//! the `counting` lock (exclusive, with the replay shards' locks under it, so that the
//! per-level totals add up to the transition counter), each level's slot (with its rate
//! limiter's lock under it), the publisher's state, the registry (map, then each entry), the
//! rates window, and the turns. It is called with no lock held (an evaluation report holds
//! only the gate, shared).

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use hac_nn::UpdateStats;
use hac_proto::{ActorRole, RejectReason};
use hac_replay::RateLimiterStatus;

use crate::{Shared, TurnStatus, Wal, WalStatus};

/// A status snapshot of one level.
#[derive(Debug, Clone)]
pub struct LevelStatus {
    pub updates: u64,
    /// Over the status's `rates.window`.
    pub updates_per_s: f64,
    pub replay_len: usize,
    pub replay_capacity: usize,
    pub shard_lens: Vec<usize>,
    pub transitions_inserted: u64,
    pub last: Option<UpdateStats>,
    pub limiter: RateLimiterStatus,
    /// Updates undone because they diverged (non-finite or exploding), in all and in a row now
    /// (a level is failing at [`MAX_DIVERGED_IN_A_ROW`](crate::MAX_DIVERGED_IN_A_ROW)).
    pub diverged_updates: u64,
    pub diverged_in_a_row: u32,
}

/// A status snapshot of one actor.
#[derive(Debug, Clone)]
pub struct RegisteredActor {
    pub actor_id: String,
    pub role: ActorRole,
    pub hostname: String,
    pub incarnation: u64,
    pub registered_for: Duration,
    pub last_seen_ago: Duration,
    pub episodes: u64,
    pub env_steps: u64,
    pub transitions: u64,
    pub duplicates: u64,
    /// The newest weights version the actor acted with (batches, episodes and evaluation
    /// reports carry it).
    pub weights_version: u64,
    /// Versions between the learner's newest and `weights_version`.
    pub weights_lag: u64,
    /// How the actor reaches the learner ("grpc", "shm"; "" before its transport said).
    pub transport: &'static str,
    /// Over the time since the actor's previous status sample (about [`RATES_WINDOW`](crate::RATES_WINDOW)).
    pub env_steps_per_s: f64,
    /// Every sequence of the incarnation up to this one is stored (acknowledged).
    pub stored_through: u64,
    /// ... and up to this one durable: in the write-ahead log on disk (or, without one, equal
    /// to `stored_through`). `stored_through - durable_through` is the ack-durable gap.
    pub durable_through: u64,
}

/// Ingest rates over a sliding window (about [`RATES_WINDOW`](crate::RATES_WINDOW), or the time since the previous
/// status when status is read rarely).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Rates {
    pub window: Duration,
    pub transitions_per_s: f64,
    pub batches_per_s: f64,
    pub episodes_per_s: f64,
    pub env_steps_per_s: f64,
    /// Every level together (each level's own is in its [`LevelStatus`]).
    pub updates_per_s: f64,
}

/// A status snapshot of the learner.
#[derive(Debug, Clone)]
pub struct LearnerStatus {
    pub uptime: Duration,
    pub run_config_digest: String,
    pub weights_version: u64,
    pub finished: bool,
    pub messages: u64,
    pub duplicates: u64,
    pub batches: u64,
    pub transitions: u64,
    pub episodes: u64,
    pub successes: u64,
    pub env_steps: u64,
    pub rejected: Vec<(RejectReason, u64)>,
    /// Messages the per-actor rate limit held back, and the total wait it imposed.
    pub throttled: u64,
    pub throttled_for: Duration,
    pub turns: TurnStatus,
    pub rates: Rates,
    pub levels: Vec<LevelStatus>,
    /// Sorted by id.
    pub actors: Vec<RegisteredActor>,
    /// The write-ahead log, if the learner keeps one.
    pub wal: Option<WalStatus>,
}

impl Shared {
    /// A status snapshot; see the module docs for its locks.
    pub(crate) fn status(&self) -> LearnerStatus {
        let now = Instant::now();
        self.registry.forget_silent(now);
        let c = &self.counters;
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
        // One cut of what ingest inserts and counts together.
        let (tables, transitions, batches) = {
            let _counting = self.counting.write();
            let tables: Vec<(u64, Vec<usize>)> = (0..self.dims.len())
                .map(|level| {
                    let table = self.replay.table(level);
                    (table.inserted_total(), table.shard_lens().collect())
                })
                .collect();
            (tables, load(&c.transitions), load(&c.batches))
        };
        let mut levels: Vec<LevelStatus> = tables
            .into_iter()
            .enumerate()
            .map(|(level, (inserted, shard_lens))| {
                self.publisher.slot(level, |slot| LevelStatus {
                    updates: slot.completed,
                    updates_per_s: 0.0,
                    replay_len: shard_lens.iter().sum(),
                    replay_capacity: self.replay.table(level).capacity(),
                    shard_lens,
                    transitions_inserted: inserted,
                    last: slot.last,
                    limiter: self.limiters[level].status(),
                    diverged_updates: slot.diverged,
                    diverged_in_a_row: slot.diverged_in_a_row,
                })
            })
            .collect();
        let weights_version = self.publisher.version();
        let actors = self
            .registry
            .status(now, weights_version, self.wal.as_ref());
        let (episodes, env_steps) = (load(&c.episodes), load(&c.env_steps));
        let totals: Vec<u64> = [transitions, batches, episodes, env_steps]
            .into_iter()
            .chain(levels.iter().map(|l| l.updates))
            .collect();
        let (window, per_s) = self.rates.lock().rates(now, &totals);
        for (level, rate) in levels.iter_mut().zip(&per_s[4..]) {
            level.updates_per_s = *rate;
        }
        LearnerStatus {
            uptime: now.saturating_duration_since(self.started),
            run_config_digest: self.digest.clone(),
            weights_version,
            finished: self.is_finished(),
            messages: load(&c.messages),
            duplicates: load(&c.duplicates),
            batches,
            transitions,
            episodes,
            successes: load(&c.successes),
            env_steps,
            rejected: RejectReason::ALL
                .iter()
                .zip(&c.rejected)
                .map(|(&r, n)| (r, load(n)))
                .collect(),
            throttled: load(&c.throttled),
            throttled_for: Duration::from_nanos(load(&c.throttled_ns)),
            turns: self.turns.status(),
            rates: Rates {
                window,
                transitions_per_s: per_s[0],
                batches_per_s: per_s[1],
                episodes_per_s: per_s[2],
                env_steps_per_s: per_s[3],
                updates_per_s: per_s[4..].iter().sum(),
            },
            levels,
            actors,
            wal: self.wal.as_ref().map(Wal::status),
        }
    }
}
