//! The learner daemon's checkpoints: when they are taken, where they go, and resuming from them.
//!
//! Checkpoints go to `<out>/checkpoints/ckpt-<seq>/` ([`hac_run::checkpoints`]: atomic, with a
//! manifest, the newest `--keep-checkpoints` kept), holding what [`LearnerCheckpoint`] saves. They
//! are taken every `--checkpoint-every` seconds, on SIGUSR1 (`kill -USR1 <pid>`), and at graceful
//! shutdown once the server has drained. Taking one pauses ingest for about one update (up to
//! 50 ms when a trainer is idle) plus the time to copy the replay with `--checkpoint-replay`;
//! writing happens on a blocking thread while serving goes on.
//!
//! `--resume` continues the run in `--out` from its newest checkpoint that verifies; each newer
//! one that does not (truncated, corrupt, unfinished) is logged and skipped. The config given
//! must be the checkpoint's (the error names every key that differs). A directory with no run
//! starts one, so a deployment can always pass `--resume`.

use std::collections::VecDeque;
use std::path::Path;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use hac_learner::{FinishedRun, Learner, LearnerCheckpoint, WalOptions};
use hac_run::checkpoints::{CheckpointStore, Written};
use tokio::signal::unix::{Signal, SignalKind, signal};
use tokio::task::JoinHandle;
use tokio::time::{Interval, MissedTickBehavior};

use crate::seconds;

/// When and how the learner checkpoints (also `[learner]` config keys).
#[derive(Debug, Clone, clap::Args)]
pub struct CheckpointArgs {
    /// Seconds between checkpoints; 0 takes them only on SIGUSR1 and at shutdown.
    #[arg(long, value_name = "SECS", default_value = "300", value_parser = seconds)]
    pub checkpoint_every: Duration,
    /// How many of the newest checkpoints to keep in <out>/checkpoints.
    #[arg(long, value_name = "K", default_value_t = 3,
          value_parser = clap::value_parser!(u64).range(1..=1000))]
    pub keep_checkpoints: u64,
    /// Save the replay tables in checkpoints too (large); without them a resumed learner starts
    /// with empty replay, which actors fill again.
    #[arg(long)]
    pub checkpoint_replay: bool,
    /// Continue the run in --out from its newest valid checkpoint (corrupt ones are skipped)
    /// and the write-ahead log after it; a directory without a run starts a new one.
    #[arg(long, conflicts_with = "overwrite")]
    pub resume: bool,
    /// Seconds between commits of the write-ahead log (<out>/wal: every stored message, fsynced
    /// in groups), which makes acknowledged messages durable between checkpoints: actors keep
    /// what is not durable yet and resend it to a resumed learner. 0 turns the log off (a message
    /// is then durable once stored, which lasts only as long as the process).
    #[arg(long, value_name = "SECS", default_value = "0.1", value_parser = seconds)]
    pub durable_interval: Duration,
}

impl CheckpointArgs {
    /// The write-ahead log of a run in `out`, unless `--durable-interval 0`.
    pub fn wal(&self, out: &Path) -> Option<WalOptions> {
        (!self.durable_interval.is_zero())
            .then(|| WalOptions::new(out.join(WAL_DIR), self.durable_interval))
    }
}

/// The write-ahead log's directory in the run directory.
pub const WAL_DIR: &str = "wal";

/// How the daemon starts its run.
#[derive(Debug)]
pub(crate) enum Start {
    /// A new run; `replace` says whether an unfinished run without checkpoints is replaced.
    New { replace: bool },
    /// From the checkpoint named `name`.
    Resume {
        checkpoint: Box<LearnerCheckpoint>,
        name: String,
    },
    /// The newest checkpoint holds a completed run: nothing to do.
    Complete { reason: String },
}

/// Picks how to start: a new run unless `--resume` finds a checkpoint in `out`.
pub(crate) fn start(args: &CheckpointArgs, out: &Path) -> Result<Start> {
    if !args.resume {
        return Ok(Start::New { replace: false });
    }
    let store = CheckpointStore::of_run(out);
    match store.load_newest(LearnerCheckpoint::from_files)? {
        Some(loaded) => {
            for line in loaded.skipped_lines() {
                tracing::warn!("{line}");
            }
            if let Some(reason) = loaded.value.completed() {
                return Ok(Start::Complete {
                    reason: reason.to_string(),
                });
            }
            Ok(Start::Resume {
                checkpoint: Box::new(loaded.value),
                name: loaded.name,
            })
        }
        None if out.join("summary.json").exists() => bail!(
            "{} holds a finished run without checkpoints: there is nothing to resume",
            out.display()
        ),
        None => {
            let replace = out.join("config.toml").exists();
            if replace {
                tracing::warn!(
                    out = %out.display(),
                    "no checkpoint to resume from: starting the run from the beginning"
                );
            }
            Ok(Start::New { replace })
        }
    }
}

/// Checkpoints while serving: on the timer and on SIGUSR1, one at a time.
#[derive(Debug)]
pub(crate) struct Checkpoints {
    store: CheckpointStore,
    keep: usize,
    with_replay: bool,
    timer: Option<Interval>,
    on_demand: Signal,
    running: Option<JoinHandle<Result<String>>>,
    /// The log cuts of the checkpoints this process wrote, oldest first, at most `keep`: the
    /// log is kept from the oldest on, so that a resume that falls back from a damaged newest
    /// checkpoint to an older kept one still finds the log after that one's cut.
    cuts: Arc<Mutex<VecDeque<u64>>>,
}

impl Checkpoints {
    /// Installs the SIGUSR1 handler (before the port is bound, so the signal never kills a
    /// serving learner) and the timer.
    /// `resumed_cut` is the log cut of the checkpoint a resumed learner started from.
    pub(crate) fn install(
        args: &CheckpointArgs,
        out: &Path,
        resumed_cut: Option<u64>,
    ) -> Result<Self> {
        let timer = (!args.checkpoint_every.is_zero()).then(|| {
            let every = args.checkpoint_every;
            let mut timer = tokio::time::interval_at(tokio::time::Instant::now() + every, every);
            timer.set_missed_tick_behavior(MissedTickBehavior::Delay);
            timer
        });
        Ok(Self {
            store: CheckpointStore::of_run(out),
            keep: usize::try_from(args.keep_checkpoints).unwrap_or(usize::MAX),
            with_replay: args.checkpoint_replay,
            timer,
            on_demand: signal(SignalKind::user_defined1())
                .context("installing the SIGUSR1 handler")?,
            running: None,
            cuts: Arc::new(Mutex::new(resumed_cut.into_iter().collect())),
        })
    }

    /// Waits until a checkpoint is due and starts it, or until the running one is written (and
    /// logs it). Cancel-safe: use it as a `select!` branch in a loop.
    pub(crate) async fn step(&mut self, learner: &Arc<Learner>) {
        if let Some(running) = &mut self.running {
            let result = running.await;
            self.running = None;
            log(result);
            return;
        }
        let timer = async {
            match &mut self.timer {
                Some(timer) => timer.tick().await,
                None => std::future::pending().await,
            }
        };
        let why = tokio::select! {
            _ = timer => "timer",
            _ = self.on_demand.recv() => "SIGUSR1",
        };
        tracing::debug!(why, "checkpoint due");
        let (learner, store) = (learner.clone(), self.store.clone());
        let (keep, with_replay) = (self.keep, self.with_replay);
        let cuts = self.cuts.clone();
        self.running = Some(tokio::task::spawn_blocking(move || {
            let started = Instant::now();
            let checkpoint = learner.checkpoint(with_replay)?;
            let name = write(&store, &checkpoint, keep, Some(started.elapsed()))?;
            // The checkpoint is on disk: the log before the oldest kept one's cut is not needed
            // any more.
            truncated(learner.truncate_wal(oldest_kept(&cuts, &checkpoint, keep)));
            Ok(name)
        }));
    }

    /// Waits for a checkpoint still being written (before the final one).
    pub(crate) async fn settle(&mut self) {
        if let Some(running) = self.running.take() {
            log(running.await);
        }
    }

    /// Writes the final checkpoint of a learner that has shut down, then drops the log before
    /// its cut.
    pub(crate) fn write_final(&self, finished: &FinishedRun) -> Result<String> {
        let checkpoint = finished.checkpoint(self.with_replay);
        let name = write(&self.store, &checkpoint, self.keep, None)?;
        truncated(finished.truncate_wal(oldest_kept(&self.cuts, &checkpoint, self.keep)));
        Ok(name)
    }
}

/// Notes `checkpoint`'s log cut among the last `keep` and returns the oldest of them.
fn oldest_kept(cuts: &Mutex<VecDeque<u64>>, checkpoint: &LearnerCheckpoint, keep: usize) -> u64 {
    let mut cuts = cuts.lock().unwrap_or_else(PoisonError::into_inner);
    cuts.push_back(checkpoint.wal_lsn());
    while cuts.len() > keep.max(1) {
        cuts.pop_front();
    }
    cuts.front().copied().unwrap_or(0)
}

/// Writes `checkpoint` to `store`; returns its name. `snapshot` is how long taking it took
/// (ingest pauses for most of that).
fn write(
    store: &CheckpointStore,
    checkpoint: &LearnerCheckpoint,
    keep: usize,
    snapshot: Option<Duration>,
) -> Result<String> {
    let started = Instant::now();
    let Written { name, bytes, .. } = store
        .write(&checkpoint.to_files(), keep)
        .context("writing a checkpoint")?;
    tracing::info!(
        checkpoint = %name,
        weights_version = checkpoint.weights_version(),
        episodes = checkpoint.episodes(),
        updates = ?checkpoint.updates(),
        replay = checkpoint.has_replay(),
        bytes,
        snapshot_ms = snapshot.map(|d| d.as_secs_f64() * 1e3),
        write_ms = started.elapsed().as_secs_f64() * 1e3,
        "checkpoint written"
    );
    Ok(name)
}

/// Logs what truncating the write-ahead log after a checkpoint did (a failure leaves segments
/// that the next checkpoint deletes; nothing is lost).
fn truncated(result: Result<u64, hac_learner::WalError>) {
    match result {
        Ok(0) => {}
        Ok(bytes) => tracing::debug!(bytes, "write-ahead log truncated at the checkpoint"),
        Err(e) => tracing::warn!(error = %e, "truncating the write-ahead log failed"),
    }
}

fn log(result: Result<Result<String>, tokio::task::JoinError>) {
    match result {
        Ok(Ok(_)) => {}
        // The run finished while the trainers were asked: the final checkpoint follows.
        Ok(Err(e))
            if e.downcast_ref::<hac_learner::CheckpointError>()
                .is_some_and(|e| matches!(e, hac_learner::CheckpointError::Finished)) => {}
        // Serving goes on: the next checkpoint may succeed (space freed, disk back).
        Ok(Err(e)) => tracing::error!(error = format!("{e:#}"), "checkpoint failed"),
        Err(e) => tracing::error!(error = %e, "checkpoint task failed"),
    }
}
