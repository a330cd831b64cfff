//! Checkpoints of the learner's whole state, and resuming from them.
//!
//! [`Learner::checkpoint`] takes a consistent cut of a running learner: it pauses ingest and
//! evaluation reports (the exclusive side of the learner's `gate`), asks every trainer for a snapshot
//! of its level between two updates (weights, optimiser state, update count, random stream and
//! rate-limiter counts agree), reads counters, curve and weights version, and optionally copies
//! the replay tables; then ingest resumes. [`FinishedRun::checkpoint`] does the same for a learner
//! that has shut down. [`Learner::resume`] starts a learner from a checkpoint.
//!
//! A [`LearnerCheckpoint`] is a set of named files ([`LearnerCheckpoint::to_files`]):
//!
//! - `learner.json`: the run config (TOML text) and its digest, the weights version, counters,
//!   the learning curve, each level's update count, rate-limiter counts and random-stream state;
//! - `level<i>.safetensors`: level `i`'s actor, critic and Adam state (`hac_nn::LevelLearner`);
//! - `replay-level<i>.safetensors`: level `i`'s replay table, when saved with the replay;
//! - `best-level<i>.safetensors`: level `i`'s actor as of the best test round so far
//!   ([`BestWeights`]), once a round has been evaluated; `learner.json` says which round.
//!
//! Writing them to disk atomically, with a manifest, is the caller's business (`hac-run`).
//!
//! Resumed without its replay, a level starts with an empty table: the updates its trainer still
//! owed are forgiven and new episodes earn updates once the table holds a batch again, as at the
//! start of a run.
//!
//! A learner with a write-ahead log ([`crate::wal`]) also records the log's LSN at the cut and
//! every trainer that had stored something (id, incarnation, the sequence stored through, its
//! counts): resuming then stores the log's records from the cut on again, exactly as ingest
//! stored them, and recognises those incarnations when their actors register again, so that
//! their resends of what the log did not hold are stored once. Without a log, transitions
//! acknowledged after the checkpoint are lost with the process that acknowledged them.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use hac_agent::{Agent, RoundReport, RunConfig};
use hac_core::{EnvSpec, Rng};
use hac_nn::{LevelModel, UpdateStats};
use hac_proto::{ActorRole, WeightsSnapshot};
use hac_replay::{RateLimiter, RateLimiterCounts, Replay};
use parking_lot::{Condvar, Mutex};
use serde::{Deserialize, Serialize};

use crate::ingest::Counters;
use crate::registry::{ActorEntry, Registry};
use crate::{BestWeights, FinishedRun, Learner, LearnerOptions, RejectReason, Shared, StartError};

/// Name of the state file in a checkpoint.
pub const STATE_FILE: &str = "learner.json";
const STATE_FORMAT: &str = "hac-learner/state";
const STATE_VERSION: u32 = 1;

fn level_file(level: usize) -> String {
    format!("level{level}.safetensors")
}

fn replay_file(level: usize) -> String {
    format!("replay-level{level}.safetensors")
}

fn best_file(level: usize) -> String {
    format!("best-level{level}.safetensors")
}

/// Why a checkpoint could not be taken, read or resumed from.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// The run finished while the checkpoint waited for the trainers; the final state is
    /// [`FinishedRun::checkpoint`]'s.
    #[error("the run finished before the checkpoint was taken")]
    Finished,
    #[error("{file} is missing")]
    Missing { file: String },
    #[error("{file}: {message}")]
    Invalid { file: String, message: String },
    #[error("the checkpoint was written by a run with another configuration: {differences}")]
    ConfigMismatch { differences: String },
    #[error("the run in the checkpoint is complete ({reason}): there is nothing to resume")]
    Complete { reason: String },
    /// [`LearnerCheckpoint::continue_as`] was given a run with nothing left to train.
    #[error("{0}")]
    NothingToTrain(String),
}

fn invalid(file: impl Into<String>, message: impl ToString) -> CheckpointError {
    CheckpointError::Invalid {
        file: file.into(),
        message: message.to_string(),
    }
}

/// One level's state, taken by its trainer between two updates (or after it stopped).
#[derive(Debug, Clone)]
pub(crate) struct LevelSnapshot {
    learner: LevelModel,
    rng: Rng,
    limiter: RateLimiterCounts,
    covered_episodes: u64,
    last: Option<UpdateStats>,
}

/// `hac_nn::UpdateStats` as stored.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
struct StatsState {
    critic_loss: f32,
    actor_loss: f32,
    mean_q: f32,
    mean_target: f32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct LevelState {
    /// Updates done: equal to the optimiser's step count in `level<i>.safetensors`.
    updates: u64,
    covered_episodes: u64,
    last: Option<StatsState>,
    limiter: RateLimiterCounts,
    /// The level's sampler stream.
    rng: Rng,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct CounterState {
    messages: u64,
    duplicates: u64,
    batches: u64,
    transitions: u64,
    episodes: u64,
    successes: u64,
    env_steps: u64,
    /// Refusals by reason name (every reason, zeros included).
    rejected: BTreeMap<String, u64>,
}

impl CounterState {
    fn of(counters: &Counters) -> Self {
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
        Self {
            messages: load(&counters.messages),
            duplicates: load(&counters.duplicates),
            batches: load(&counters.batches),
            transitions: load(&counters.transitions),
            episodes: load(&counters.episodes),
            successes: load(&counters.successes),
            env_steps: load(&counters.env_steps),
            rejected: RejectReason::ALL
                .iter()
                .zip(&counters.rejected)
                .map(|(r, n)| (r.name().to_string(), load(n)))
                .collect(),
        }
    }

    pub(crate) fn restore(&self) -> Counters {
        let counters = Counters {
            messages: AtomicU64::new(self.messages),
            duplicates: AtomicU64::new(self.duplicates),
            batches: AtomicU64::new(self.batches),
            transitions: AtomicU64::new(self.transitions),
            episodes: AtomicU64::new(self.episodes),
            successes: AtomicU64::new(self.successes),
            env_steps: AtomicU64::new(self.env_steps),
            ..Counters::default()
        };
        for (reason, n) in RejectReason::ALL.iter().zip(&counters.rejected) {
            n.store(
                self.rejected.get(reason.name()).copied().unwrap_or(0),
                Ordering::Relaxed,
            );
        }
        counters
    }
}

/// `learner.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct LearnerState {
    format: String,
    format_version: u32,
    /// The run config as TOML (what actors receive at registration) and its SHA-256.
    run_config: String,
    run_config_digest: String,
    /// The newest weights version published before the checkpoint.
    pub(crate) weights_version: u64,
    pub(crate) published_episodes: u64,
    pub(crate) next_incarnation: u64,
    /// Training time so far, in seconds (the curve's `elapsed_s` continues from it).
    pub(crate) elapsed_s: f64,
    /// Why the run completed, if it did (budget or target reached); absent for a run that was
    /// interrupted or is still going.
    completed: Option<String>,
    pub(crate) counters: CounterState,
    pub(crate) curve: Vec<RoundReport>,
    /// Env steps and total updates at the last curve point (for the next point's speeds).
    pub(crate) curve_env_steps: u64,
    pub(crate) curve_updates: u64,
    /// Whether `replay-level<i>.safetensors` files belong to the checkpoint.
    replay: bool,
    levels: Vec<LevelState>,
    /// The write-ahead log's LSN at the cut: records from it on came after the checkpoint (0:
    /// no log).
    #[serde(default)]
    pub(crate) wal_lsn: u64,
    /// The trainers that had stored something, with what they had stored: a resumed learner
    /// recognises their incarnations when they register again.
    #[serde(default)]
    pub(crate) actors: Vec<ActorState>,
    /// The best test round so far, whose actors are `best-level<i>.safetensors` (absent before
    /// the first round, and in checkpoints written before best weights were kept).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    best: Option<BestState>,
}

/// [`BestWeights`] without its networks, in `learner.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct BestState {
    round: usize,
    episodes: u64,
    env_steps: u64,
    success_rate: f32,
    weights_version: u64,
}

/// A registered trainer as a checkpoint holds it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub(crate) struct ActorState {
    id: String,
    hostname: String,
    ordinal: u64,
    incarnation: u64,
    stored_through: u64,
    episodes: u64,
    env_steps: u64,
    batches: u64,
    transitions: u64,
    weights_version: u64,
}

/// Puts the checkpoint's trainers into the registry of a learner being built.
pub(crate) fn restore_actors(registry: &Registry, state: &LearnerState) {
    let now = Instant::now();
    for a in &state.actors {
        let mut entry = ActorEntry::new(
            ActorRole::Trainer,
            a.hostname.clone(),
            a.ordinal,
            a.incarnation,
            None,
            now,
        );
        entry.stored_through = a.stored_through;
        entry.episodes = a.episodes;
        entry.env_steps = a.env_steps;
        entry.batches = a.batches;
        entry.transitions = a.transitions;
        entry.weights_version = a.weights_version;
        registry.restore(a.id.clone(), entry);
    }
}

/// Checkpoint requests to the trainers, and their answers.
///
/// # Locks
/// `one_at_a_time` is the outermost lock of a checkpoint (before the learner's gate); `taken`
/// is taken alone, by the checkpoint (released while it waits on `served`) and by each trainer
/// answering between two updates with no other lock held.
#[derive(Debug)]
pub(crate) struct Snapshots {
    /// Set by a checkpoint for each level; the level's trainer clears it when it answers.
    pub(crate) requested: Vec<AtomicBool>,
    /// Each trainer's answer, taken by the checkpoint.
    taken: Mutex<Vec<Option<LevelSnapshot>>>,
    served: Condvar,
    /// One checkpoint at a time.
    one_at_a_time: Mutex<()>,
}

impl Snapshots {
    pub(crate) fn new(levels: usize) -> Self {
        Self {
            requested: (0..levels).map(|_| AtomicBool::new(false)).collect(),
            taken: Mutex::new(vec![None; levels]),
            served: Condvar::new(),
            one_at_a_time: Mutex::new(()),
        }
    }
}

impl LearnerState {
    pub(crate) fn covered_episodes(&self, level: usize) -> u64 {
        self.levels[level].covered_episodes
    }

    pub(crate) fn last_stats(&self, level: usize) -> Option<UpdateStats> {
        self.levels[level].last.map(|s| UpdateStats {
            critic_loss: s.critic_loss,
            actor_loss: s.actor_loss,
            mean_q: s.mean_q,
            mean_target: s.mean_target,
        })
    }
}

/// What [`Shared::capture`] reads while ingest is paused.
struct Captured {
    state: LearnerState,
    replay: Option<Vec<Vec<u8>>>,
    /// The best round's actors, as `state.best` describes.
    best: Option<Vec<Vec<u8>>>,
}

/// A consistent snapshot of a learner's whole state; see the module docs. Written to disk as
/// the files of [`to_files`](Self::to_files).
#[derive(Debug, Clone, PartialEq)]
pub struct LearnerCheckpoint {
    state: LearnerState,
    /// `level<i>.safetensors`, level 0 first.
    levels: Vec<Vec<u8>>,
    /// `replay-level<i>.safetensors`, when the replay was saved.
    replay: Option<Vec<Vec<u8>>>,
    /// `best-level<i>.safetensors`, when `state.best` is set.
    best: Option<Vec<Vec<u8>>>,
}

impl LearnerCheckpoint {
    /// The newest weights version published before the checkpoint; a learner resumed from it
    /// publishes versions above it.
    pub fn weights_version(&self) -> u64 {
        self.state.weights_version
    }

    /// Training episodes ingested.
    pub fn episodes(&self) -> u64 {
        self.state.counters.episodes
    }

    /// Transitions stored.
    pub fn transitions(&self) -> u64 {
        self.state.counters.transitions
    }

    /// Updates done by each level, level 0 first.
    pub fn updates(&self) -> Vec<u64> {
        self.state.levels.iter().map(|l| l.updates).collect()
    }

    /// The learning curve up to the checkpoint.
    pub fn curve(&self) -> &[RoundReport] {
        &self.state.curve
    }

    /// Why the run completed, if it did; such a checkpoint cannot be resumed.
    pub fn completed(&self) -> Option<&str> {
        self.state.completed.as_deref()
    }

    /// The weights of the best test round up to the checkpoint, if a round was evaluated.
    pub fn best(&self) -> Option<BestWeights> {
        let (state, levels) = (self.state.best.as_ref()?, self.best.as_ref()?);
        Some(BestWeights {
            round: state.round,
            episodes: state.episodes,
            env_steps: state.env_steps,
            success_rate: state.success_rate,
            snapshot: std::sync::Arc::new(WeightsSnapshot {
                version: state.weights_version,
                levels: levels.clone(),
                episodes: state.episodes,
                run_finished: false,
                learner_start: 0,
            }),
        })
    }

    /// The write-ahead log's LSN at the checkpoint's cut (0: the learner kept no log): the log's
    /// records before it are in the checkpoint.
    pub fn wal_lsn(&self) -> u64 {
        self.state.wal_lsn
    }

    /// Whether the replay tables were saved.
    pub fn has_replay(&self) -> bool {
        self.replay.is_some()
    }

    /// The SHA-256 of the run config, as actors see it at registration.
    pub fn run_config_digest(&self) -> &str {
        &self.state.run_config_digest
    }

    /// The run config the checkpoint was written under.
    pub fn run_config(&self) -> Result<RunConfig, CheckpointError> {
        RunConfig::from_toml(&self.state.run_config, "the checkpoint's run config")
            .map_err(|e| invalid(STATE_FILE, e))
    }

    /// Lets the run in the checkpoint go on under `run`: the checkpoint's config with a larger
    /// episode budget and any `stop_at` that no round of its curve has reached yet, and nothing
    /// else changed (the error names every other key that differs). A run that completed (its
    /// budget trained, or its target reached) can then be resumed; what it learned and every
    /// random stream go on as they stood, so a run continued from a checkpoint of its own end
    /// is the run it would have been with the larger budget from the start.
    pub fn continue_as(&mut self, run: &RunConfig) -> Result<(), CheckpointError> {
        let saved = self.run_config()?;
        let mut same = run.clone();
        (same.episodes, same.stop_at) = (saved.episodes, saved.stop_at);
        if same.to_toml() != saved.to_toml() {
            return Err(CheckpointError::ConfigMismatch {
                differences: differences(&saved, &same),
            });
        }
        let trained = self.episodes();
        if run.episodes <= trained {
            return Err(CheckpointError::NothingToTrain(format!(
                "the run has trained {trained} episodes already; ask for more than that"
            )));
        }
        if let Some(target) = run.stop_at
            && let Some(round) = self.curve().iter().find(|r| r.success_rate >= target)
        {
            return Err(CheckpointError::NothingToTrain(format!(
                "round {} ({} episodes) reached {:.1}% already, which stop_at {target} asks for; \
                 raise it or leave it out",
                round.round,
                round.episodes,
                round.success_rate * 100.0
            )));
        }
        let text = run.to_toml();
        self.state.run_config_digest = crate::config_digest(&text);
        self.state.run_config = text;
        self.state.completed = None;
        Ok(())
    }

    /// The trained agent (every level's networks), checked against the checkpoint's config.
    pub fn agent(&self) -> Result<Agent, CheckpointError> {
        let run = self.run_config()?;
        let env = run.make_env().map_err(|e| invalid(STATE_FILE, e))?;
        let levels = (0..run.levels)
            .map(|level| self.level_learner(&run, env.spec(), level))
            .collect::<Result<_, _>>()?;
        Ok(Agent::from_levels(levels))
    }

    fn level_learner(
        &self,
        run: &RunConfig,
        spec: &EnvSpec,
        level: usize,
    ) -> Result<LevelModel, CheckpointError> {
        let bytes = self.levels.get(level).ok_or(CheckpointError::Missing {
            file: level_file(level),
        })?;
        LevelModel::from_safetensors(&run.agent, run.hiro(), spec, level, bytes)
            .map_err(|e| invalid(level_file(level), e))
    }

    /// The checkpoint's files: `learner.json`, `level<i>.safetensors` and, with the replay,
    /// `replay-level<i>.safetensors`.
    pub fn to_files(&self) -> Vec<(String, Vec<u8>)> {
        let state = serde_json::to_vec_pretty(&self.state).expect("the state is plain data");
        let mut files = vec![(STATE_FILE.to_string(), state)];
        for (level, bytes) in self.levels.iter().enumerate() {
            files.push((level_file(level), bytes.clone()));
        }
        for (level, bytes) in self.replay.iter().flatten().enumerate() {
            files.push((replay_file(level), bytes.clone()));
        }
        for (level, bytes) in self.best.iter().flatten().enumerate() {
            files.push((best_file(level), bytes.clone()));
        }
        files
    }

    /// Reads the files [`to_files`](Self::to_files) wrote (extra files are ignored). The
    /// networks and tables are checked against the run when resuming.
    pub fn from_files(files: &BTreeMap<String, Vec<u8>>) -> Result<Self, CheckpointError> {
        let take = |name: &str| {
            files
                .get(name)
                .cloned()
                .ok_or_else(|| CheckpointError::Missing { file: name.into() })
        };
        let state: LearnerState =
            serde_json::from_slice(&take(STATE_FILE)?).map_err(|e| invalid(STATE_FILE, e))?;
        if state.format != STATE_FORMAT || state.format_version != STATE_VERSION {
            return Err(invalid(
                STATE_FILE,
                format!(
                    "format `{}` version {}, expected `{STATE_FORMAT}` version {STATE_VERSION}",
                    state.format, state.format_version
                ),
            ));
        }
        let count = state.levels.len();
        let levels = (0..count)
            .map(|level| take(&level_file(level)))
            .collect::<Result<_, _>>()?;
        let replay = if state.replay {
            Some(
                (0..count)
                    .map(|level| take(&replay_file(level)))
                    .collect::<Result<_, _>>()?,
            )
        } else {
            None
        };
        let best = match &state.best {
            Some(_) => Some(
                (0..count)
                    .map(|level| take(&best_file(level)))
                    .collect::<Result<_, _>>()?,
            ),
            None => None,
        };
        Ok(Self {
            state,
            levels,
            replay,
            best,
        })
    }

    /// Puts the checkpoint's state into a learner being built for `run`: networks, random
    /// streams, replay and rate limiters; returns the rest for the caller to place.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn restore_into(
        &self,
        run: &RunConfig,
        digest: &str,
        spec: &EnvSpec,
        learners: &mut [LevelModel],
        rngs: &mut [Rng],
        replay: &Replay,
        limiters: &[RateLimiter],
    ) -> Result<&LearnerState, CheckpointError> {
        let state = &self.state;
        if let Some(reason) = &state.completed {
            return Err(CheckpointError::Complete {
                reason: reason.clone(),
            });
        }
        if state.run_config_digest != digest {
            return Err(CheckpointError::ConfigMismatch {
                differences: differences(&self.run_config()?, run),
            });
        }
        if state.levels.len() != learners.len() {
            return Err(invalid(
                STATE_FILE,
                format!(
                    "{} levels, the run has {}",
                    state.levels.len(),
                    learners.len()
                ),
            ));
        }
        for (level, saved) in state.levels.iter().enumerate() {
            let learner = self.level_learner(run, spec, level)?;
            if learner.updates() != saved.updates || saved.limiter.updates != saved.updates {
                return Err(invalid(
                    level_file(level),
                    format!(
                        "the optimiser did {} steps, {STATE_FILE} says {} updates ({} granted)",
                        learner.updates(),
                        saved.updates,
                        saved.limiter.updates
                    ),
                ));
            }
            learners[level] = learner;
            rngs[level] = saved.rng.clone();
            match &self.replay {
                Some(tables) => {
                    replay
                        .table(level)
                        .restore_safetensors(&tables[level])
                        .map_err(|e| invalid(replay_file(level), e))?;
                    limiters[level].restore(saved.limiter, false);
                }
                None => limiters[level].restore(
                    RateLimiterCounts {
                        inserts: 0,
                        ..saved.limiter
                    },
                    true,
                ),
            }
        }
        Ok(state)
    }
}

/// The keys whose values differ between two run configs, as `key: A in the checkpoint, B now`.
fn differences(saved: &RunConfig, now: &RunConfig) -> String {
    fn flatten(prefix: &str, value: &serde_json::Value, out: &mut BTreeMap<String, String>) {
        match value {
            serde_json::Value::Object(map) => {
                for (key, v) in map {
                    let key = if prefix.is_empty() {
                        key.clone()
                    } else {
                        format!("{prefix}.{key}")
                    };
                    flatten(&key, v, out);
                }
            }
            other => {
                out.insert(prefix.to_string(), other.to_string());
            }
        }
    }
    let (mut a, mut b) = (BTreeMap::new(), BTreeMap::new());
    let json = |c: &RunConfig| serde_json::to_value(c).expect("a run config is plain data");
    flatten("", &json(saved), &mut a);
    flatten("", &json(now), &mut b);
    let keys: std::collections::BTreeSet<&String> = a.keys().chain(b.keys()).collect();
    let shown = |v: Option<&String>| v.map_or("absent".to_string(), Clone::clone);
    let diffs: Vec<String> = keys
        .into_iter()
        .filter(|k| a.get(*k) != b.get(*k))
        .map(|k| {
            format!(
                "`{k}` is {} in the checkpoint, {} now",
                shown(a.get(k)),
                shown(b.get(k))
            )
        })
        .collect();
    if diffs.is_empty() {
        "the config digests differ".into()
    } else {
        diffs.join("; ")
    }
}

impl Learner {
    /// Starts a learner that continues the run saved in `checkpoint`: the same networks,
    /// optimiser state, update counts, random streams, counters and learning curve (and replay,
    /// if saved); weights versions continue above the checkpoint's. `run` must be the
    /// checkpoint's run config (its digest is compared; the error names every key that
    /// differs), and a completed run is refused.
    pub fn resume(
        run: RunConfig,
        options: LearnerOptions,
        checkpoint: &LearnerCheckpoint,
    ) -> Result<Self, StartError> {
        Self::launch(run, options, Some(checkpoint))
    }

    /// A consistent snapshot of the running learner (see the module docs), with the replay
    /// tables if `with_replay`. Ingest and evaluation reports wait meanwhile (each trainer
    /// answers within one update or 50 ms); registration and weights watchers do not.
    pub fn checkpoint(&self, with_replay: bool) -> Result<LearnerCheckpoint, CheckpointError> {
        let shared = &self.shared;
        let _one_at_a_time = shared.snapshots.one_at_a_time.lock();
        let (levels, captured) = {
            let _ingest_paused = shared.gate.write();
            let levels = shared.collect_snapshots()?;
            let captured = shared.capture(&levels, with_replay);
            (levels, captured)
        };
        Ok(LearnerCheckpoint::of(captured, &levels))
    }
}

impl FinishedRun {
    /// Deletes the write-ahead log's segments before `before_lsn` ([`Learner::truncate_wal`]).
    pub fn truncate_wal(&self, before_lsn: u64) -> Result<u64, crate::WalError> {
        self.shared.truncate_wal(before_lsn)
    }

    /// The final state of a learner that has shut down, as a checkpoint (with the replay tables
    /// if `with_replay`). A run that was interrupted rather than completed can be resumed from
    /// it.
    pub fn checkpoint(&self, with_replay: bool) -> LearnerCheckpoint {
        let shared = &self.shared;
        let levels: Vec<LevelSnapshot> = self
            .agent
            .levels()
            .iter()
            .zip(&self.rngs)
            .enumerate()
            .map(|(level, (learner, rng))| {
                let (covered_episodes, last) = shared
                    .publisher
                    .slot(level, |slot| (slot.covered_episodes, slot.last));
                LevelSnapshot {
                    learner: learner.clone(),
                    rng: rng.clone(),
                    limiter: shared.limiters[level].counts(),
                    covered_episodes,
                    last,
                }
            })
            .collect();
        LearnerCheckpoint::of(shared.capture(&levels, with_replay), &levels)
    }
}

impl Shared {
    /// The trainer of `level`, between two updates: answers a checkpoint request.
    pub(crate) fn serve_snapshot(&self, level: usize, learner: &LevelModel, rng: &Rng) {
        let (covered_episodes, last) = self
            .publisher
            .slot(level, |slot| (slot.covered_episodes, slot.last));
        let snapshot = LevelSnapshot {
            learner: learner.clone(),
            rng: rng.clone(),
            // The trainer is between updates: every update granted is done and in `learner`.
            limiter: self.limiters[level].counts(),
            covered_episodes,
            last,
        };
        let mut taken = self.snapshots.taken.lock();
        taken[level] = Some(snapshot);
        self.snapshots.requested[level].store(false, Ordering::Release);
        self.snapshots.served.notify_all();
    }

    /// Asks every trainer for its level's snapshot and waits for all of them (ingest must be
    /// paused by the caller, so that the limiter counts agree across levels).
    fn collect_snapshots(&self) -> Result<Vec<LevelSnapshot>, CheckpointError> {
        let snapshots = &self.snapshots;
        let mut taken = snapshots.taken.lock();
        taken.iter_mut().for_each(|t| *t = None);
        for requested in &snapshots.requested {
            requested.store(true, Ordering::Release);
        }
        loop {
            if taken.iter().all(Option::is_some) {
                return Ok(taken.iter_mut().filter_map(Option::take).collect());
            }
            if self.is_finished() {
                // Trainers stop once the run is finished; they may never answer.
                for requested in &snapshots.requested {
                    requested.store(false, Ordering::Release);
                }
                return Err(CheckpointError::Finished);
            }
            snapshots
                .served
                .wait_for(&mut taken, Duration::from_millis(50));
        }
    }

    /// The state of `levels` with this learner's counters, curve and version, and the replay
    /// tables if `with_replay`: what must be read while ingest is paused.
    fn capture(&self, levels: &[LevelSnapshot], with_replay: bool) -> Captured {
        let (curve, curve_env_steps, curve_updates) = self.curve.capture();
        let (weights_version, published_episodes) = self.publisher.version_and_episodes();
        let replay = with_replay.then(|| {
            (0..levels.len())
                .map(|level| self.replay.table(level).to_safetensors())
                .collect()
        });
        let best = self.curve.best().latest();
        let wal_lsn = self.wal.as_ref().map_or(0, crate::Wal::cut);
        let mut actors: Vec<ActorState> = Vec::new();
        self.registry.each(|id, a| {
            if a.role == ActorRole::Trainer && a.stored_through > 0 {
                actors.push(ActorState {
                    id: id.to_string(),
                    hostname: a.hostname.clone(),
                    ordinal: a.ordinal,
                    incarnation: a.incarnation,
                    stored_through: a.stored_through,
                    episodes: a.episodes,
                    env_steps: a.env_steps,
                    batches: a.batches,
                    transitions: a.transitions,
                    weights_version: a.weights_version,
                });
            }
        });
        actors.sort_by(|a, b| a.id.cmp(&b.id));
        let state = LearnerState {
            format: STATE_FORMAT.into(),
            format_version: STATE_VERSION,
            run_config: self.run_toml.clone(),
            run_config_digest: self.digest.clone(),
            weights_version,
            published_episodes,
            next_incarnation: self.registry.next_incarnation(),
            elapsed_s: self.elapsed().as_secs_f64(),
            completed: self.completed.lock().clone(),
            counters: CounterState::of(&self.counters),
            curve,
            curve_env_steps,
            curve_updates,
            replay: with_replay,
            wal_lsn,
            actors,
            levels: levels
                .iter()
                .map(|l| LevelState {
                    updates: l.learner.updates(),
                    covered_episodes: l.covered_episodes,
                    last: l.last.map(|s| StatsState {
                        critic_loss: s.critic_loss,
                        actor_loss: s.actor_loss,
                        mean_q: s.mean_q,
                        mean_target: s.mean_target,
                    }),
                    limiter: l.limiter,
                    rng: l.rng.clone(),
                })
                .collect(),
            best: best.as_ref().map(|b| BestState {
                round: b.round,
                episodes: b.episodes,
                env_steps: b.env_steps,
                success_rate: b.success_rate,
                weights_version: b.snapshot.version,
            }),
        };
        Captured {
            state,
            replay,
            best: best.map(|b| b.snapshot.levels.clone()),
        }
    }
}

impl LearnerCheckpoint {
    /// Serialises the levels' networks (no need to pause ingest for that).
    fn of(captured: Captured, levels: &[LevelSnapshot]) -> Self {
        Self {
            state: captured.state,
            levels: levels.iter().map(|l| l.learner.to_safetensors()).collect(),
            replay: captured.replay,
            best: captured.best,
        }
    }
}
