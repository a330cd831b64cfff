//! [`RateLimiter`]: keeps one level's updates per ingested episode near the configured ratio,
//! shared between the learner's ingest (many actor streams) and that level's trainer thread.
//!
//! The rule and its guarantees are documented on [`RateLimiter`].

use std::time::{Duration, Instant};

use hac_core::AgentConfig;
use parking_lot::{Condvar, Mutex};
use serde::{Deserialize, Serialize};

/// One level's rate-limiter settings; see [`RateLimiter`] for how they are used.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RateLimiterConfig {
    /// `r`: updates the trainer does per credited episode, on average. Finite and above zero;
    /// fractions are allowed (0.5 = one update every two episodes).
    pub updates_per_episode: f64,
    /// `M`: transitions inserted into the level's table before an episode earns updates (the
    /// paper's rule is one batch). At least 1, at most the table's capacity.
    pub min_size_to_update: usize,
    /// `B`: how many updates ingest may run ahead of training before it is refused. At least
    /// `max(updates_per_episode, 1)`: below one update, ingest could be refused while less than
    /// a whole update is owed, and neither side could move; below one episode's worth, ingest
    /// would stall after every episode until the trainer caught up, leaving no overlap.
    pub error_buffer: f64,
}

impl RateLimiterConfig {
    /// The paper's setting for `config`: `updates_per_episode` per episode once a level's table
    /// holds one batch, with room for two episodes' worth of updates.
    pub fn for_agent(config: &AgentConfig) -> Self {
        let updates_per_episode = config.updates_per_episode as f64;
        Self {
            updates_per_episode,
            min_size_to_update: config.batch_size,
            error_buffer: 2.0 * updates_per_episode,
        }
    }

    /// Rejects settings that make no sense or could deadlock the trainer and ingest, naming the
    /// field. `table_capacity` is the level's replay capacity: a minimum size above it would
    /// never be reached.
    pub fn validate(&self, table_capacity: usize) -> Result<(), RateLimiterConfigError> {
        let r = self.updates_per_episode;
        if !(r.is_finite() && r > 0.0) {
            return Err(RateLimiterConfigError::UpdatesPerEpisode(r));
        }
        let min = r.max(1.0);
        if !(self.error_buffer.is_finite() && self.error_buffer >= min) {
            return Err(RateLimiterConfigError::ErrorBuffer {
                got: self.error_buffer,
                min,
            });
        }
        if !(1..=table_capacity).contains(&self.min_size_to_update) {
            return Err(RateLimiterConfigError::MinSizeToUpdate {
                got: self.min_size_to_update,
                capacity: table_capacity,
            });
        }
        Ok(())
    }
}

/// The reference: 40 updates per episode once the table holds a batch of 1024, with room for
/// two episodes' worth of updates.
impl Default for RateLimiterConfig {
    fn default() -> Self {
        Self {
            updates_per_episode: 40.0,
            min_size_to_update: 1024,
            error_buffer: 80.0,
        }
    }
}

/// A [`RateLimiterConfig`] field with a value that makes no sense or could deadlock.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum RateLimiterConfigError {
    #[error("updates_per_episode must be finite and above 0, got {0}")]
    UpdatesPerEpisode(f64),
    #[error(
        "error_buffer must be finite and at least max(updates_per_episode, 1) = {min}, got {got}"
    )]
    ErrorBuffer { got: f64, min: f64 },
    #[error(
        "min_size_to_update must be at least 1 and at most the table capacity {capacity}, got {got}"
    )]
    MinSizeToUpdate { got: usize, capacity: usize },
}

impl RateLimiterConfigError {
    /// The offending field's name.
    pub fn field(&self) -> &'static str {
        match self {
            Self::UpdatesPerEpisode(_) => "updates_per_episode",
            Self::ErrorBuffer { .. } => "error_buffer",
            Self::MinSizeToUpdate { .. } => "min_size_to_update",
        }
    }
}

/// Why a wait on the [`RateLimiter`] ended without its permission.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum WaitError {
    /// The limiter was closed (shutdown); every later wait fails the same way.
    #[error("rate limiter closed")]
    Closed,
    /// The timeout passed first; a zero timeout means "do not wait".
    #[error("rate limiter wait timed out")]
    TimedOut,
}

/// A snapshot of a [`RateLimiter`]'s counts, for status and metrics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RateLimiterStatus {
    /// Episodes recorded, credited or not.
    pub episodes: u64,
    /// `C`: episodes recorded once the table held `min_size_to_update` transitions.
    pub credited_episodes: u64,
    /// Transitions recorded.
    pub inserts: u64,
    /// `U`: updates granted.
    pub updates: u64,
    /// `D = C * updates_per_episode - U`: updates owed; never negative.
    pub deficit: f64,
    /// Total time trainers spent waiting for an update to be granted.
    pub trainer_blocked: Duration,
    /// Ingest admission checks that found no room (each blocking wait counts once).
    pub ingest_refused: u64,
    /// Total time ingest callers spent waiting for room.
    pub ingest_blocked: Duration,
    /// Trainers waiting for an update right now.
    pub trainers_waiting: usize,
    /// Ingest callers waiting for room right now.
    pub ingest_waiting: usize,
    pub closed: bool,
}

/// The counts that define a [`RateLimiter`]'s state, saved in checkpoints:
/// [`RateLimiter::counts`] and [`RateLimiter::restore`].
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct RateLimiterCounts {
    pub episodes: u64,
    pub credited_episodes: u64,
    pub inserts: u64,
    pub updates: u64,
    /// Updates owed once but dropped by a restore that forgave them (see
    /// [`RateLimiter::restore`]); 0 otherwise.
    pub forgiven_updates: f64,
}

#[derive(Debug, Default)]
struct State {
    episodes: u64,
    credited_episodes: u64,
    inserts: u64,
    updates: u64,
    forgiven_updates: f64,
    trainer_blocked: Duration,
    ingest_refused: u64,
    ingest_blocked: Duration,
    trainers_waiting: usize,
    ingest_waiting: usize,
    closed: bool,
}

impl State {
    /// `C * r`: the updates the credited episodes have earned (less those forgiven at a
    /// restore).
    fn earned(&self, r: f64) -> f64 {
        self.credited_episodes as f64 * r - self.forgiven_updates
    }

    fn deficit(&self, r: f64) -> f64 {
        self.earned(r) - self.updates as f64
    }

    /// `U + 1 <= C * r`. Compared without subtracting, so a granted update can never make the
    /// deficit negative through rounding.
    fn update_owed(&self, r: f64) -> bool {
        (self.updates + 1) as f64 <= self.earned(r)
    }

    /// `D <= B`.
    fn has_room(&self, config: &RateLimiterConfig) -> bool {
        self.deficit(config.updates_per_episode) <= config.error_buffer
    }
}

/// One level's rate limiter: ingest records transitions and episodes and asks for room before
/// accepting more; the trainer asks for each update. Share it by reference or `Arc`; every
/// method takes `&self`.
///
/// # The rule
/// The paper does `r` updates per level after every training episode, once the level's buffer
/// holds a batch. In a distributed run episodes arrive while the trainer works, so the limiter
/// keeps the same ratio on average instead of in lockstep. With
///
/// - `r` = [`updates_per_episode`](RateLimiterConfig::updates_per_episode),
/// - `B` = [`error_buffer`](RateLimiterConfig::error_buffer),
/// - `M` = [`min_size_to_update`](RateLimiterConfig::min_size_to_update),
/// - `C` = *credited* episodes: those recorded when at least `M` transitions had been inserted
///   (the paper's episodes that are followed by updates; earlier ones earn nothing, so the
///   trainer never starts with a burst of updates owed for episodes played before the buffer
///   held a batch),
/// - `U` = updates granted, and the deficit `D = C * r - U` (ideal minus actual updates),
///
/// the limiter
///
/// - grants an update iff `U + 1 <= C * r`, that is `D >= 1` (the update is already owed);
/// - admits ingest iff `D <= B`, and refuses it (backpressure) iff `D > B`;
/// - refuses both once [closed](RateLimiter::close).
///
/// # Guarantees
/// - `D >= 0` always: the trainer never runs ahead of the episodes it trains on, as in the paper.
///   Since no episode is credited before the table holds `M` transitions, no update is granted
///   before then either.
/// - `D <= B + r` when ingest checks for room before each episode it records, one check per
///   episode, and checks do not race; `k` ingest streams that each pass the check at the same
///   time and then record one episode give `D <= B + k * r`.
/// - Drained (the trainer takes updates until refused), `U = floor(C * r)`: exactly `C * r` for
///   a whole ratio, and `U / C -> r` for any ratio.
/// - No deadlock: [`validate`](RateLimiterConfig::validate) requires `B >= max(r, 1)`, so
///   whenever ingest is refused (`D > B >= 1`) the trainer is granted, and whenever the trainer is
///   refused (`D < 1 <= B`) ingest is admitted. Before the table reaches `M`, `C = 0` and `D = 0`,
///   so ingest is never refused while the table fills. Neither side waits forever while the other
///   keeps going.
///
/// Counts are `u64` and `C * r` is computed in `f64`: exact for whole or dyadic ratios and
/// moderate counts; other fractional ratios follow `f64` rounding at the boundaries. The two
/// checks stay complementary under rounding, so the no-deadlock argument holds as computed.
///
/// One mutex guards all counts. Calls never allocate, and the lock is held across nothing that
/// blocks except the condition variable waits, which release it.
#[derive(Debug)]
pub struct RateLimiter {
    config: RateLimiterConfig,
    state: Mutex<State>,
    /// Signalled when an update becomes owed, and on close.
    update_owed: Condvar,
    /// Signalled when ingest has room again, and on close.
    room: Condvar,
}

impl RateLimiter {
    /// A limiter for a level whose table holds at most `table_capacity` transitions, after
    /// [validating](RateLimiterConfig::validate) `config`.
    pub fn new(
        config: RateLimiterConfig,
        table_capacity: usize,
    ) -> Result<Self, RateLimiterConfigError> {
        config.validate(table_capacity)?;
        Ok(Self {
            config,
            state: Mutex::default(),
            update_owed: Condvar::new(),
            room: Condvar::new(),
        })
    }

    pub fn config(&self) -> &RateLimiterConfig {
        &self.config
    }

    /// Ingest: `transitions` more were stored in the level's table. Record an episode's
    /// transitions before its end, so the episode that fills the table to the minimum size is
    /// credited, as in the paper.
    pub fn record_insert(&self, transitions: usize) {
        self.state.lock().inserts += transitions as u64;
    }

    /// Ingest: a training episode ended. It earns `updates_per_episode` updates if at least
    /// `min_size_to_update` transitions have been recorded, and nothing otherwise. Never refused:
    /// an episode already stored must count, so check for room *before* accepting its data.
    pub fn record_episode(&self) {
        let mut state = self.state.lock();
        state.episodes += 1;
        if state.inserts >= self.config.min_size_to_update as u64 {
            state.credited_episodes += 1;
            if state.trainers_waiting > 0 && state.update_owed(self.config.updates_per_episode) {
                self.update_owed.notify_all();
            }
        }
    }

    /// Ingest admission, without waiting: true if a batch may be accepted now (`D <= B` and not
    /// closed). False counts as a refusal (unless closed); the learner then withholds the ack
    /// and the actor resends later.
    pub fn try_accept(&self) -> bool {
        self.wait_for_room(Duration::ZERO).is_ok()
    }

    /// Ingest admission, waiting up to `timeout` for the trainer to bring `D` back to at most
    /// `B`. A call that has to wait counts as one refusal.
    pub fn wait_for_room(&self, timeout: Duration) -> Result<(), WaitError> {
        let config = &self.config;
        let mut state = self.state.lock();
        if !state.closed && !state.has_room(config) {
            state.ingest_refused += 1;
            if !timeout.is_zero() {
                let started = Instant::now();
                state.ingest_waiting += 1;
                self.room
                    .wait_while_for(&mut state, |s| !s.closed && !s.has_room(config), timeout);
                state.ingest_waiting -= 1;
                state.ingest_blocked += started.elapsed();
            }
        }
        if state.closed {
            Err(WaitError::Closed)
        } else if state.has_room(config) {
            Ok(())
        } else {
            Err(WaitError::TimedOut)
        }
    }

    /// Trainer: waits up to `timeout` until an update is owed (`U + 1 <= C * r`), then grants
    /// and counts it; the caller does the update. Once closed, fails with
    /// [`WaitError::Closed`] even if updates are owed, so the trainer stops at shutdown.
    pub fn acquire_update(&self, timeout: Duration) -> Result<(), WaitError> {
        let r = self.config.updates_per_episode;
        let mut state = self.state.lock();
        if !state.closed && !state.update_owed(r) && !timeout.is_zero() {
            let started = Instant::now();
            state.trainers_waiting += 1;
            self.update_owed.wait_while_for(
                &mut state,
                |s| !s.closed && !s.update_owed(r),
                timeout,
            );
            state.trainers_waiting -= 1;
            state.trainer_blocked += started.elapsed();
        }
        if state.closed {
            return Err(WaitError::Closed);
        }
        if !state.update_owed(r) {
            return Err(WaitError::TimedOut);
        }
        state.updates += 1;
        if state.ingest_waiting > 0 && state.has_room(&self.config) {
            self.room.notify_all();
        }
        Ok(())
    }

    /// Shutdown: wakes every waiter; from now on waits fail with [`WaitError::Closed`] and
    /// ingest is refused (not counted as refusals). Recording still counts, so batches already
    /// admitted are accounted for. Idempotent.
    pub fn close(&self) {
        self.state.lock().closed = true;
        self.update_owed.notify_all();
        self.room.notify_all();
    }

    pub fn is_closed(&self) -> bool {
        self.state.lock().closed
    }

    /// The counts to save in a checkpoint (read under one lock, so they agree with each other).
    pub fn counts(&self) -> RateLimiterCounts {
        let state = self.state.lock();
        RateLimiterCounts {
            episodes: state.episodes,
            credited_episodes: state.credited_episodes,
            inserts: state.inserts,
            updates: state.updates,
            forgiven_updates: state.forgiven_updates,
        }
    }

    /// Continues from `counts` (of a limiter with the same config), before anyone uses this one.
    ///
    /// With `forgive_owed`, the updates owed at that point are dropped, so the deficit restarts
    /// at 0: a learner resumed without its replay has nothing to sample them from. Pass
    /// `counts.inserts = 0` as well in that case, so that new episodes earn updates again only
    /// once the empty table holds `min_size_to_update` transitions, as at the start of a run.
    pub fn restore(&self, counts: RateLimiterCounts, forgive_owed: bool) {
        let mut state = self.state.lock();
        state.episodes = counts.episodes;
        state.credited_episodes = counts.credited_episodes;
        state.inserts = counts.inserts;
        state.updates = counts.updates;
        state.forgiven_updates = counts.forgiven_updates;
        if forgive_owed {
            let owed = state.deficit(self.config.updates_per_episode).max(0.0);
            state.forgiven_updates += owed;
        }
    }

    pub fn status(&self) -> RateLimiterStatus {
        let state = self.state.lock();
        RateLimiterStatus {
            episodes: state.episodes,
            credited_episodes: state.credited_episodes,
            inserts: state.inserts,
            updates: state.updates,
            deficit: state.deficit(self.config.updates_per_episode),
            trainer_blocked: state.trainer_blocked,
            ingest_refused: state.ingest_refused,
            ingest_blocked: state.ingest_blocked,
            trainers_waiting: state.trainers_waiting,
            ingest_waiting: state.ingest_waiting,
            closed: state.closed,
        }
    }
}

#[cfg(test)]
mod tests {
    use std::thread;

    use proptest::prelude::*;

    use super::*;

    /// Only a deadlock guard: waits that should end early are woken long before this.
    const GUARD: Duration = Duration::from_secs(10);

    fn config(r: f64, b: f64, m: usize) -> RateLimiterConfig {
        RateLimiterConfig {
            updates_per_episode: r,
            error_buffer: b,
            min_size_to_update: m,
        }
    }

    fn limiter(r: f64, b: f64, m: usize) -> RateLimiter {
        RateLimiter::new(config(r, b, m), 1000).unwrap()
    }

    /// Polls `cond` every millisecond until it holds, failing after [`GUARD`].
    fn wait_until(what: &str, mut cond: impl FnMut() -> bool) {
        let deadline = Instant::now() + GUARD;
        while !cond() {
            assert!(Instant::now() < deadline, "timed out waiting for {what}");
            thread::sleep(Duration::from_millis(1));
        }
    }

    /// Grants updates with zero timeouts until none is owed; returns how many.
    fn drain(limiter: &RateLimiter) -> u64 {
        let mut granted = 0;
        while limiter.acquire_update(Duration::ZERO).is_ok() {
            granted += 1;
        }
        granted
    }

    #[test]
    fn a_restored_limiter_continues_and_a_forgiving_restore_owes_nothing() {
        let a = limiter(3.0, 6.0, 2);
        a.record_insert(2);
        a.record_episode();
        a.record_episode();
        assert_eq!(a.acquire_update(Duration::ZERO), Ok(()));
        let counts = a.counts();
        assert_eq!(
            (counts.episodes, counts.credited_episodes, counts.updates),
            (2, 2, 1)
        );

        let b = limiter(3.0, 6.0, 2);
        b.restore(counts, false);
        assert_eq!(b.counts(), counts);
        assert_eq!(drain(&b), 5, "the 5 updates still owed");

        let c = limiter(3.0, 6.0, 2);
        c.restore(
            RateLimiterCounts {
                inserts: 0,
                ..counts
            },
            true,
        );
        assert_eq!(c.status().deficit, 0.0);
        assert_eq!(drain(&c), 0, "nothing owed after forgiving");
        c.record_insert(1);
        c.record_episode();
        assert_eq!(drain(&c), 0, "not credited before the table holds M again");
        c.record_insert(1);
        c.record_episode();
        assert_eq!(drain(&c), 3);
        let status = c.status();
        assert_eq!((status.episodes, status.updates), (4, 4));
        assert!(c.try_accept());
        // Saved and restored again, the forgiven updates stay forgiven.
        let d = limiter(3.0, 6.0, 2);
        d.restore(c.counts(), false);
        assert_eq!(drain(&d), 0);
    }

    #[test]
    fn defaults_and_agent_settings_are_valid() {
        RateLimiterConfig::default().validate(1024).unwrap();
        let agent = AgentConfig::reference(3, 10);
        let config = RateLimiterConfig::for_agent(&agent);
        assert_eq!(config.updates_per_episode, 40.0);
        assert_eq!(config.min_size_to_update, 1024);
        for level in 0..3 {
            config.validate(agent.replay_capacity(level)).unwrap();
        }
    }

    #[test]
    fn validation_names_the_field() {
        let cases = [
            (config(0.0, 40.0, 1), "updates_per_episode"),
            (config(-1.0, 40.0, 1), "updates_per_episode"),
            (config(f64::NAN, 40.0, 1), "updates_per_episode"),
            (config(f64::INFINITY, 40.0, 1), "updates_per_episode"),
            (config(40.0, 39.0, 1), "error_buffer"),
            (config(0.5, 0.5, 1), "error_buffer"),
            (config(40.0, f64::NAN, 1), "error_buffer"),
            (config(40.0, f64::INFINITY, 1), "error_buffer"),
            (config(40.0, 40.0, 0), "min_size_to_update"),
            (config(40.0, 40.0, 101), "min_size_to_update"),
        ];
        for (config, field) in cases {
            let err = config.validate(100).unwrap_err();
            assert_eq!(err.field(), field, "{config:?}");
            assert!(err.to_string().starts_with(field), "{err}");
            // Compared as text: NaN fields are not equal to themselves.
            let new_err = RateLimiter::new(config, 100).unwrap_err();
            assert_eq!(new_err.to_string(), err.to_string());
        }
        assert_eq!(
            config(40.0, 39.0, 1).validate(100).unwrap_err().to_string(),
            "error_buffer must be finite and at least max(updates_per_episode, 1) = 40, got 39"
        );
        // The edges are allowed.
        config(40.0, 40.0, 100).validate(100).unwrap();
        config(0.5, 1.0, 1).validate(1).unwrap();
    }

    #[test]
    fn episodes_before_the_table_holds_min_size_earn_nothing() {
        let limiter = limiter(2.0, 4.0, 10);
        limiter.record_insert(9);
        limiter.record_episode();
        assert_eq!(
            limiter.acquire_update(Duration::ZERO),
            Err(WaitError::TimedOut)
        );
        // Reaching the minimum size owes nothing by itself; the next episode earns updates.
        limiter.record_insert(1);
        assert_eq!(
            limiter.acquire_update(Duration::ZERO),
            Err(WaitError::TimedOut)
        );
        limiter.record_episode();
        assert_eq!(drain(&limiter), 2);

        let status = limiter.status();
        assert_eq!(status.episodes, 2);
        assert_eq!(status.credited_episodes, 1);
        assert_eq!(status.inserts, 10);
        assert_eq!(status.updates, 2);
        assert_eq!(status.deficit, 0.0);
        // Zero timeouts never block.
        assert_eq!(status.trainer_blocked, Duration::ZERO);
    }

    #[test]
    fn trainer_blocks_until_the_table_reaches_min_size() {
        let limiter = limiter(2.0, 4.0, 10);
        thread::scope(|scope| {
            let trainer = scope.spawn(|| limiter.acquire_update(GUARD));
            wait_until("the trainer to wait", || {
                limiter.status().trainers_waiting == 1
            });

            limiter.record_insert(9);
            limiter.record_episode();
            limiter.record_insert(1);
            let status = limiter.status();
            assert_eq!((status.credited_episodes, status.updates), (0, 0));
            assert_eq!(status.trainers_waiting, 1, "released below min size");

            limiter.record_episode();
            assert_eq!(trainer.join().unwrap(), Ok(()));
        });
        let status = limiter.status();
        assert_eq!((status.credited_episodes, status.updates), (1, 1));
        assert_eq!(status.deficit, 1.0);
        assert_eq!(status.trainers_waiting, 0);
        assert!(status.trainer_blocked > Duration::ZERO);
    }

    #[test]
    fn ingest_is_refused_beyond_the_error_buffer_until_the_trainer_catches_up() {
        let limiter = limiter(4.0, 8.0, 1);
        limiter.record_insert(1);
        for deficit in [0.0, 4.0, 8.0] {
            assert_eq!(limiter.status().deficit, deficit);
            assert!(limiter.try_accept());
            limiter.record_episode();
        }
        // D = 12 > B = 8.
        assert!(!limiter.try_accept());
        assert_eq!(
            limiter.wait_for_room(Duration::ZERO),
            Err(WaitError::TimedOut)
        );
        assert_eq!(limiter.status().ingest_refused, 2);

        for _ in 0..3 {
            limiter.acquire_update(Duration::ZERO).unwrap();
            assert!(!limiter.try_accept(), "D = {}", limiter.status().deficit);
        }
        limiter.acquire_update(Duration::ZERO).unwrap();
        assert_eq!(limiter.status().deficit, 8.0);
        assert!(limiter.try_accept());
        assert_eq!(limiter.wait_for_room(Duration::ZERO), Ok(()));
        assert_eq!(limiter.status().ingest_refused, 5);
        // Checks that do not wait take no time.
        assert_eq!(limiter.status().ingest_blocked, Duration::ZERO);
    }

    #[test]
    fn blocked_ingest_is_released_by_updates() {
        let limiter = limiter(1.0, 1.0, 1);
        limiter.record_insert(1);
        limiter.record_episode();
        limiter.record_episode();
        thread::scope(|scope| {
            let ingest = scope.spawn(|| limiter.wait_for_room(GUARD));
            wait_until("ingest to wait", || limiter.status().ingest_waiting == 1);
            limiter.acquire_update(Duration::ZERO).unwrap();
            assert_eq!(ingest.join().unwrap(), Ok(()));
        });
        assert_eq!(limiter.status().ingest_refused, 1);
        assert!(limiter.status().ingest_blocked > Duration::ZERO);
    }

    /// A scripted run in one thread: the trainer makes `step % 5` attempts per step (2 on
    /// average); ingest offers an episode of 2 transitions (3 updates' worth) every step for 30
    /// steps, so it runs into the buffer, then every third step, so the trainer catches up.
    #[test]
    fn scripted_run_keeps_updates_within_the_buffer_and_drains_exactly() {
        let (r, b) = (3.0, 6.0);
        let limiter = limiter(r, b, 4);
        let mut trainer_refused = 0;
        for step in 0..60 {
            if (step < 30 || step % 3 == 0) && limiter.try_accept() {
                limiter.record_insert(2);
                limiter.record_episode();
            }
            for _ in 0..step % 5 {
                if limiter.acquire_update(Duration::ZERO).is_err() {
                    trainer_refused += 1;
                }
            }
            let s = limiter.status();
            let deficit = s.credited_episodes as f64 * r - s.updates as f64;
            assert_eq!(s.deficit, deficit);
            assert!(
                (0.0..=b + r).contains(&deficit),
                "step {step}: D = {deficit}"
            );
        }
        drain(&limiter);

        let s = limiter.status();
        assert_eq!(s.updates as f64, s.credited_episodes as f64 * r);
        // The episode that filled the table to 4 transitions was the first credited.
        assert_eq!(s.episodes, s.credited_episodes + 1);
        assert!(
            s.ingest_refused > 0 && trainer_refused > 0,
            "both sides waited"
        );
    }

    #[test]
    fn fractional_ratio_drains_to_the_floor() {
        let limiter = limiter(2.5, 5.0, 1);
        limiter.record_insert(1);
        let mut granted = 0;
        for episodes in 1..=9u64 {
            limiter.record_episode();
            granted += drain(&limiter);
            assert_eq!(granted, episodes * 5 / 2);
        }
    }

    #[test]
    fn trainer_and_two_ingest_threads_end_on_the_exact_ratio() {
        const EPISODES: u64 = 300;
        const R: u64 = 3;
        let r = R as f64;
        // A tight buffer makes both sides block often.
        let limiter = limiter(r, 4.0, 5);
        let total = 2 * EPISODES * R;
        thread::scope(|scope| {
            // Every episode brings the minimum size itself, so all are credited and the total is
            // known up front.
            let blocking = scope.spawn(|| {
                for _ in 0..EPISODES {
                    limiter.wait_for_room(GUARD).unwrap();
                    limiter.record_insert(5);
                    limiter.record_episode();
                }
            });
            let polling = scope.spawn(|| {
                for _ in 0..EPISODES {
                    if !limiter.try_accept() {
                        limiter.wait_for_room(GUARD).unwrap();
                    }
                    limiter.record_insert(7);
                    limiter.record_episode();
                }
            });
            let trainer = scope.spawn(|| {
                for _ in 0..total {
                    limiter.acquire_update(GUARD).unwrap();
                }
            });
            for t in [blocking, polling, trainer] {
                t.join().unwrap();
            }
        });
        assert_eq!(
            limiter.acquire_update(Duration::ZERO),
            Err(WaitError::TimedOut)
        );
        let s = limiter.status();
        assert_eq!(s.episodes, 2 * EPISODES);
        assert_eq!(s.credited_episodes, 2 * EPISODES);
        assert_eq!(s.inserts, EPISODES * 12);
        assert_eq!(s.updates, total);
        assert_eq!(s.updates as f64, s.episodes as f64 * r);
        assert_eq!(s.deficit, 0.0);
        assert_eq!((s.trainers_waiting, s.ingest_waiting), (0, 0));
    }

    #[test]
    fn close_releases_a_blocked_trainer() {
        let limiter = limiter(1.0, 1.0, 1);
        thread::scope(|scope| {
            let trainer = scope.spawn(|| limiter.acquire_update(GUARD));
            wait_until("the trainer to wait", || {
                limiter.status().trainers_waiting == 1
            });
            limiter.close();
            assert_eq!(trainer.join().unwrap(), Err(WaitError::Closed));
        });
        // Closed for good, even with updates owed.
        limiter.record_insert(1);
        limiter.record_episode();
        assert_eq!(limiter.acquire_update(GUARD), Err(WaitError::Closed));
        assert!(limiter.status().closed);
    }

    #[test]
    fn close_releases_a_blocked_ingest_waiter() {
        let limiter = limiter(1.0, 1.0, 1);
        limiter.record_insert(1);
        limiter.record_episode();
        limiter.record_episode();
        thread::scope(|scope| {
            let ingest = scope.spawn(|| limiter.wait_for_room(GUARD));
            wait_until("ingest to wait", || limiter.status().ingest_waiting == 1);
            limiter.close();
            assert_eq!(ingest.join().unwrap(), Err(WaitError::Closed));
        });
        assert_eq!(limiter.wait_for_room(GUARD), Err(WaitError::Closed));
        // Refusals after close are shutdown, not backpressure.
        assert!(!limiter.try_accept());
        assert!(limiter.is_closed());
        assert_eq!(limiter.status().ingest_refused, 1);
    }

    #[derive(Debug, Clone)]
    enum Op {
        /// Store this many transitions.
        Insert(usize),
        /// Offer an episode: recorded only if ingest is admitted.
        Episode,
        /// One update attempt with a zero timeout.
        Update,
    }

    fn op() -> impl Strategy<Value = Op> {
        prop_oneof![
            (0usize..8).prop_map(Op::Insert),
            Just(Op::Episode),
            Just(Op::Update),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        /// Any single-threaded interleaving: each call does what the rule says, the deficit
        /// stays in `0 ..= B + r`, and draining leaves `U = floor(C * r)`.
        #[test]
        fn any_interleaving_stays_within_the_bound(
            r in prop_oneof![
                Just(0.25), Just(0.5), Just(1.0), Just(2.5), Just(3.0), Just(40.0), 0.1f64..50.0,
            ],
            extra in 0.0f64..3.0,
            m in 1usize..30,
            ops in prop::collection::vec(op(), 0..300),
        ) {
            let b = r.max(1.0) + extra * r;
            let limiter = RateLimiter::new(config(r, b, m), m).unwrap();
            let (mut inserts, mut episodes, mut credited, mut updates, mut refused) =
                (0u64, 0u64, 0u64, 0u64, 0u64);
            for op in ops {
                let owed = (updates + 1) as f64 <= credited as f64 * r;
                let deficit = credited as f64 * r - updates as f64;
                match op {
                    Op::Insert(n) => {
                        limiter.record_insert(n);
                        inserts += n as u64;
                    }
                    Op::Episode => {
                        let admitted = limiter.try_accept();
                        prop_assert_eq!(admitted, deficit <= b);
                        if admitted {
                            limiter.record_episode();
                            episodes += 1;
                            credited += u64::from(inserts >= m as u64);
                        } else {
                            refused += 1;
                        }
                    }
                    Op::Update => {
                        let granted = limiter.acquire_update(Duration::ZERO);
                        prop_assert_eq!(granted.is_ok(), owed);
                        updates += u64::from(granted.is_ok());
                    }
                }
                let s = limiter.status();
                prop_assert_eq!(
                    (s.inserts, s.episodes, s.credited_episodes, s.updates, s.ingest_refused),
                    (inserts, episodes, credited, updates, refused)
                );
                prop_assert!(s.deficit >= 0.0, "D = {}", s.deficit);
                prop_assert!(s.deficit <= b + r + 1e-9 * b, "D = {} > {}", s.deficit, b + r);
            }
            drain(&limiter);
            let s = limiter.status();
            let earned = s.credited_episodes as f64 * r;
            prop_assert!(s.updates as f64 <= earned && earned < (s.updates + 1) as f64);
        }
    }
}
