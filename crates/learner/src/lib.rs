//! The HAC learner, independent of any transport: the run's single source of truth.
//!
//! - [`Learner::register`] admits an actor (a fresh incarnation, the run's config, a seed).
//! - [`Learner::ingest`] validates each message (known actor, current incarnation, sequence,
//!   dimensions, finite values, level range), stores every `(actor, incarnation, sequence)`
//!   exactly once (resends of stored messages count as duplicates and are acknowledged), and
//!   routes batches to the actor's replay shard of the batch's level.
//! - One trainer thread per level takes updates from its [`RateLimiter`] (updates per ingested
//!   episode, the paper's 40 by default), so training neither runs ahead of the data nor falls
//!   behind it; [`Learner::wait_for_room`] is the backpressure ingest applies to actors. The
//!   levels share `learner_threads` ([`level_threads`]): a level with more than one thread cuts
//!   each minibatch's gradient among them (weights bit-identical to one thread's).
//! - Weights are published as whole-model, versioned [`WeightsSnapshot`]s through a
//!   [`Published`] cell: whenever every level has caught up with the episodes ingested (so an
//!   actor that waits for it gets exactly the paper's schedule), when every level has done
//!   `publish_every_updates` more updates, and otherwise at the latest `max_publish_delay` after
//!   fresh weights appeared.
//! - Episode turns ([`Learner::await_turn`], with `episodes_in_flight` > 0): trainers ask before
//!   each episode and the learner lets at most that many training episodes be played or wait to
//!   be trained on at once, over all actors, granting turns in the order asked. Many actors then
//!   act on weights as fresh as one lockstep actor does, instead of on weights that miss every
//!   episode the others have in flight.
//! - [`Learner::report_evaluation`] collects greedy test results into the learning curve; the
//!   run finishes when a point reaches `stop_at` or the episode budget is trained (and
//!   evaluated, if an evaluator is registered). The final snapshot says so, and actors stop.
//!
//! - [`Learner::status`] is a consistent-enough snapshot for operators (counters, per-level
//!   replay and rate limiter state, rates over a sliding [`RateWindow`], every actor); the
//!   per-actor message rate limit ([`Learner::throttle`], a [`TokenBucket`] per actor) is applied
//!   by the transports before they hand a message to ingest.
//! - [`Learner::checkpoint`] takes a consistent cut of the whole state (ingest paused, each
//!   trainer snapshotted between two updates) as a [`LearnerCheckpoint`], and
//!   [`Learner::resume`] continues from one: the same weights, optimiser state, update counts,
//!   random streams, counters and curve, with weights versions continuing above the
//!   checkpoint's (`checkpoint` module; files in safetensors and JSON).
//!
//! Transports (in-process, gRPC, shared memory) are thin adapters over these methods; they live in
//! `hac-transport`.

mod best;
mod checkpoint;
mod hiro;
pub mod wal;

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use hac_agent::{Agent, LevelReport, RoundReport, RunConfig};
use hac_core::{Batch, EnvSpec, LevelDims, LimitError, Rng, TransitionLimits};
use hac_nn::{Diverged, LearnerBackup, LevelModel, UpdateStats};
use hac_proto::{
    ActorRole, Admission, Evaluation, IngestItemRef, IngestMessage, IngestRef, PreviousIncarnation,
    Registration, WeightsSnapshot, WireError, check_batch,
};
use hac_replay::{
    RateLimiter, RateLimiterConfig, RateLimiterConfigError, RateLimiterStatus, Replay, WaitError,
};
use parking_lot::{Condvar, Mutex, RwLock};
use sha2::{Digest, Sha256};

pub use best::RECENT_SNAPSHOTS;
use best::RecentSnapshots;
pub use checkpoint::{CheckpointError, LearnerCheckpoint};
pub use hac_core::rates::{RATES_WINDOW, RateWindow, TokenBucket};
pub use hac_proto::{BestWeights, Published, RejectReason};
pub use wal::{Wal, WalError, WalOptions, WalStatus};

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

/// Why the learner could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    #[error(transparent)]
    Config(#[from] hac_agent::RunConfigError),
    #[error(transparent)]
    Options(#[from] InvalidOption),
    /// The run's environment is not one this learner serves (a grid world), or cannot be made.
    #[error("invalid value for `env`: {0}")]
    Env(String),
    #[error("level {level}: invalid rate limiter setting `{}`: {source}", source.field())]
    RateLimiter {
        level: usize,
        #[source]
        source: RateLimiterConfigError,
    },
    /// The checkpoint to resume from does not fit this run.
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// The write-ahead log could not be read back or opened.
    #[error(transparent)]
    Wal(#[from] WalError),
}

/// Why a registration was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RegisterError {
    #[error("register_request.actor_id is empty")]
    EmptyActorId,
    #[error("the run is finished")]
    Finished,
}

/// Why an ingest message or evaluation report was refused. Nothing of a refused message is
/// stored; the actor's earlier messages are unaffected.
#[derive(Debug, Clone, thiserror::Error)]
pub enum IngestError {
    #[error(transparent)]
    Invalid(#[from] WireError),
    #[error("unknown actor `{0}`: register first")]
    UnknownActor(String),
    #[error(
        "actor `{actor}`: incarnation {got} is not the current one ({current}); register again"
    )]
    StaleIncarnation {
        actor: String,
        got: u64,
        current: u64,
    },
    #[error("actor `{actor}`: sequence {got} skips ahead of the next expected sequence {expected}")]
    SequenceGap {
        actor: String,
        got: u64,
        expected: u64,
    },
    #[error("actor `{actor}`: {source}")]
    OutOfRange {
        actor: String,
        #[source]
        source: LimitError,
    },
    #[error(
        "actor `{actor}`: episode_summary.env_steps {got} is above the episode budget of {max} \
         primitive actions"
    )]
    EpisodeTooLong { actor: String, got: u64, max: u64 },
    #[error("actor `{0}` is an evaluator: evaluators send no transitions")]
    WrongRole(String),
    #[error(
        "actor `{0}` is a trainer and an evaluator is registered: only evaluators report \
         evaluations then"
    )]
    TrainerEvaluation(String),
    #[error("evaluation_report.weights_version {0} was never published")]
    UnknownWeightsVersion(u64),
    #[error(
        "evaluation of weights from another learner process (learner_start {got}, this one is \
         {current}): the learner restarted since; evaluate its weights instead"
    )]
    StaleWeights { got: u64, current: u64 },
    #[error("the run is finished")]
    Finished,
}

impl IngestError {
    pub fn reason(&self) -> RejectReason {
        match self {
            Self::Invalid(e) => RejectReason::of_wire(e),
            Self::UnknownActor(_) => RejectReason::UnknownActor,
            Self::StaleIncarnation { .. } => RejectReason::StaleIncarnation,
            Self::SequenceGap { .. } => RejectReason::SequenceGap,
            Self::OutOfRange { .. } | Self::EpisodeTooLong { .. } => RejectReason::OutOfRange,
            Self::WrongRole(_) | Self::TrainerEvaluation(_) => RejectReason::WrongRole,
            Self::UnknownWeightsVersion(_) => RejectReason::InvalidBatch,
            Self::StaleWeights { .. } => RejectReason::StaleWeights,
            Self::Finished => RejectReason::Finished,
        }
    }
}

/// What became of an accepted ingest message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stored {
    /// Stored now.
    New,
    /// Stored before (a resend); acknowledged again, not stored twice.
    Duplicate,
}

/// The answer to [`Learner::await_turn`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Turn {
    /// The actor may play its next training episode now.
    pub granted: bool,
    /// Training episodes every level had trained on (and published) when the answer was given.
    pub episodes: u64,
}

/// Episode turns in status.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TurnStatus {
    /// `episodes_in_flight` (0: no turns).
    pub limit: u32,
    /// Turns granted whose episode has not arrived yet.
    pub held: u64,
    /// Trainers waiting for a turn now.
    pub waiting: u64,
    pub granted: u64,
    /// Turns whose lease ran out before their episode arrived.
    pub expired: u64,
}

/// The default [`LearnerOptions::turn_lease`].
pub const TURN_LEASE: Duration = Duration::from_secs(60);

/// The longest a single [`Learner::await_turn`] call waits; actors ask again.
pub const MAX_TURN_WAIT: Duration = Duration::from_secs(10);

/// How long a place in the line for turns is kept after the call holding it ended without a
/// turn.
const PLACE_KEPT: Duration = Duration::from_secs(2);

/// A place in the line for turns.
#[derive(Debug)]
struct Waiter {
    actor: String,
    incarnation: u64,
    /// A call is waiting on this place now.
    asking: bool,
    /// When the last call on this place ended.
    left_at: Instant,
}

/// Who holds and who waits for episode turns.
#[derive(Debug, Default)]
struct TurnState {
    /// Actor id -> (incarnation, when granted).
    holders: HashMap<String, (u64, Instant)>,
    /// Places in line by ticket, served lowest first among the actors asking now. A place
    /// outlives the call that took it by [`PLACE_KEPT`], so that an actor asking again after
    /// its call timed out keeps its place instead of going to the back.
    waiting: BTreeMap<u64, Waiter>,
    next_ticket: u64,
    granted: u64,
    expired: u64,
}

/// The backpressure wait ended without room.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum RoomError {
    #[error("the learner is behind; try again")]
    TimedOut,
    #[error("the run is finished")]
    Finished,
}

/// One registered actor.
#[derive(Debug)]
struct ActorEntry {
    role: ActorRole,
    hostname: String,
    /// Registration order of the actor id (stable across its incarnations): picks its shard.
    ordinal: u64,
    incarnation: u64,
    /// Every sequence up to this one is stored (0: none yet).
    stored_through: u64,
    registered_at: Instant,
    last_seen: Instant,
    episodes: u64,
    env_steps: u64,
    batches: u64,
    transitions: u64,
    duplicates: u64,
    weights_version: u64,
    /// How the actor reaches the learner, as its transport reported it ("" until then).
    transport: &'static str,
    /// `[env_steps]` over time, for the actor's env steps per second.
    env_steps_rate: RateWindow,
    /// The message rate limit, carried over from the actor's earlier incarnations.
    bucket: Option<TokenBucket>,
}

impl ActorEntry {
    fn new(
        role: ActorRole,
        hostname: String,
        ordinal: u64,
        incarnation: u64,
        bucket: Option<TokenBucket>,
        now: Instant,
    ) -> Self {
        Self {
            role,
            hostname,
            ordinal,
            incarnation,
            stored_through: 0,
            registered_at: now,
            last_seen: now,
            episodes: 0,
            env_steps: 0,
            batches: 0,
            transitions: 0,
            duplicates: 0,
            weights_version: 0,
            transport: "",
            env_steps_rate: RateWindow::new(now, 1, RATES_WINDOW),
            bucket,
        }
    }
}

/// A level's trainer output, shared with ingest and the publisher.
#[derive(Debug)]
struct LevelSlot {
    /// The actor network (safetensors) after `weights_updates` updates.
    weights: Arc<Vec<u8>>,
    weights_updates: u64,
    /// Updates finished (granted updates may still be running).
    completed: u64,
    /// Episodes ingested whose owed updates are all finished and in `weights`.
    covered_episodes: u64,
    last: Option<UpdateStats>,
    /// Updates undone because they diverged, in all and in a row now.
    diverged: u64,
    diverged_in_a_row: u32,
    last_divergence: Option<Diverged>,
}

/// Updates undone in a row after which a level counts as failing: health goes `NOT_SERVING`
/// with the reason until an update of the level succeeds again.
pub const MAX_DIVERGED_IN_A_ROW: u32 = 10;

#[derive(Debug)]
struct PublisherState {
    version: u64,
    published_updates: Vec<u64>,
    published_episodes: u64,
    last_publish: Instant,
    /// `version -> episodes` of every snapshot, to place evaluations on the curve.
    episodes_of: BTreeMap<u64, u64>,
    /// The newest snapshots, one of which an evaluation may make the best.
    recent: RecentSnapshots,
}

#[derive(Debug)]
struct CurveState {
    points: Vec<RoundReport>,
    last_at: Instant,
    last_env_steps: u64,
    last_updates: u64,
}

/// Counters for status; monotone.
#[derive(Debug, Default)]
struct Counters {
    messages: AtomicU64,
    duplicates: AtomicU64,
    batches: AtomicU64,
    transitions: AtomicU64,
    episodes: AtomicU64,
    successes: AtomicU64,
    env_steps: AtomicU64,
    rejected: [AtomicU64; RejectReason::ALL.len()],
    /// Messages the per-actor rate limit held back, and the waits it imposed (nanoseconds).
    throttled: AtomicU64,
    throttled_ns: AtomicU64,
}

/// Checkpoint requests to the trainers, and their answers.
#[derive(Debug)]
struct Snapshots {
    /// Set by a checkpoint for each level; the level's trainer clears it when it answers.
    requested: Vec<AtomicBool>,
    /// Each trainer's answer, taken by the checkpoint.
    taken: Mutex<Vec<Option<checkpoint::LevelSnapshot>>>,
    served: Condvar,
    /// One checkpoint at a time.
    one_at_a_time: Mutex<()>,
}

#[derive(Debug)]
struct Shared {
    run: RunConfig,
    run_toml: String,
    digest: String,
    dims: Vec<LevelDims>,
    options: LearnerOptions,
    replay: Replay,
    /// What each level's transitions can hold (admission by meaning).
    limits: Vec<TransitionLimits>,
    /// The episode budget: no episode summary reports more env steps.
    max_episode_actions: u64,
    limiters: Vec<RateLimiter>,
    actors: RwLock<HashMap<String, Arc<Mutex<ActorEntry>>>>,
    /// The next new actor id's registration order (ids forgotten and back get a new one).
    next_ordinal: AtomicU64,
    next_incarnation: AtomicU64,
    slots: Vec<Mutex<LevelSlot>>,
    publisher: Mutex<PublisherState>,
    /// This process's random id, in every snapshot (`WeightsSnapshot::learner_start`).
    learner_start: u64,
    /// `publisher.published_episodes`, readable without the publisher's lock.
    published_episodes: AtomicU64,
    turns: Mutex<TurnState>,
    turn_changed: Condvar,
    weights: Published<WeightsSnapshot>,
    /// The first snapshot, then each that covered more episodes than the one before: weights
    /// fixed by the schedule rather than by when a trainer offered them (with one lockstep
    /// actor, the weights of the episode just played). HIRO's off-policy correction reads its
    /// low-level policy here, so that a seed gives the same run.
    covering: Published<WeightsSnapshot>,
    /// Why the learner is unhealthy (a level failing, see [`MAX_DIVERGED_IN_A_ROW`]), or
    /// `None`; republished whenever that changes.
    trouble: Published<Option<String>>,
    /// The weights of the best test round so far; republished when a round beats it.
    best: Published<BestWeights>,
    curve: Mutex<CurveState>,
    counters: Counters,
    /// `[transitions, batches, episodes, env_steps, updates of level 0, 1, ...]` over time.
    rates: Mutex<RateWindow>,
    finished: AtomicBool,
    /// Why the run completed (budget or target reached), if it did; an interrupted run has
    /// none and can be resumed.
    completed: Mutex<Option<String>>,
    started: Instant,
    /// Training time before this process resumed the run.
    elapsed_before: Duration,
    /// Ingest and evaluation reports hold it shared; a checkpoint holds it exclusively, which
    /// pauses them so that counters, replay and curve form one cut.
    gate: RwLock<()>,
    /// An ingest holds it shared while it inserts a batch and counts it; [`Shared::status`]
    /// holds it exclusively while it reads the replay totals and the transition counter, so a
    /// status's per-level totals add up to its total. Innermost: nothing is taken under it.
    counting: RwLock<()>,
    snapshots: Snapshots,
    /// The write-ahead log (see [`LearnerOptions::wal`]).
    wal: Option<Wal>,
}

/// A running learner; share it with `Arc`. Call [`shutdown`](Self::shutdown) to stop the
/// trainers and take the trained agent.
#[derive(Debug)]
pub struct Learner {
    shared: Arc<Shared>,
    trainers: Mutex<Vec<JoinHandle<(LevelModel, Rng)>>>,
}

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
    /// (a level is failing at [`MAX_DIVERGED_IN_A_ROW`]).
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
    /// Over the time since the actor's previous status sample (about [`RATES_WINDOW`]).
    pub env_steps_per_s: f64,
    /// Every sequence of the incarnation up to this one is stored (acknowledged).
    pub stored_through: u64,
    /// ... and up to this one durable: in the write-ahead log on disk (or, without one, equal
    /// to `stored_through`). `stored_through - durable_through` is the ack-durable gap.
    pub durable_through: u64,
}

/// Ingest rates over a sliding window (about [`RATES_WINDOW`], or the time since the previous
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

/// What [`Learner::shutdown`] hands back; [`FinishedRun::checkpoint`] saves its final state.
#[derive(Debug)]
pub struct FinishedRun {
    pub agent: Agent,
    pub curve: Vec<RoundReport>,
    /// The weights of the best test round, if any round was evaluated.
    pub best: Option<Arc<BestWeights>>,
    pub status: LearnerStatus,
    /// The trainers' random streams as they stopped, level 0 first.
    rngs: Vec<Rng>,
    shared: Arc<Shared>,
}

impl Learner {
    /// Validates `run` and `options`, builds replay, rate limiters and networks (seeded from
    /// `run.seed`), starts one trainer thread per level and publishes weights version 1.
    pub fn start(run: RunConfig, options: LearnerOptions) -> Result<Self, StartError> {
        Self::launch(run, options, None)
    }

    /// [`start`](Self::start), or with `from`, [`resume`](Self::resume).
    fn launch(
        run: RunConfig,
        options: LearnerOptions,
        from: Option<&LearnerCheckpoint>,
    ) -> Result<Self, StartError> {
        run.validate("the run config")?;
        if run.is_tabular() {
            return Err(StartError::Env(format!(
                "`{}` is a grid world for the tabular learner (`hac train`), not the neural \
                 learner service",
                run.env
            )));
        }
        options.validate()?;
        let env = run.make_env().map_err(|e| StartError::Env(e.to_string()))?;
        let spec: EnvSpec = env.spec().clone();
        let config = &run.agent;
        let dims: Vec<LevelDims> = (0..config.levels)
            .map(|l| spec.level_dims(l, config.levels))
            .collect();
        let limits: Vec<TransitionLimits> = (0..config.levels)
            .map(|level| match run.hiro() {
                None => {
                    TransitionLimits::for_level(&spec, level, config.levels, config.horizon as f32)
                }
                Some(hiro) => TransitionLimits::for_hiro_level(&spec, level, hiro.c),
            })
            .collect();
        // A HIRO run's high level keeps its low-level steps beside its transitions.
        let replay = Replay::for_agent(&spec, config, run.replay_shards, &run.extra_widths(&spec));
        let limiters = (0..config.levels)
            .map(|level| {
                let mut limiter_config = RateLimiterConfig::for_agent(config);
                if let Some(hiro) = run.hiro() {
                    limiter_config.updates_per_episode =
                        hiro.updates_per_episode(level, spec.max_actions);
                }
                limiter_config.error_buffer =
                    options.error_buffer_episodes * limiter_config.updates_per_episode.max(1.0);
                RateLimiter::new(limiter_config, replay.table(level).capacity())
                    .map_err(|source| StartError::RateLimiter { level, source })
            })
            .collect::<Result<Vec<_>, _>>()?;

        // The same streams as the embedded trainer: networks first, then one sampler stream per
        // level.
        let mut root = Rng::seed_from(run.seed);
        let agent = Agent::for_run(&spec, &run, &mut root);
        let mut level_rngs: Vec<Rng> = (0..config.levels).map(|_| root.fork()).collect();
        let mut learners = agent.into_levels();
        let run_toml = run.to_toml();
        let digest = hex(&Sha256::digest(run_toml.as_bytes()));
        let resumed = match from {
            Some(checkpoint) => Some(checkpoint.restore_into(
                &run,
                &digest,
                &spec,
                &mut learners,
                &mut level_rngs,
                &replay,
                &limiters,
            )?),
            None => None,
        };
        let slots = learners
            .iter()
            .enumerate()
            .map(|(level, l)| {
                // A fresh learner has done 0 updates; a restored one all of its checkpoint's.
                Mutex::new(LevelSlot {
                    weights: Arc::new(l.actor().to_safetensors()),
                    weights_updates: l.updates(),
                    completed: l.updates(),
                    covered_episodes: resumed.map_or(0, |r| r.covered_episodes(level)),
                    last: resumed.and_then(|r| r.last_stats(level)),
                    diverged: 0,
                    diverged_in_a_row: 0,
                    last_divergence: None,
                })
            })
            .collect();
        let levels = config.levels;
        let batch_size = config.batch_size;
        let mut shared = Shared {
            run,
            run_toml,
            digest,
            dims,
            options,
            replay,
            limits,
            max_episode_actions: spec.max_actions as u64,
            limiters,
            actors: RwLock::default(),
            next_ordinal: AtomicU64::new(0),
            next_incarnation: AtomicU64::new(resumed.map_or(1, |r| r.next_incarnation)),
            publisher: Mutex::new(PublisherState {
                // Resumed: the next snapshot's version is above every version of the checkpoint.
                version: resumed.map_or(0, |r| r.weights_version),
                published_updates: learners.iter().map(LevelModel::updates).collect(),
                published_episodes: resumed.map_or(0, |r| r.published_episodes),
                last_publish: Instant::now(),
                episodes_of: BTreeMap::new(),
                recent: RecentSnapshots::default(),
            }),
            learner_start: learner_start_id(),
            published_episodes: AtomicU64::new(resumed.map_or(0, |r| r.published_episodes)),
            turns: Mutex::default(),
            turn_changed: Condvar::new(),
            slots,
            weights: Published::default(),
            covering: Published::default(),
            trouble: Published::default(),
            best: Published::default(),
            curve: Mutex::new(CurveState {
                points: resumed.map_or_else(Vec::new, |r| r.curve.clone()),
                last_at: Instant::now(),
                last_env_steps: resumed.map_or(0, |r| r.curve_env_steps),
                last_updates: resumed.map_or(0, |r| r.curve_updates),
            }),
            counters: resumed.map_or_else(Counters::default, |r| r.counters.restore()),
            rates: Mutex::new(RateWindow::new(Instant::now(), 4 + levels, RATES_WINDOW)),
            finished: AtomicBool::new(false),
            completed: Mutex::new(None),
            started: Instant::now(),
            elapsed_before: resumed.map_or(Duration::ZERO, |r| {
                Duration::try_from_secs_f64(r.elapsed_s).unwrap_or_default()
            }),
            gate: RwLock::new(()),
            counting: RwLock::new(()),
            snapshots: Snapshots {
                requested: (0..levels).map(|_| AtomicBool::new(false)).collect(),
                taken: Mutex::new(vec![None; levels]),
                served: Condvar::new(),
                one_at_a_time: Mutex::new(()),
            },
            wal: None,
        };
        // Only with a log: without one, actors hold only what was never acknowledged, and a
        // registry from the checkpoint would expect them to resend what they dropped since.
        if let (Some(r), Some(_)) = (resumed, &shared.options.wal) {
            checkpoint::restore_actors(&shared, r);
        }
        if let Some(wal_options) = shared.options.wal.clone() {
            // Everything stored after the checkpoint's cut (or since the run began) is stored
            // again, exactly as it was; then every actor is durable through what it has stored.
            let from = resumed.map_or(1, |r| r.wal_lsn.max(1));
            let mut expected = from;
            let (wal, recovered) = Wal::open(wal_options, from, |record| {
                if record.lsn != expected {
                    tracing::error!(
                        expected,
                        found = record.lsn,
                        "the write-ahead log does not continue the checkpoint: records between \
                         them are lost"
                    );
                }
                expected = record.lsn + 1;
                shared.replay_record(&record);
            })?;
            for (id, entry) in shared.actors.read().iter() {
                let entry = entry.lock();
                wal.set_durable(id, entry.incarnation, entry.stored_through);
            }
            if recovered.records > 0 || recovered.cut_reason.is_some() {
                tracing::info!(
                    records = recovered.records,
                    cut_bytes = recovered.cut_bytes,
                    transitions = shared.counters.transitions.load(Ordering::Relaxed),
                    episodes = shared.counters.episodes.load(Ordering::Relaxed),
                    actors = shared.actors.read().len(),
                    "write-ahead log replayed"
                );
            }
            shared.wal = Some(wal);
        }
        let shared = Arc::new(shared);
        shared.publish(false);
        shared.trouble.publish(Arc::new(None));
        if let Some(best) = from.and_then(LearnerCheckpoint::best) {
            shared.best.publish(Arc::new(best));
        }
        let shares = level_threads(shared.options.learner_threads, levels);
        for (learner, threads) in learners.iter_mut().zip(shares) {
            learner.set_threads(threads);
        }
        let trainers = learners
            .into_iter()
            .zip(level_rngs)
            .enumerate()
            .map(|(level, (learner, rng))| {
                let shared = shared.clone();
                let batch = Batch::zeros_with_extra(
                    shared.dims[level],
                    shared.replay.table(level).extra_width(),
                    batch_size,
                );
                std::thread::Builder::new()
                    .name(format!("trainer-{level}"))
                    .spawn(move || shared.train_level(level, learner, rng, batch))
                    .expect("spawning a trainer thread")
            })
            .collect();
        tracing::info!(
            env = %shared.run.env,
            levels,
            digest = %shared.digest,
            resumed_from_version = resumed.map(|r| r.weights_version),
            "learner started"
        );
        Ok(Self {
            shared,
            trainers: Mutex::new(trainers),
        })
    }

    pub fn run_config(&self) -> &RunConfig {
        &self.shared.run
    }

    /// Dimensions of each level's transitions, level 0 first.
    pub fn dims(&self) -> &[LevelDims] {
        &self.shared.dims
    }

    pub fn options(&self) -> &LearnerOptions {
        &self.shared.options
    }

    /// The weights of the best test round so far (none before the first round): a cell
    /// republished whenever a round beats every earlier one.
    pub fn best(&self) -> &Published<BestWeights> {
        &self.shared.best
    }

    /// The weights cell: the latest snapshot, waitable from threads and tasks.
    pub fn weights(&self) -> &Published<WeightsSnapshot> {
        &self.shared.weights
    }

    pub fn is_finished(&self) -> bool {
        self.shared.finished.load(Ordering::Acquire)
    }

    /// Why the learner is unhealthy now (`None`: it is not): a level whose last
    /// [`MAX_DIVERGED_IN_A_ROW`] updates all diverged and were undone. Servers report
    /// `NOT_SERVING` while it is set; its weights stay the last good ones.
    pub fn trouble(&self) -> &Published<Option<String>> {
        &self.shared.trouble
    }

    /// Admits an actor: a fresh incarnation (an actor id registering again supersedes its
    /// earlier incarnation, whose messages are refused from now on), the run's config and a
    /// seed derived from the run's seed, the actor's registration order and the incarnation.
    pub fn register(&self, registration: Registration) -> Result<Admission, RegisterError> {
        self.register_again(registration, None)
    }

    /// [`register`](Self::register) for a link that registers again and names the incarnation
    /// its messages are numbered under (`previous`): the new incarnation is above it, never the
    /// same number, so that messages of the old numbering still in flight are refused as stale
    /// instead of being taken for the new incarnation's (a restarted learner counts its
    /// incarnations from where its checkpoint left off, or from 1).
    pub fn register_again(
        &self,
        registration: Registration,
        previous: Option<PreviousIncarnation>,
    ) -> Result<Admission, RegisterError> {
        if registration.actor_id.is_empty() {
            return Err(RegisterError::EmptyActorId);
        }
        if self.is_finished() {
            return Err(RegisterError::Finished);
        }
        let shared = &self.shared;
        let now = Instant::now();
        shared.forget_silent_actors(now);
        if let Some(previous) = previous {
            if let Some(ordinal) = shared.keep_incarnation(&registration, previous, now) {
                tracing::info!(
                    actor = %registration.actor_id,
                    role = ?registration.role,
                    incarnation = previous.incarnation,
                    resend_from = previous.resend_from,
                    "actor registered again under its incarnation"
                );
                return Ok(shared.admission(previous.incarnation, ordinal));
            }
            shared
                .next_incarnation
                .fetch_max(previous.incarnation.saturating_add(1), Ordering::Relaxed);
        }
        let incarnation = shared.next_incarnation.fetch_add(1, Ordering::Relaxed);
        let ordinal = {
            let mut actors = shared.actors.write();
            let (ordinal, bucket) = match actors.get(&registration.actor_id) {
                Some(earlier) => {
                    let earlier = earlier.lock();
                    (earlier.ordinal, earlier.bucket.clone())
                }
                None => (shared.next_ordinal.fetch_add(1, Ordering::Relaxed), None),
            };
            let bucket = bucket.or_else(|| {
                shared
                    .options
                    .max_actor_messages_per_second
                    .map(|rate| TokenBucket::new(rate, now))
            });
            actors.insert(
                registration.actor_id.clone(),
                Arc::new(Mutex::new(ActorEntry::new(
                    registration.role,
                    registration.hostname.clone(),
                    ordinal,
                    incarnation,
                    bucket,
                    now,
                ))),
            );
            ordinal
        };
        // A turn held, or a place in line kept, by an earlier incarnation will never be used.
        {
            let mut turns = shared.turns.lock();
            let held = turns.holders.remove(&registration.actor_id).is_some();
            let places = turns.waiting.len();
            turns
                .waiting
                .retain(|_, w| w.asking || w.actor != registration.actor_id);
            if held || turns.waiting.len() != places {
                shared.turn_changed.notify_all();
            }
        }
        tracing::info!(
            actor = %registration.actor_id,
            role = ?registration.role,
            incarnation,
            "actor registered"
        );
        Ok(shared.admission(incarnation, ordinal))
    }

    /// The highest sequence of `actor_id`'s `incarnation` that is durable: in the write-ahead log
    /// on disk (or recovered from it and the checkpoint), so that a learner killed now and
    /// resumed still has it. Without a log, what is stored (acknowledged). 0 for an unknown
    /// actor or another incarnation.
    pub fn durable_through(&self, actor_id: &str, incarnation: u64) -> u64 {
        match &self.shared.wal {
            Some(wal) => wal.durable_through(actor_id, incarnation),
            None => self.shared.actor(actor_id).map_or(0, |entry| {
                let entry = entry.lock();
                if entry.incarnation == incarnation {
                    entry.stored_through
                } else {
                    0
                }
            }),
        }
    }

    /// Published after every commit of the write-ahead log (`None` without one: what is stored is
    /// durable at once): transports wait on it to tell actors that durability advanced.
    pub fn durable_commits(&self) -> Option<&Published<u64>> {
        self.shared.wal.as_ref().map(Wal::commits)
    }

    /// Waits until every message stored so far is in the write-ahead log on disk (true at once
    /// without one); false if `timeout` passed first or the log failed.
    pub fn sync_wal(&self, timeout: Duration) -> bool {
        self.shared.wal.as_ref().is_none_or(|wal| wal.sync(timeout))
    }

    /// For tests of recovery: stops the write-ahead log without committing what waits for its
    /// next commit, as `kill -9` would, and finishes the run. Nothing more is durable.
    #[doc(hidden)]
    pub fn simulate_crash(&self) {
        if let Some(wal) = &self.shared.wal {
            wal.abandon();
        }
        self.shared.finish("crashed");
    }

    /// Deletes the write-ahead log's segments before `before_lsn` (a written checkpoint's
    /// [`LearnerCheckpoint::wal_lsn`]: the oldest checkpoint a resume may fall back to, so that
    /// each kept checkpoint still has the log after its cut); returns the bytes freed.
    pub fn truncate_wal(&self, before_lsn: u64) -> Result<u64, WalError> {
        self.shared.truncate_wal(before_lsn)
    }

    /// Backpressure: true if ingest may accept more now. Ingest paths call this (or
    /// [`wait_for_room`](Self::wait_for_room)) before each message and withhold the ack while
    /// it says no.
    pub fn has_room(&self) -> bool {
        self.wait_for_room(Duration::ZERO).is_ok()
    }

    /// Waits up to `timeout` until every level's rate limiter admits more ingest.
    pub fn wait_for_room(&self, timeout: Duration) -> Result<(), RoomError> {
        let deadline = Instant::now() + timeout;
        for limiter in &self.shared.limiters {
            let left = deadline.saturating_duration_since(Instant::now());
            match limiter.wait_for_room(left) {
                Ok(()) => {}
                Err(WaitError::TimedOut) => return Err(RoomError::TimedOut),
                Err(WaitError::Closed) => return Err(RoomError::Finished),
            }
        }
        Ok(())
    }

    /// The per-actor message rate limit (`max_actor_messages_per_second`): takes a token from
    /// `actor_id`'s bucket and says how long to hold its message back before [`ingest`]
    /// (zero without a limit, or for an unknown actor, which ingest refuses anyway). Transports
    /// wait without reading further, so the actor's sends block (backpressure), and nothing is
    /// refused. Held-back messages and the waits are counted in status.
    ///
    /// [`ingest`]: Self::ingest
    pub fn throttle(&self, actor_id: &str) -> Duration {
        if self.shared.options.max_actor_messages_per_second.is_none() {
            return Duration::ZERO;
        }
        let Some(entry) = self.shared.actor(actor_id) else {
            return Duration::ZERO;
        };
        let wait = match entry.lock().bucket.as_mut() {
            Some(bucket) => bucket.take(Instant::now()),
            None => Duration::ZERO,
        };
        if !wait.is_zero() {
            let counters = &self.shared.counters;
            counters.throttled.fetch_add(1, Ordering::Relaxed);
            counters.throttled_ns.fetch_add(
                u64::try_from(wait.as_nanos()).unwrap_or(u64::MAX),
                Ordering::Relaxed,
            );
        }
        wait
    }

    /// Records how `actor_id` reaches the learner (shown in status): transports call this when
    /// an actor registers or opens a stream through them. Unknown actors are ignored.
    pub fn set_actor_transport(&self, actor_id: &str, transport: &'static str) {
        if let Some(entry) = self.shared.actor(actor_id) {
            entry.lock().transport = transport;
        }
    }

    /// Checks that `incarnation` is `actor_id`'s current one (unknown actor, stale incarnation;
    /// counted), for a transport serving a per-actor request that reaches the learner no other
    /// way (the weights watch).
    pub fn check_incarnation(&self, actor_id: &str, incarnation: u64) -> Result<(), IngestError> {
        let current = self
            .shared
            .actor(actor_id)
            .map(|entry| entry.lock().incarnation)
            .ok_or_else(|| IngestError::UnknownActor(actor_id.to_string()));
        self.counted(current.and_then(|current| {
            if current == incarnation {
                Ok(())
            } else {
                Err(IngestError::StaleIncarnation {
                    actor: actor_id.to_string(),
                    got: incarnation,
                    current,
                })
            }
        }))
    }

    /// Validates and stores one message of an actor's ingest stream; see the crate docs. On
    /// error nothing is stored and the rejection is counted.
    pub fn ingest(&self, msg: &IngestMessage) -> Result<Stored, IngestError> {
        self.ingest_ref(&msg.view())
    }

    /// [`ingest`](Self::ingest) for a borrowed message (a batch read in place from shared
    /// memory): the same checks, counts and exactly-once rule; nothing is copied but into replay.
    pub fn ingest_ref(&self, msg: &IngestRef<'_>) -> Result<Stored, IngestError> {
        // Checkpoints take the gate exclusively: a consistent cut between messages.
        let _running = self.shared.gate.read();
        self.counted(self.shared.ingest(msg))
    }

    /// `result`, with its rejection (if any) counted under its reason.
    fn counted<T>(&self, result: Result<T, IngestError>) -> Result<T, IngestError> {
        if let Err(e) = &result {
            self.count_rejection(e.reason());
        }
        result
    }

    /// Episode turns: waits up to `wait` (at most [`MAX_TURN_WAIT`]) until trainer `actor_id`
    /// may play its next training episode. A turn is granted, in the order the calls arrived,
    /// when fewer than `episodes_in_flight` training episodes are held as turns or received but
    /// not yet trained on and published; it is held until the actor's next episode summary
    /// arrives, its next registration, or `turn_lease`. Asking again while holding a turn
    /// returns it again. Without turns (`episodes_in_flight` 0) every call is granted at once.
    ///
    /// Turns schedule; they do not admit: ingest accepts episodes played without one. Errors:
    /// unknown actor, stale incarnation, an evaluator asking, the run finished (each counted).
    pub fn await_turn(
        &self,
        actor_id: &str,
        incarnation: u64,
        wait: Duration,
    ) -> Result<Turn, IngestError> {
        self.counted(self.shared.await_turn(actor_id, incarnation, wait))
    }

    /// Counts a rejection the transport found before the learner saw the message (malformed,
    /// oversized or unauthenticated input).
    pub fn count_rejection(&self, reason: RejectReason) {
        let index = RejectReason::ALL
            .iter()
            .position(|&r| r == reason)
            .expect("every reason is listed");
        self.shared.counters.rejected[index].fetch_add(1, Ordering::Relaxed);
    }

    /// Adds an evaluator's (or a self-evaluating trainer's) greedy test results to the learning
    /// curve, at the episode count of the weights version they used; may finish the run.
    pub fn report_evaluation(&self, evaluation: &Evaluation) -> Result<(), IngestError> {
        let _running = self.shared.gate.read();
        self.counted(self.shared.report_evaluation(evaluation))
    }

    /// The learning curve so far, one point per evaluation report.
    pub fn curve(&self) -> Vec<RoundReport> {
        self.shared.curve.lock().points.clone()
    }

    /// The last `max` points of the learning curve (all of them for 0), and how many there are.
    pub fn recent_curve(&self, max: usize) -> (usize, Vec<RoundReport>) {
        let curve = self.shared.curve.lock();
        let total = curve.points.len();
        let from = if max == 0 {
            0
        } else {
            total.saturating_sub(max)
        };
        (total, curve.points[from..].to_vec())
    }

    /// Publishes the current weights again as a new version and returns it (weights fan-out
    /// benchmarks; a nudge for actors waiting on a version). Nothing after the run finished.
    pub fn republish(&self) -> u64 {
        if !self.is_finished() {
            self.shared.publish(false);
        }
        self.shared.publisher.lock().version
    }

    /// Ends the run now (interrupt, shutdown): publishes the final snapshot and stops trainers.
    pub fn finish(&self, why: &str) {
        self.shared.finish(why);
    }

    pub fn status(&self) -> LearnerStatus {
        self.shared.status()
    }

    /// Training time of the run, including the time before a resume.
    pub fn elapsed(&self) -> Duration {
        self.shared.elapsed()
    }

    /// Finishes the run (if it is not already), waits for the trainer threads and returns the
    /// trained agent with the curve and final status.
    pub fn shutdown(self) -> FinishedRun {
        self.shared.finish("shutdown");
        let (levels, rngs): (Vec<LevelModel>, Vec<Rng>) = self
            .trainers
            .lock()
            .drain(..)
            .map(|t| t.join().expect("a trainer thread panicked"))
            .unzip();
        FinishedRun {
            agent: Agent::from_levels(levels),
            curve: self.curve(),
            best: self.shared.best.latest(),
            status: self.status(),
            rngs,
            shared: self.shared.clone(),
        }
    }
}

impl Shared {
    fn actor(&self, id: &str) -> Option<Arc<Mutex<ActorEntry>>> {
        self.actors.read().get(id).cloned()
    }

    /// Drops every actor not heard from for `forget_actors_after` (at registrations and status
    /// reads, so the registry stays bounded by the actors alive lately).
    fn forget_silent_actors(&self, now: Instant) {
        let limit = self.options.forget_actors_after;
        let silent = |a: &Arc<Mutex<ActorEntry>>| now.duration_since(a.lock().last_seen) >= limit;
        if !self.actors.read().values().any(silent) {
            return;
        }
        let mut actors = self.actors.write();
        let before = actors.len();
        actors.retain(|_, a| !silent(a));
        tracing::info!(forgotten = before - actors.len(), after = ?limit, "silent actors forgotten");
    }

    fn ingest(&self, msg: &IngestRef<'_>) -> Result<Stored, IngestError> {
        let counters = &self.counters;
        counters.messages.fetch_add(1, Ordering::Relaxed);
        let entry = self
            .actor(msg.actor_id)
            .ok_or_else(|| IngestError::UnknownActor(msg.actor_id.to_string()))?;
        let mut actor = entry.lock();
        if msg.incarnation != actor.incarnation {
            return Err(IngestError::StaleIncarnation {
                actor: msg.actor_id.to_string(),
                got: msg.incarnation,
                current: actor.incarnation,
            });
        }
        actor.last_seen = Instant::now();
        if msg.sequence == 0 {
            return Err(WireError::missing("ingest_request.sequence").into());
        }
        if msg.sequence <= actor.stored_through {
            actor.duplicates += 1;
            counters.duplicates.fetch_add(1, Ordering::Relaxed);
            return Ok(Stored::Duplicate);
        }
        let expected = actor.stored_through + 1;
        if msg.sequence != expected {
            return Err(IngestError::SequenceGap {
                actor: msg.actor_id.to_string(),
                got: msg.sequence,
                expected,
            });
        }
        if actor.role == ActorRole::Evaluator {
            return Err(IngestError::WrongRole(msg.actor_id.to_string()));
        }
        if self.finished.load(Ordering::Acquire) {
            return Err(IngestError::Finished);
        }
        // Admission by meaning: nothing below may fail, so what the log holds is exactly what
        // is stored.
        let shard = match msg.item {
            IngestItemRef::Batch { level, batch, .. } => {
                check_batch(level, batch, &self.dims, self.options.max_batch_transitions)?;
                self.limits[level]
                    .check(&batch)
                    .map_err(|source| IngestError::OutOfRange {
                        actor: msg.actor_id.to_string(),
                        source,
                    })?;
                // Each actor starts at its own shard and moves on by one per batch: writers
                // rarely meet, and one actor alone still fills every shard.
                (actor.ordinal as usize + actor.batches as usize)
                    % self.replay.table(level).shard_count()
            }
            IngestItemRef::Episode { env_steps, .. } => {
                if env_steps > self.max_episode_actions {
                    return Err(IngestError::EpisodeTooLong {
                        actor: msg.actor_id.to_string(),
                        got: env_steps,
                        max: self.max_episode_actions,
                    });
                }
                0
            }
        };
        if let Some(wal) = &self.wal {
            wal.append(shard as u32, msg);
        }
        let episode = self.store(&mut actor, msg, shard);
        if episode {
            let incarnation = actor.incarnation;
            drop(actor);
            {
                // The turn this episode was played in (if any) is used up; the episode counts
                // as in flight until it is trained on.
                let mut turns = self.turns.lock();
                if turns
                    .holders
                    .get(msg.actor_id)
                    .is_some_and(|&(held, _)| held == incarnation)
                {
                    turns.holders.remove(msg.actor_id);
                }
            }
            self.count_episode();
            self.maybe_publish();
        }
        Ok(Stored::New)
    }

    /// Stores an admitted message of `actor` (a batch into `shard` of its level's table) and
    /// counts it; true for an episode summary, whose effects on the rate limiters follow
    /// ([`count_episode`](Self::count_episode)) once the actor's lock is released.
    fn store(&self, actor: &mut ActorEntry, msg: &IngestRef<'_>, shard: usize) -> bool {
        let counters = &self.counters;
        let episode = match msg.item {
            IngestItemRef::Batch {
                level,
                weights_version,
                batch,
            } => {
                let table = self.replay.table(level);
                actor.batches += 1;
                self.limiters[level].record_insert(batch.len);
                {
                    let _counting = self.counting.read();
                    table.insert_batch_into(shard, batch);
                    counters.batches.fetch_add(1, Ordering::Relaxed);
                    counters
                        .transitions
                        .fetch_add(batch.len as u64, Ordering::Relaxed);
                }
                actor.transitions += batch.len as u64;
                actor.weights_version = actor.weights_version.max(weights_version);
                false
            }
            IngestItemRef::Episode {
                env_steps,
                success,
                weights_version,
            } => {
                actor.episodes += 1;
                actor.env_steps += env_steps;
                actor.weights_version = actor.weights_version.max(weights_version);
                counters.episodes.fetch_add(1, Ordering::Relaxed);
                counters
                    .successes
                    .fetch_add(u64::from(success), Ordering::Relaxed);
                counters.env_steps.fetch_add(env_steps, Ordering::Relaxed);
                true
            }
        };
        actor.stored_through = msg.sequence;
        episode
    }

    /// An episode summary was stored: every level's rate limiter owes its updates.
    fn count_episode(&self) {
        for level in 0..self.limiters.len() {
            self.limiters[level].record_episode();
            // A level with nothing owed (its table is still below one batch, or its trainer is
            // idle) covers the episode at once.
            let mut slot = self.slots[level].lock();
            let status = self.limiters[level].status();
            if status.updates == slot.completed && status.deficit < 1.0 {
                slot.covered_episodes = slot.covered_episodes.max(status.episodes);
            }
        }
    }

    /// Stores a message read back from the write-ahead log, as ingest stored it (same shard,
    /// same counts); registers its actor as a trainer if the registry does not know it yet, or
    /// under the record's incarnation if it was a newer one.
    fn replay_record(&self, record: &wal::Record<'_>) {
        let msg = &record.message;
        let now = Instant::now();
        let entry = {
            let mut actors = self.actors.write();
            actors
                .entry(msg.actor_id.to_string())
                .or_insert_with(|| {
                    let ordinal = self.next_ordinal.fetch_add(1, Ordering::Relaxed);
                    Arc::new(Mutex::new(ActorEntry::new(
                        ActorRole::Trainer,
                        String::new(),
                        ordinal,
                        msg.incarnation,
                        None,
                        now,
                    )))
                })
                .clone()
        };
        let mut actor = entry.lock();
        if actor.incarnation != msg.incarnation {
            let (ordinal, bucket) = (actor.ordinal, actor.bucket.take());
            *actor = ActorEntry::new(
                ActorRole::Trainer,
                String::new(),
                ordinal,
                msg.incarnation,
                bucket,
                now,
            );
        }
        self.next_incarnation
            .fetch_max(msg.incarnation.saturating_add(1), Ordering::Relaxed);
        if msg.sequence != actor.stored_through + 1 {
            tracing::warn!(
                actor = %msg.actor_id,
                sequence = msg.sequence,
                expected = actor.stored_through + 1,
                "write-ahead log record out of sequence"
            );
        }
        self.counters.messages.fetch_add(1, Ordering::Relaxed);
        let shard = match msg.item {
            IngestItemRef::Batch { level, .. } if level < self.dims.len() => {
                (record.shard as usize) % self.replay.table(level).shard_count()
            }
            _ => 0,
        };
        if self.store(&mut actor, msg, shard) {
            drop(actor);
            self.count_episode();
        }
    }

    /// Keeps `previous` for an actor registering again if the registry knows it under exactly
    /// that incarnation with every sequence before `previous.resend_from` stored (a resumed
    /// learner recovered it); its ordinal then.
    fn keep_incarnation(
        &self,
        registration: &Registration,
        previous: PreviousIncarnation,
        now: Instant,
    ) -> Option<u64> {
        let entry = self.actor(&registration.actor_id)?;
        let mut actor = entry.lock();
        let keep = actor.incarnation == previous.incarnation
            && previous.resend_from <= actor.stored_through + 1
            && (actor.role == registration.role || actor.hostname.is_empty());
        if !keep {
            return None;
        }
        actor.role = registration.role;
        actor.hostname.clone_from(&registration.hostname);
        actor.last_seen = now;
        Some(actor.ordinal)
    }

    /// What an actor admitted under `incarnation` is told.
    fn admission(&self, incarnation: u64, ordinal: u64) -> Admission {
        Admission {
            incarnation,
            run_config_toml: self.run_toml.clone(),
            run_config_digest: self.digest.clone(),
            seed: mix(self.run.seed, ordinal, incarnation),
            levels: self.dims.clone(),
            max_batch_transitions: self.options.max_batch_transitions,
            max_weights_lag: self.options.max_weights_lag,
            shm: None,
            episodes_in_flight: self.options.episodes_in_flight,
            // None for HAC, whose admissions stay as they were.
            extra_widths: if self.run.hiro().is_some() {
                (0..self.dims.len())
                    .map(|level| self.replay.table(level).extra_width())
                    .collect()
            } else {
                Vec::new()
            },
        }
    }

    fn truncate_wal(&self, before_lsn: u64) -> Result<u64, WalError> {
        match &self.wal {
            Some(wal) if before_lsn > 0 => wal.truncate_before(before_lsn),
            _ => Ok(0),
        }
    }

    fn await_turn(
        &self,
        actor_id: &str,
        incarnation: u64,
        wait: Duration,
    ) -> Result<Turn, IngestError> {
        {
            let entry = self
                .actor(actor_id)
                .ok_or_else(|| IngestError::UnknownActor(actor_id.to_string()))?;
            let actor = entry.lock();
            if incarnation != actor.incarnation {
                return Err(IngestError::StaleIncarnation {
                    actor: actor_id.to_string(),
                    got: incarnation,
                    current: actor.incarnation,
                });
            }
            if actor.role == ActorRole::Evaluator {
                return Err(IngestError::WrongRole(actor_id.to_string()));
            }
        }
        let answer = |granted| Turn {
            granted,
            episodes: self.published_episodes.load(Ordering::Acquire),
        };
        let limit = u64::from(self.options.episodes_in_flight);
        if limit == 0 {
            return Ok(answer(true));
        }
        let deadline = Instant::now() + wait.min(MAX_TURN_WAIT);
        let mut turns = self.turns.lock();
        if turns
            .holders
            .get(actor_id)
            .is_some_and(|&(held, _)| held == incarnation)
        {
            return Ok(answer(true));
        }
        let kept = turns
            .waiting
            .iter()
            .find(|(_, w)| w.actor == actor_id && w.incarnation == incarnation)
            .map(|(&ticket, _)| ticket);
        let ticket = kept.unwrap_or_else(|| {
            let ticket = turns.next_ticket;
            turns.next_ticket += 1;
            ticket
        });
        turns.waiting.insert(
            ticket,
            Waiter {
                actor: actor_id.to_string(),
                incarnation,
                asking: true,
                left_at: Instant::now(),
            },
        );
        let leave = |turns: &mut TurnState, keep_place: bool| {
            match turns.waiting.get_mut(&ticket) {
                Some(w) if keep_place => {
                    w.asking = false;
                    w.left_at = Instant::now();
                }
                _ => {
                    turns.waiting.remove(&ticket);
                }
            }
            // The next in line may be able to go now.
            self.turn_changed.notify_all();
        };
        loop {
            if self.finished.load(Ordering::Acquire) {
                leave(&mut turns, false);
                return Err(IngestError::Finished);
            }
            let now = Instant::now();
            turns
                .waiting
                .retain(|_, w| w.asking || now.duration_since(w.left_at) < PLACE_KEPT);
            let before = turns.holders.len();
            let lease = self.options.turn_lease;
            turns
                .holders
                .retain(|_, &mut (_, at)| now.duration_since(at) < lease);
            turns.expired += (before - turns.holders.len()) as u64;
            let received = self.counters.episodes.load(Ordering::Acquire);
            let untrained =
                received.saturating_sub(self.published_episodes.load(Ordering::Acquire));
            let in_flight = turns.holders.len() as u64 + untrained;
            let first = turns
                .waiting
                .iter()
                .find(|(_, w)| w.asking)
                .map(|(&t, _)| t);
            if first == Some(ticket) && in_flight < limit {
                turns
                    .holders
                    .insert(actor_id.to_string(), (incarnation, now));
                turns.granted += 1;
                leave(&mut turns, false);
                return Ok(answer(true));
            }
            if now >= deadline {
                leave(&mut turns, true);
                return Ok(answer(false));
            }
            // Publications and episode summaries wake waiters; the slice bounds how late an
            // expired lease is noticed.
            let slice = (deadline - now).min(Duration::from_millis(100));
            self.turn_changed.wait_for(&mut turns, slice);
        }
    }

    fn report_evaluation(&self, evaluation: &Evaluation) -> Result<(), IngestError> {
        let entry = self
            .actor(&evaluation.actor_id)
            .ok_or_else(|| IngestError::UnknownActor(evaluation.actor_id.clone()))?;
        {
            let mut actor = entry.lock();
            if evaluation.incarnation != actor.incarnation {
                return Err(IngestError::StaleIncarnation {
                    actor: evaluation.actor_id.clone(),
                    got: evaluation.incarnation,
                    current: actor.incarnation,
                });
            }
            actor.last_seen = Instant::now();
            // A trainer may evaluate itself (`--eval-every`) while the run has no evaluator;
            // once one is registered, the curve is the evaluators' alone.
            if actor.role == ActorRole::Trainer {
                drop(actor);
                if self.has_evaluator() {
                    return Err(IngestError::TrainerEvaluation(evaluation.actor_id.clone()));
                }
            }
        }
        if evaluation.learner_start != 0 && evaluation.learner_start != self.learner_start {
            return Err(IngestError::StaleWeights {
                got: evaluation.learner_start,
                current: self.learner_start,
            });
        }
        if evaluation.episodes == 0 {
            return Err(WireError::zero("evaluation_report.episodes").into());
        }
        if evaluation.successes > evaluation.episodes {
            return Err(WireError::SuccessesAboveEpisodes {
                successes: evaluation.successes,
                episodes: evaluation.episodes,
            }
            .into());
        }
        let (episodes, snapshot) = {
            let publisher = self.publisher.lock();
            match publisher.episodes_of.get(&evaluation.weights_version) {
                Some(&e) => (e, publisher.recent.get(evaluation.weights_version).cloned()),
                None => {
                    return Err(IngestError::UnknownWeightsVersion(
                        evaluation.weights_version,
                    ));
                }
            }
        };
        {
            let mut actor = entry.lock();
            actor.weights_version = actor.weights_version.max(evaluation.weights_version);
        }
        let success_rate = evaluation.successes as f32 / evaluation.episodes as f32;
        let status = self.status();
        let env_steps = status.env_steps;
        let updates: u64 = status.levels.iter().map(|l| l.updates).sum();
        let report = {
            let mut curve = self.curve.lock();
            let dt = curve.last_at.elapsed().as_secs_f64();
            let rate = |n: u64| if dt > 0.0 { n as f64 / dt } else { 0.0 };
            let report = RoundReport {
                round: curve.points.len() + 1,
                episodes,
                env_steps,
                success_rate,
                elapsed_s: self.elapsed().as_secs_f64(),
                env_steps_per_s: rate(env_steps.saturating_sub(curve.last_env_steps)),
                updates_per_s: rate(updates.saturating_sub(curve.last_updates)),
                levels: status
                    .levels
                    .iter()
                    .map(|l| {
                        let last = l.last.unwrap_or_default();
                        LevelReport {
                            updates: l.updates,
                            replay_len: l.replay_len,
                            critic_loss: last.critic_loss,
                            actor_loss: last.actor_loss,
                            mean_q: last.mean_q,
                        }
                    })
                    .collect(),
            };
            curve.points.push(report.clone());
            curve.last_at = Instant::now();
            curve.last_env_steps = env_steps;
            curve.last_updates = updates;
            // Under the curve's lock: rounds are judged in the order they joined the curve.
            if best::improves(self.best.latest().as_deref(), success_rate) {
                match snapshot {
                    Some(snapshot) => self.best.publish(Arc::new(BestWeights {
                        round: report.round,
                        episodes,
                        env_steps,
                        success_rate,
                        snapshot,
                    })),
                    None => tracing::warn!(
                        round = report.round,
                        weights_version = evaluation.weights_version,
                        kept = RECENT_SNAPSHOTS,
                        "the best test round so far evaluated weights older than the snapshots kept: \
                         the best weights stay those of an earlier round"
                    ),
                }
            }
            report
        };
        tracing::debug!(
            episodes = report.episodes,
            success = report.success_rate,
            "evaluation"
        );
        if self
            .run
            .stop_at
            .is_some_and(|target| success_rate >= target)
        {
            self.complete("target success rate reached");
        } else if episodes >= self.run.episodes {
            self.complete("episode budget trained and evaluated");
        }
        Ok(())
    }

    /// The trainer thread of `level`: takes each update the rate limiter grants, offers the
    /// weights for publication when caught up or every `publish_every_updates`, answers
    /// checkpoint requests between updates; returns the trained networks and its random stream
    /// once the limiter is closed.
    fn train_level(
        &self,
        level: usize,
        mut learner: LevelModel,
        mut rng: Rng,
        mut batch: Batch,
    ) -> (LevelModel, Rng) {
        let limiter = &self.limiters[level];
        let table = self.replay.table(level);
        let every = self.options.publish_every_updates;
        let mut backup = LearnerBackup::default();
        let mut hiro = self.run.hiro().map(|h| {
            let env = self
                .run
                .make_env()
                .expect("the run's environment was made at start");
            hiro::HiroPrep::new(level, env, h.c, h.candidates)
        });
        loop {
            if self.snapshots.requested[level].load(Ordering::Acquire) {
                self.serve_snapshot(level, &learner, &rng);
            }
            match limiter.acquire_update(Duration::from_millis(50)) {
                Ok(()) => {}
                Err(WaitError::TimedOut) => {
                    self.maybe_publish();
                    continue;
                }
                Err(WaitError::Closed) => break,
            }
            // Granted updates are owed for credited episodes, which need a table holding at
            // least one batch.
            table
                .sample(&mut rng, &mut batch)
                .expect("an update is granted only once the table holds a batch");
            // A diverged update is undone and still counts as done: the schedule goes on with
            // the last good weights, which are all that is ever published.
            let outcome = match (&mut learner, &mut hiro) {
                (LevelModel::Hac(l), _) => l.update_or_undo(&batch, &mut backup),
                (LevelModel::Td3(l), Some(prep)) => {
                    let next_goals = prep.prepare(&mut batch, &self.covering, &mut rng);
                    l.update_or_undo(&batch, next_goals, &mut rng, &mut backup)
                }
                (LevelModel::Td3(_), None) => unreachable!("TD3 levels are HIRO's"),
            };
            // Whether the level started or stopped failing: reported once its slot is released.
            let failing_changed;
            {
                let mut slot = self.slots[level].lock();
                slot.completed += 1;
                match outcome {
                    Ok(stats) => {
                        slot.last = Some(stats);
                        failing_changed = slot.diverged_in_a_row >= MAX_DIVERGED_IN_A_ROW;
                        if failing_changed {
                            tracing::info!(level, "level recovered: an update succeeded");
                        }
                        slot.diverged_in_a_row = 0;
                    }
                    Err(diverged) => {
                        slot.diverged += 1;
                        slot.diverged_in_a_row += 1;
                        slot.last_divergence = Some(diverged);
                        let in_a_row = slot.diverged_in_a_row;
                        tracing::warn!(level, %diverged, in_a_row, "update undone");
                        failing_changed = in_a_row == MAX_DIVERGED_IN_A_ROW;
                    }
                }
                let status = limiter.status();
                let caught_up = status.updates == slot.completed && status.deficit < 1.0;
                if caught_up || slot.completed.is_multiple_of(every) {
                    slot.weights = Arc::new(learner.actor().to_safetensors());
                    slot.weights_updates = slot.completed;
                    // Under sustained ingest a level is rarely caught up, yet these weights
                    // cover every episode whose owed updates they include: the uncredited ones
                    // and the first `completed / r` credited ones.
                    let r = limiter.config().updates_per_episode;
                    let served =
                        ((slot.completed as f64 / r).floor() as u64).min(status.credited_episodes);
                    let uncredited = status.episodes - status.credited_episodes;
                    slot.covered_episodes = slot.covered_episodes.max(uncredited + served);
                }
                if caught_up {
                    slot.covered_episodes = slot.covered_episodes.max(status.episodes);
                }
            }
            if failing_changed {
                self.report_trouble();
            }
            self.maybe_publish();
        }
        (learner, rng)
    }

    /// Publishes why the learner is unhealthy (the first failing level), if that changed.
    fn report_trouble(&self) {
        let trouble = self.slots.iter().enumerate().find_map(|(level, slot)| {
            let slot = slot.lock();
            (slot.diverged_in_a_row >= MAX_DIVERGED_IN_A_ROW).then(|| {
                let last = slot
                    .last_divergence
                    .map_or_else(String::new, |d| format!(": {d}"));
                format!(
                    "level {level}: the last {} updates diverged and were undone{last}",
                    slot.diverged_in_a_row
                )
            })
        });
        if self.trouble.latest().as_deref() != Some(&trouble) {
            if let Some(why) = &trouble {
                tracing::error!(reason = %why, "learner unhealthy");
            }
            self.trouble.publish(Arc::new(trouble));
        }
    }

    /// Publishes a snapshot if coverage grew, every level has fresh weights, or some level's
    /// fresh weights have waited `max_publish_delay`; then checks whether the budget is done.
    fn maybe_publish(&self) {
        if self.finished.load(Ordering::Acquire) {
            return;
        }
        let covered = {
            let mut publisher = self.publisher.lock();
            let mut covered = u64::MAX;
            let (mut fresh, mut all_fresh) = (false, true);
            for (slot, &published) in self.slots.iter().zip(&publisher.published_updates) {
                let slot = slot.lock();
                covered = covered.min(slot.covered_episodes);
                let f = slot.weights_updates > published;
                fresh |= f;
                all_fresh &= f;
            }
            let due = covered > publisher.published_episodes
                || (fresh
                    && (all_fresh
                        || publisher.last_publish.elapsed() >= self.options.max_publish_delay));
            if !due {
                return;
            }
            self.publish_locked(&mut publisher, false);
            covered
        };
        if covered >= self.run.episodes && !self.has_evaluator() {
            self.complete("episode budget trained");
        }
    }

    fn has_evaluator(&self) -> bool {
        self.actors
            .read()
            .values()
            .any(|a| a.lock().role == ActorRole::Evaluator)
    }

    /// Publishes a snapshot of every level's latest weights as the next version.
    fn publish(&self, run_finished: bool) {
        self.publish_locked(&mut self.publisher.lock(), run_finished);
    }

    fn publish_locked(&self, publisher: &mut PublisherState, run_finished: bool) {
        let mut levels = Vec::with_capacity(self.slots.len());
        let mut covered = u64::MAX;
        for (level, slot) in self.slots.iter().enumerate() {
            let slot = slot.lock();
            levels.push(slot.weights.as_ref().clone());
            publisher.published_updates[level] = slot.weights_updates;
            covered = covered.min(slot.covered_episodes);
        }
        let covers_more =
            covered > publisher.published_episodes || self.covering.latest().is_none();
        publisher.version += 1;
        publisher.published_episodes = covered;
        publisher.last_publish = Instant::now();
        let version = publisher.version;
        publisher.episodes_of.insert(version, covered);
        // Bounded memory in long runs: evaluations refer to recent versions.
        while publisher.episodes_of.len() > 100_000 {
            publisher.episodes_of.pop_first();
        }
        let snapshot = Arc::new(WeightsSnapshot {
            version,
            levels,
            episodes: covered,
            run_finished,
            learner_start: self.learner_start,
        });
        publisher.recent.push(snapshot.clone());
        if covers_more {
            self.covering.publish(snapshot.clone());
        }
        self.weights.publish(snapshot);
        self.published_episodes.store(covered, Ordering::Release);
        // Under the turns' lock, so that a waiter between its check and its wait still wakes.
        drop(self.turns.lock());
        self.turn_changed.notify_all();
    }

    /// Finishes a run that reached its end (not an interruption): it cannot be resumed.
    fn complete(&self, why: &str) {
        if !self.finished.load(Ordering::Acquire) {
            self.completed.lock().get_or_insert_with(|| why.to_string());
        }
        self.finish(why);
    }

    fn elapsed(&self) -> Duration {
        self.elapsed_before + self.started.elapsed()
    }

    fn finish(&self, why: &str) {
        if self.finished.swap(true, Ordering::AcqRel) {
            return;
        }
        tracing::info!(reason = why, "run finished");
        self.publish(true);
        for limiter in &self.limiters {
            limiter.close();
        }
    }

    fn status(&self) -> LearnerStatus {
        self.forget_silent_actors(Instant::now());
        let c = &self.counters;
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
        // One cut of what ingest inserts and counts together.
        let (tables, transitions, batches) = {
            let _counting = self.counting.write();
            let tables: Vec<(u64, Vec<usize>)> = (0..self.slots.len())
                .map(|level| {
                    let table = self.replay.table(level);
                    (table.inserted_total(), table.shard_lens().collect())
                })
                .collect();
            (tables, load(&c.transitions), load(&c.batches))
        };
        let mut levels: Vec<LevelStatus> = self
            .slots
            .iter()
            .zip(tables)
            .enumerate()
            .map(|(level, (slot, (inserted, shard_lens)))| {
                let slot = slot.lock();
                LevelStatus {
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
                }
            })
            .collect();
        let weights_version = self.publisher.lock().version;
        let now = Instant::now();
        let mut actors: Vec<RegisteredActor> = self
            .actors
            .read()
            .iter()
            .map(|(id, entry)| {
                let mut a = entry.lock();
                let env_steps = a.env_steps;
                let (_, rate) = a.env_steps_rate.rates(now, &[env_steps]);
                RegisteredActor {
                    actor_id: id.clone(),
                    role: a.role,
                    hostname: a.hostname.clone(),
                    incarnation: a.incarnation,
                    registered_for: now.saturating_duration_since(a.registered_at),
                    last_seen_ago: now.saturating_duration_since(a.last_seen),
                    episodes: a.episodes,
                    env_steps,
                    transitions: a.transitions,
                    duplicates: a.duplicates,
                    weights_version: a.weights_version,
                    weights_lag: weights_version.saturating_sub(a.weights_version),
                    transport: a.transport,
                    env_steps_per_s: rate[0],
                    stored_through: a.stored_through,
                    durable_through: match &self.wal {
                        Some(wal) => wal.durable_through(id, a.incarnation),
                        None => a.stored_through,
                    },
                }
            })
            .collect();
        actors.sort_by(|a, b| a.actor_id.cmp(&b.actor_id));
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
            finished: self.finished.load(Ordering::Acquire),
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
            turns: {
                let turns = self.turns.lock();
                TurnStatus {
                    limit: self.options.episodes_in_flight,
                    held: turns.holders.len() as u64,
                    waiting: turns.waiting.values().filter(|w| w.asking).count() as u64,
                    granted: turns.granted,
                    expired: turns.expired,
                }
            },
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

/// A well-mixed 64-bit seed from the run seed, the actor's registration order and incarnation
/// (SplitMix64 finaliser over each input in turn).
fn mix(seed: u64, ordinal: u64, incarnation: u64) -> u64 {
    let mut z = seed;
    for x in [ordinal, incarnation] {
        z = z.wrapping_add(0x9E37_79B9_7F4A_7C15).wrapping_add(x);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
    }
    z
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// A random, non-zero id for this learner process: the clock and the process id, mixed.
fn learner_start_id() -> u64 {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64);
    mix(nanos, u64::from(std::process::id()), 0).max(1)
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
