//! [`Publisher`]: each level's trainer output and the versioned snapshots made of it. The rule
//! for when weights are published lives here, and only here.
//!
//! # The publishing rule
//! A level *covers* an ingested episode once every update the episode earned it is done and in
//! the weights it offers. Each level's slot keeps the weights it offers and the episodes they
//! cover, and coverage grows in exactly two ways:
//!
//! - [`Publisher::update_done`] (the trainer, after each update): the level offers its weights
//!   when it has caught up with the episodes ingested (every granted update done, less than
//!   one owed) and every `publish_every_updates` updates. Offered weights cover the episodes
//!   whose owed updates they include; caught up, they cover every episode ingested.
//! - [`Publisher::episode_counted`] (ingest, after an episode summary): a level with nothing
//!   owed (its table still below one batch, or its trainer idle and caught up) covers the new
//!   episode at once with the weights it already offered.
//!
//! [`Publisher::maybe_publish`] then publishes a snapshot of every level's offered weights when
//! it is due: coverage (the least over the levels) grew, so that an actor waiting for weights
//! trained on its episodes gets them at once (the paper's schedule, with one lockstep actor);
//! or every level offers fresh weights; or some level's fresh weights have waited
//! `max_publish_delay`. [`Publisher::publish`] publishes unconditionally (the first snapshot, a
//! republish, the final one). A snapshot's `episodes` is the coverage it was made with.
//!
//! Besides the latest snapshot ([`Publisher::weights`]), the [`Publisher::covering`] cell holds
//! the first snapshot and then each that covered more episodes than the one before: weights
//! fixed by the schedule rather than by when a trainer offered them.
//!
//! # Locks
//! The publisher's state (`Mutex`, versions and what was published) is taken before any level's
//! slot (`Mutex` each); [`Publisher::update_done`] and [`Publisher::episode_counted`] take one
//! slot alone and read that level's rate limiter under it (the limiter's lock is innermost).
//! Publishing into the weights cells happens under the state's lock, so that versions appear in
//! order. No method calls out of this module while holding a lock.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use hac_nn::{Diverged, LevelModel, UpdateStats};
use hac_proto::{Published, WeightsSnapshot};
use hac_replay::RateLimiter;
use parking_lot::Mutex;

use crate::best::RecentSnapshots;

/// Updates undone in a row after which a level counts as failing: health goes `NOT_SERVING`
/// with the reason until an update of the level succeeds again.
pub const MAX_DIVERGED_IN_A_ROW: u32 = 10;

/// A level's trainer output: the weights it offers for publication, the episodes they cover,
/// and how its updates went.
#[derive(Debug)]
pub(crate) struct LevelSlot {
    /// The actor network (safetensors) after `weights_updates` updates.
    weights: Arc<Vec<u8>>,
    weights_updates: u64,
    /// Updates finished (granted updates may still be running).
    pub(crate) completed: u64,
    /// Episodes ingested whose owed updates are all finished and in `weights`.
    pub(crate) covered_episodes: u64,
    pub(crate) last: Option<UpdateStats>,
    /// Updates undone because they diverged, in all and in a row now.
    pub(crate) diverged: u64,
    pub(crate) diverged_in_a_row: u32,
    last_divergence: Option<Diverged>,
}

impl LevelSlot {
    /// The slot of `learner` as it starts: its weights offered, `covered_episodes` covered (0,
    /// or a checkpoint's), `last` the statistics of its last update, if known.
    pub(crate) fn new(
        learner: &LevelModel,
        covered_episodes: u64,
        last: Option<UpdateStats>,
    ) -> Self {
        Self {
            weights: Arc::new(learner.actor().to_safetensors()),
            weights_updates: learner.updates(),
            completed: learner.updates(),
            covered_episodes,
            last,
            diverged: 0,
            diverged_in_a_row: 0,
            last_divergence: None,
        }
    }

    /// Counts a finished update of `level` and its outcome; true if the level started or
    /// stopped failing (see [`MAX_DIVERGED_IN_A_ROW`]).
    fn record(&mut self, level: usize, outcome: Result<UpdateStats, Diverged>) -> bool {
        self.completed += 1;
        match outcome {
            Ok(stats) => {
                self.last = Some(stats);
                let recovered = self.diverged_in_a_row >= MAX_DIVERGED_IN_A_ROW;
                if recovered {
                    tracing::info!(level, "level recovered: an update succeeded");
                }
                self.diverged_in_a_row = 0;
                recovered
            }
            Err(diverged) => {
                self.diverged += 1;
                self.diverged_in_a_row += 1;
                self.last_divergence = Some(diverged);
                let in_a_row = self.diverged_in_a_row;
                tracing::warn!(level, %diverged, in_a_row, "update undone");
                in_a_row == MAX_DIVERGED_IN_A_ROW
            }
        }
    }

    /// Why this level is failing, if it is.
    fn failing(&self, level: usize) -> Option<String> {
        (self.diverged_in_a_row >= MAX_DIVERGED_IN_A_ROW).then(|| {
            let last = self
                .last_divergence
                .map_or_else(String::new, |d| format!(": {d}"));
            format!(
                "level {level}: the last {} updates diverged and were undone{last}",
                self.diverged_in_a_row
            )
        })
    }
}

/// What was published, under the publisher's lock.
#[derive(Debug)]
struct PublisherState {
    version: u64,
    /// Each level's `weights_updates` in the latest snapshot.
    published_updates: Vec<u64>,
    published_episodes: u64,
    last_publish: Instant,
    /// `version -> episodes` of every snapshot, to place evaluations on the curve.
    episodes_of: BTreeMap<u64, u64>,
    /// The newest snapshots, one of which an evaluation may make the best.
    recent: RecentSnapshots,
}

/// The levels' trainer output and the snapshots published from it; see the module docs.
#[derive(Debug)]
pub(crate) struct Publisher {
    state: Mutex<PublisherState>,
    slots: Vec<Mutex<LevelSlot>>,
    /// The latest snapshot.
    weights: Published<WeightsSnapshot>,
    /// The first snapshot, then each that covered more episodes than the one before (HIRO's
    /// off-policy correction reads its low-level policy here, so that a seed gives the same
    /// run).
    covering: Published<WeightsSnapshot>,
    /// `state.published_episodes`, readable without the lock.
    published_episodes: AtomicU64,
    /// This process's random id, in every snapshot (`WeightsSnapshot::learner_start`).
    learner_start: u64,
    /// `publish_every_updates`.
    every: u64,
    /// `max_publish_delay`.
    max_delay: Duration,
}

impl Publisher {
    /// A publisher of `slots` that has published nothing yet in this process: the next
    /// version is `version + 1` (a resumed run's versions continue above its checkpoint's), and
    /// `published_episodes` were covered by the last snapshot before.
    pub(crate) fn new(
        slots: Vec<LevelSlot>,
        version: u64,
        published_episodes: u64,
        learner_start: u64,
        every: u64,
        max_delay: Duration,
    ) -> Self {
        Self {
            state: Mutex::new(PublisherState {
                version,
                published_updates: slots.iter().map(|s| s.weights_updates).collect(),
                published_episodes,
                last_publish: Instant::now(),
                episodes_of: BTreeMap::new(),
                recent: RecentSnapshots::default(),
            }),
            slots: slots.into_iter().map(Mutex::new).collect(),
            weights: Published::default(),
            covering: Published::default(),
            published_episodes: AtomicU64::new(published_episodes),
            learner_start,
            every,
            max_delay,
        }
    }

    /// The latest snapshot, waitable. No lock of the publisher's.
    pub(crate) fn weights(&self) -> &Published<WeightsSnapshot> {
        &self.weights
    }

    /// The latest snapshot that covered more episodes than the one before. No lock.
    pub(crate) fn covering(&self) -> &Published<WeightsSnapshot> {
        &self.covering
    }

    pub(crate) fn learner_start(&self) -> u64 {
        self.learner_start
    }

    /// Episodes every level had trained on in the latest snapshot. No lock (an atomic).
    pub(crate) fn published_episodes(&self) -> u64 {
        self.published_episodes.load(Ordering::Acquire)
    }

    /// The latest version and the episodes it covered. Locks: the state.
    pub(crate) fn version_and_episodes(&self) -> (u64, u64) {
        let state = self.state.lock();
        (state.version, state.published_episodes)
    }

    /// The latest version. Locks: the state.
    pub(crate) fn version(&self) -> u64 {
        self.state.lock().version
    }

    /// The episodes `version` covered and its snapshot if it is still kept, or `None` for a
    /// version never published (or too old to remember). Locks: the state.
    pub(crate) fn published(&self, version: u64) -> Option<(u64, Option<Arc<WeightsSnapshot>>)> {
        let state = self.state.lock();
        let episodes = *state.episodes_of.get(&version)?;
        Some((episodes, state.recent.get(version).cloned()))
    }

    /// Reads `level`'s slot. Locks: that slot.
    pub(crate) fn slot<T>(&self, level: usize, read: impl FnOnce(&LevelSlot) -> T) -> T {
        read(&self.slots[level].lock())
    }

    /// Why the learner is failing: the first level whose last [`MAX_DIVERGED_IN_A_ROW`] updates
    /// all diverged, if any. Locks: each slot in turn.
    pub(crate) fn failing(&self) -> Option<String> {
        self.slots
            .iter()
            .enumerate()
            .find_map(|(level, slot)| slot.lock().failing(level))
    }

    /// Ingest counted an episode summary, and `limiter` (`level`'s) its owed updates: a level
    /// with nothing owed covers the episode at once. Locks: `level`'s slot, and the limiter's
    /// own lock under it.
    pub(crate) fn episode_counted(&self, level: usize, limiter: &RateLimiter) {
        let mut slot = self.slots[level].lock();
        let status = limiter.status();
        if status.updates == slot.completed && status.deficit < 1.0 {
            slot.covered_episodes = slot.covered_episodes.max(status.episodes);
        }
    }

    /// `level`'s trainer finished an update with `outcome` (an undone update counts as done:
    /// the schedule goes on with the last good weights, which are all that is ever offered);
    /// offers `learner`'s weights when the level has caught up or every `publish_every_updates`
    /// (see the module docs). True if the level started or stopped failing. Locks: `level`'s
    /// slot, and `limiter`'s own lock under it.
    pub(crate) fn update_done(
        &self,
        level: usize,
        outcome: Result<UpdateStats, Diverged>,
        learner: &LevelModel,
        limiter: &RateLimiter,
    ) -> bool {
        let mut slot = self.slots[level].lock();
        let failing_changed = slot.record(level, outcome);
        let status = limiter.status();
        let caught_up = status.updates == slot.completed && status.deficit < 1.0;
        if caught_up || slot.completed.is_multiple_of(self.every) {
            slot.weights = Arc::new(learner.actor().to_safetensors());
            slot.weights_updates = slot.completed;
            // Under sustained ingest a level is rarely caught up, yet these weights cover every
            // episode whose owed updates they include: the uncredited ones and the first
            // `completed / r` credited ones.
            let r = limiter.config().updates_per_episode;
            let served = ((slot.completed as f64 / r).floor() as u64).min(status.credited_episodes);
            let uncredited = status.episodes - status.credited_episodes;
            slot.covered_episodes = slot.covered_episodes.max(uncredited + served);
        }
        if caught_up {
            slot.covered_episodes = slot.covered_episodes.max(status.episodes);
        }
        failing_changed
    }

    /// Publishes a snapshot if it is due (see the module docs); the episodes it covers if it
    /// did. Locks: the state, and each slot in turn under it.
    pub(crate) fn maybe_publish(&self) -> Option<u64> {
        let mut state = self.state.lock();
        let mut covered = u64::MAX;
        let (mut fresh, mut all_fresh) = (false, true);
        for (slot, &published) in self.slots.iter().zip(&state.published_updates) {
            let slot = slot.lock();
            covered = covered.min(slot.covered_episodes);
            let f = slot.weights_updates > published;
            fresh |= f;
            all_fresh &= f;
        }
        let due = covered > state.published_episodes
            || (fresh && (all_fresh || state.last_publish.elapsed() >= self.max_delay));
        if !due {
            return None;
        }
        self.publish_locked(&mut state, false);
        Some(covered)
    }

    /// Publishes a snapshot of every level's offered weights as the next version (`run_finished`
    /// marks the final one); its version. Locks: the state, and each slot in turn under it.
    pub(crate) fn publish(&self, run_finished: bool) -> u64 {
        self.publish_locked(&mut self.state.lock(), run_finished)
    }

    fn publish_locked(&self, state: &mut PublisherState, run_finished: bool) -> u64 {
        let mut levels = Vec::with_capacity(self.slots.len());
        let mut covered = u64::MAX;
        for (level, slot) in self.slots.iter().enumerate() {
            let slot = slot.lock();
            levels.push(slot.weights.as_ref().clone());
            state.published_updates[level] = slot.weights_updates;
            covered = covered.min(slot.covered_episodes);
        }
        let covers_more = covered > state.published_episodes || self.covering.latest().is_none();
        state.version += 1;
        state.published_episodes = covered;
        state.last_publish = Instant::now();
        let version = state.version;
        state.episodes_of.insert(version, covered);
        // Bounded memory in long runs: evaluations refer to recent versions.
        while state.episodes_of.len() > 100_000 {
            state.episodes_of.pop_first();
        }
        let snapshot = Arc::new(WeightsSnapshot {
            version,
            levels,
            episodes: covered,
            run_finished,
            learner_start: self.learner_start,
        });
        state.recent.push(snapshot.clone());
        if covers_more {
            self.covering.publish(snapshot.clone());
        }
        self.weights.publish(snapshot);
        self.published_episodes.store(covered, Ordering::Release);
        version
    }
}
