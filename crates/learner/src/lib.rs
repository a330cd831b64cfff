//! The HAC learner, independent of any transport: the run's single source of truth.
//!
//! - [`Learner::register`] admits an actor (a fresh incarnation, the run's config, a seed).
//! - [`Learner::ingest`] validates each message (known actor, current incarnation, sequence,
//!   dimensions, finite values, level range), stores every `(actor, incarnation, sequence)`
//!   exactly once (resends of stored messages count as duplicates and are acknowledged), and
//!   routes batches round the replay shards of the batch's level in the order they are stored.
//! - One trainer thread per level takes updates from its [`RateLimiter`] (updates per ingested
//!   episode, the paper's 40 by default), so training neither runs ahead of the data nor falls
//!   behind it; [`Learner::wait_for_room`] is the backpressure ingest applies to actors. The
//!   levels share `learner_threads` ([`level_threads`]): a level with more than one thread cuts
//!   each minibatch's gradient among them (weights bit-identical to one thread's).
//! - Weights are published as whole-model, versioned [`WeightsSnapshot`]s through a
//!   [`Published`] cell: whenever every level has caught up with the episodes ingested (so an
//!   actor that waits for it gets exactly the paper's schedule), when every level has done
//!   `publish_every_updates` more updates, and otherwise at the latest `max_publish_delay` after
//!   fresh weights appeared (the rule, in one place, is the `publisher` module's).
//! - Episode turns ([`Learner::await_turn`], with `episodes_in_flight` > 0): trainers ask before
//!   each episode and the learner lets at most that many training episodes be played or wait to
//!   be trained on at once, over all actors, granting turns in the order asked, each for an
//!   episode index from which the trainer draws that episode's random streams. Many actors then
//!   act on weights as fresh as one lockstep actor does, instead of on weights that miss every
//!   episode the others have in flight; with one episode in flight the run is the same whichever
//!   trainers play it.
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
//!
//! # Parts, and their locks
//! [`Learner`] is a handle on one shared state made of parts, each in its own module with its
//! own state and lock, and each method documenting the locks it takes:
//!
//! | module | owns | lock |
//! | --- | --- | --- |
//! | `registry` | the actors, by id | a map (`RwLock`), then one entry (`Mutex`) per actor |
//! | `ingest` | storing messages and evaluation reports; the counters | atomics; the `gate` and `counting` locks |
//! | `turns` | who holds and who waits for episode turns | one `Mutex` and its `Condvar` |
//! | `publisher` | each level's offered weights and coverage, the snapshots; **the publishing rule** | the state (`Mutex`), then one slot (`Mutex`) per level |
//! | `trainers` | the trainer threads, health | none held while updating |
//! | `curve` | the learning curve and the best round's weights | one `Mutex` |
//! | `status` | the operator's snapshot, assembled from the others; the rates window | the rates window's `Mutex` |
//! | `checkpoint` | consistent cuts and resuming | one checkpoint at a time; trainers' answers |
//! | `wal` | the write-ahead log | its own (see the module) |
//!
//! The rate limiters (`hac-replay`) and the replay shards lock themselves inside their calls,
//! and nothing is taken under them.
//!
//! **Lock order.** A thread that holds two of these locks took them in this order:
//! 1. the `gate` (`RwLock`): ingest and evaluation reports hold it shared; a checkpoint holds it
//!    exclusively, which pauses them, so that counters, replay and curve form one cut;
//! 2. a registry entry (an actor's, while its message is checked and stored);
//! 3. the write-ahead log's, and `counting` (`RwLock`, shared by ingest while it inserts a
//!    batch and counts it, exclusive in status while it reads the totals);
//! 4. the publisher's state, then a level's slot;
//! 5. the curve; the turns; the rates window;
//! 6. a replay shard's or a rate limiter's own lock (innermost).
//!
//! Where a step releases one lock before taking the next (an entry before the turns and the
//! publisher when an episode summary arrives; the publisher's state before the turns are
//! woken), the module says so. No lock is held across a wait except the turns' own condition
//! variable and the checkpoint's (which release theirs while waiting).

mod best;
mod checkpoint;
mod curve;
mod error;
mod hiro;
mod ingest;
mod options;
mod publisher;
mod registry;
mod status;
mod trainers;
mod turns;
pub mod wal;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use hac_agent::{Agent, RoundReport, RunConfig};
use hac_core::{Batch, EnvSpec, LevelDims, Rng, TransitionLimits};
use hac_nn::LevelModel;
use hac_proto::{
    ActorRole, Admission, Evaluation, IngestMessage, IngestRef, PreviousIncarnation, Registration,
    WeightsSnapshot,
};
use hac_replay::{RateLimiter, RateLimiterConfig, Replay, WaitError};
use parking_lot::{Mutex, RwLock};
use sha2::{Digest, Sha256};

pub use best::RECENT_SNAPSHOTS;
use checkpoint::Snapshots;
pub use checkpoint::{CheckpointError, LearnerCheckpoint};
use curve::Curve;
pub use error::{IngestError, RegisterError, RoomError, StartError, Stored};
pub use hac_core::rates::{RATES_WINDOW, RateWindow, TokenBucket};
pub use hac_proto::{BestWeights, Published, RejectReason};
use ingest::Counters;
pub use options::{
    FORGET_ACTORS_AFTER, InvalidOption, LearnerOptions, MAX_LEARNER_THREADS, available_threads,
    level_threads,
};
pub use publisher::MAX_DIVERGED_IN_A_ROW;
use publisher::{LevelSlot, Publisher};
use registry::{Admitted, Registry};
pub use status::{LearnerStatus, LevelStatus, Rates, RegisteredActor};
use turns::{Grant, RunFinished, Turns};
pub use turns::{MAX_TURN_WAIT, TURN_LEASE, Turn, TurnStatus};
pub use wal::{Wal, WalError, WalOptions, WalStatus};

/// The learner's state, shared by its handle, the trainer threads and the transports' calls: the
/// run's fixed facts, then the parts (see the crate docs for who owns what, and the lock order).
#[derive(Debug)]
struct Shared {
    run: RunConfig,
    run_toml: String,
    digest: String,
    dims: Vec<LevelDims>,
    options: LearnerOptions,
    /// What each level's transitions can hold (admission by meaning).
    limits: Vec<TransitionLimits>,
    /// The episode budget: no episode summary reports more env steps.
    max_episode_actions: u64,
    replay: Replay,
    limiters: Vec<RateLimiter>,
    registry: Registry,
    turns: Turns,
    publisher: Publisher,
    /// Why the learner is unhealthy (a level failing, see [`MAX_DIVERGED_IN_A_ROW`]), or
    /// `None`; republished by the trainers whenever that changes.
    trouble: Published<Option<String>>,
    curve: Curve,
    counters: Counters,
    /// `[transitions, batches, episodes, env_steps, updates of level 0, 1, ...]` over time, for
    /// status's rates.
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
    /// status's per-level totals add up to its total. Only replay shards' locks are taken
    /// under it.
    counting: RwLock<()>,
    /// Checkpoint requests to the trainers, and their answers.
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
                Some(hiro) => {
                    TransitionLimits::for_hiro_level(&spec, level, hiro.c, hiro.task_reward)
                }
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
        let digest = config_digest(&run_toml);
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
                LevelSlot::new(
                    l,
                    resumed.map_or(0, |r| r.covered_episodes(level)),
                    resumed.and_then(|r| r.last_stats(level)),
                )
            })
            .collect();
        let levels = config.levels;
        let batch_size = config.batch_size;
        let (points, curve_env_steps, curve_updates) = resumed.map_or((Vec::new(), 0, 0), |r| {
            (r.curve.clone(), r.curve_env_steps, r.curve_updates)
        });
        let mut shared = Shared {
            digest,
            dims,
            replay,
            limits,
            max_episode_actions: spec.max_actions as u64,
            limiters,
            registry: Registry::new(
                resumed.map_or(1, |r| r.next_incarnation),
                options.forget_actors_after,
                options.max_actor_messages_per_second,
            ),
            turns: Turns::new(options.episodes_in_flight, options.turn_lease),
            publisher: Publisher::new(
                slots,
                // Resumed: the next snapshot's version is above every version of the checkpoint.
                resumed.map_or(0, |r| r.weights_version),
                resumed.map_or(0, |r| r.published_episodes),
                learner_start_id(),
                options.publish_every_updates,
                options.max_publish_delay,
            ),
            trouble: Published::default(),
            curve: Curve::new(points, curve_env_steps, curve_updates),
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
            snapshots: Snapshots::new(levels),
            wal: None,
            run,
            run_toml,
            options,
        };
        // Only with a log: without one, actors hold only what was never acknowledged, and a
        // registry from the checkpoint would expect them to resend what they dropped since.
        if let (Some(r), Some(_)) = (resumed, &shared.options.wal) {
            checkpoint::restore_actors(&shared.registry, r);
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
            shared.registry.each(|id, entry| {
                wal.set_durable(id, entry.incarnation, entry.stored_through);
            });
            if recovered.records > 0 || recovered.cut_reason.is_some() {
                tracing::info!(
                    records = recovered.records,
                    cut_bytes = recovered.cut_bytes,
                    transitions = shared.counters.transitions.load(Ordering::Relaxed),
                    episodes = shared.counters.episodes.load(Ordering::Relaxed),
                    actors = shared.registry.len(),
                    "write-ahead log replayed"
                );
            }
            shared.wal = Some(wal);
        }
        let shared = Arc::new(shared);
        shared.publish(false);
        shared.trouble.publish(Arc::new(None));
        if let Some(best) = from.and_then(LearnerCheckpoint::best) {
            shared.curve.best().publish(Arc::new(best));
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
        self.shared.curve.best()
    }

    /// The weights cell: the latest snapshot, waitable from threads and tasks.
    pub fn weights(&self) -> &Published<WeightsSnapshot> {
        self.shared.publisher.weights()
    }

    pub fn is_finished(&self) -> bool {
        self.shared.is_finished()
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
        shared.registry.forget_silent(now);
        let (incarnation, ordinal) = match shared.registry.admit(&registration, previous, now) {
            Admitted::Kept {
                incarnation,
                ordinal,
            } => {
                tracing::info!(
                    actor = %registration.actor_id,
                    role = ?registration.role,
                    incarnation,
                    resend_from = previous.map(|p| p.resend_from),
                    "actor registered again under its incarnation"
                );
                return Ok(shared.admission(incarnation, ordinal));
            }
            Admitted::New {
                incarnation,
                ordinal,
            } => (incarnation, ordinal),
        };
        shared.turns.forget(&registration.actor_id);
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
            None => self.shared.registry.get(actor_id).map_or(0, |entry| {
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
        let Some(entry) = self.shared.registry.get(actor_id) else {
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
        if let Some(entry) = self.shared.registry.get(actor_id) {
            entry.lock().transport = transport;
        }
    }

    /// Checks that `incarnation` is `actor_id`'s current one (unknown actor, stale incarnation;
    /// counted), for a transport serving a per-actor request that reaches the learner no other
    /// way (the weights watch).
    pub fn check_incarnation(&self, actor_id: &str, incarnation: u64) -> Result<(), IngestError> {
        let checked = self
            .shared
            .registry
            .entry(actor_id)
            .and_then(|entry| entry.lock().check_incarnation(actor_id, incarnation));
        self.counted(checked)
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
        self.shared.counters.reject(reason);
    }

    /// Adds an evaluator's (or a self-evaluating trainer's) greedy test results to the learning
    /// curve, at the episode count of the weights version they used; may finish the run.
    pub fn report_evaluation(&self, evaluation: &Evaluation) -> Result<(), IngestError> {
        let _running = self.shared.gate.read();
        self.counted(self.shared.report_evaluation(evaluation))
    }

    /// The learning curve so far, one point per evaluation report.
    pub fn curve(&self) -> Vec<RoundReport> {
        self.shared.curve.points()
    }

    /// The last `max` points of the learning curve (all of them for 0), and how many there are.
    pub fn recent_curve(&self, max: usize) -> (usize, Vec<RoundReport>) {
        self.shared.curve.recent(max)
    }

    /// Publishes the current weights again as a new version and returns it (weights fan-out
    /// benchmarks; a nudge for actors waiting on a version). Nothing after the run finished.
    pub fn republish(&self) -> u64 {
        if self.is_finished() {
            return self.shared.publisher.version();
        }
        self.shared.publish(false)
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
            best: self.shared.curve.best().latest(),
            status: self.status(),
            rngs,
            shared: self.shared.clone(),
        }
    }
}

impl Shared {
    fn is_finished(&self) -> bool {
        self.finished.load(Ordering::Acquire)
    }

    /// What an actor admitted under `incarnation` is told. No lock.
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

    /// [`Learner::await_turn`]. Locks: `actor_id`'s entry (released), then the turns'.
    fn await_turn(
        &self,
        actor_id: &str,
        incarnation: u64,
        wait: Duration,
    ) -> Result<Turn, IngestError> {
        {
            let entry = self.registry.entry(actor_id)?;
            let actor = entry.lock();
            actor.check_incarnation(actor_id, incarnation)?;
            if actor.role == ActorRole::Evaluator {
                return Err(IngestError::WrongRole(actor_id.to_string()));
            }
        }
        let received = || self.counters.episodes.load(Ordering::Acquire);
        let untrained = || received().saturating_sub(self.publisher.published_episodes());
        let grant = self
            .turns
            .wait(actor_id, incarnation, wait, received, untrained, || {
                self.is_finished()
            })
            .map_err(|RunFinished| IngestError::Finished)?;
        let (granted, episode) = match grant {
            Grant::Free => (true, None),
            Grant::Episode(episode) => (true, Some(episode)),
            Grant::NotYet => (false, None),
        };
        Ok(Turn {
            granted,
            episodes: self.publisher.published_episodes(),
            episode,
        })
    }

    /// Publishes a snapshot if the publisher says it is due (see `publisher`), wakes the
    /// trainers waiting for turns if it did, then checks whether the budget is done. Locks: the
    /// publisher's (released), the turns', the registry's.
    fn maybe_publish(&self) {
        if self.is_finished() {
            return;
        }
        let Some(covered) = self.publisher.maybe_publish() else {
            return;
        };
        self.turns.wake();
        if covered >= self.run.episodes && !self.registry.has_evaluator() {
            self.complete("episode budget trained");
        }
    }

    /// Publishes a snapshot of every level's latest weights as the next version, and wakes the
    /// trainers waiting for turns; the version. Locks: the publisher's (released), the turns'.
    fn publish(&self, run_finished: bool) -> u64 {
        let version = self.publisher.publish(run_finished);
        self.turns.wake();
        version
    }

    /// Finishes a run that reached its end (not an interruption): it cannot be resumed.
    fn complete(&self, why: &str) {
        if !self.is_finished() {
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

/// The digest of a run config's TOML, as actors and checkpoints carry it.
fn config_digest(run_toml: &str) -> String {
    hex(&Sha256::digest(run_toml.as_bytes()))
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
