//! An embedded run trained into its run directory, from the start or from a saved state, as
//! `hac train` and each run of `hac experiment` train; and the run's whole saved state, as
//! `--keep-state` writes it and `--resume` reads it: the learner's checkpoint with its replay,
//! and the trainer's state beside it (docs/CHECKPOINTS.md, "Training on").

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use anyhow::{Context, Result};
use hac_agent::{RoundReport, RunConfig};
use hac_learner::{LearnerCheckpoint, LearnerOptions};
use hac_run::checkpoints::{CheckpointStore, Loaded, Written};
use hac_run::outln;
use hac_run::run_dir::{self, RunDir, Summary};
use hac_serve::{SavedRun, train_embedded_from};

use crate::schedule;

/// One embedded training run into a run directory.
pub struct Embedded<'a> {
    pub run: &'a RunConfig,
    pub options: LearnerOptions,
    /// The saved state it goes on from (its directory then holds the earlier processes' rounds
    /// and summary, whose wall time the new summary adds to).
    pub from: Option<&'a SavedRun>,
    /// Save the whole state when it stops.
    pub keep_state: bool,
    pub interrupt: &'a AtomicBool,
    /// Print a progress line per round, and what was saved (`hac train`).
    pub progress: bool,
}

impl Embedded<'_> {
    /// Trains into `dir` (the run directory `out`): the curve round by round, then the best
    /// weights, the saved state if asked for, the weights and `summary.json`.
    pub fn train(self, dir: &mut RunDir, out: &Path) -> Result<(Vec<RoundReport>, Summary)> {
        let wall_time_before = match self.from {
            Some(_) => run_dir::load_summary(out).map_or(0.0, |s| s.wall_time_s),
            None => 0.0,
        };
        let started = Instant::now();
        let mut write_error = None;
        let trained = train_embedded_from(
            self.run,
            self.options,
            self.from,
            self.keep_state,
            self.interrupt,
            |report: &RoundReport| {
                if self.progress {
                    outln!("{}", schedule::progress_line(report));
                }
                if let Err(e) = dir.record(report) {
                    write_error.get_or_insert(e);
                }
            },
        )?;
        if let Some(e) = write_error {
            return Err(e);
        }
        if self.progress && self.interrupt.load(Ordering::Relaxed) {
            outln!(
                "interrupted after {} episodes: saving what was learned (a second signal exits at once)",
                trained.actor.episodes
            );
        }
        if let Some(best) = &trained.best {
            dir.save_best(best)?;
        }
        if let Some(saved) = &trained.saved {
            let written = save(out, saved)?;
            if self.progress {
                outln!(
                    "state saved in {} ({:.1} MB): `hac train --resume --out {} --episodes N` continues it",
                    written.path.display(),
                    written.bytes as f64 / 1e6,
                    out.display()
                );
            }
        }
        let summary = dir.finish(
            &trained.agent,
            &trained.curve,
            wall_time_before + started.elapsed().as_secs_f64(),
        )?;
        Ok((trained.curve, summary))
    }
}

/// The trainer's state, beside the learner's checkpoint files.
const TRAINER_STATE_FILE: &str = "trainer.json";

/// Saves `saved` as the run directory `run`'s one checkpoint.
pub fn save(run: &Path, saved: &SavedRun) -> Result<Written> {
    let mut files = saved.checkpoint.to_files();
    files.push((
        TRAINER_STATE_FILE.to_string(),
        serde_json::to_vec_pretty(&saved.trainer)?,
    ));
    CheckpointStore::of_run(run).write(&files, 1)
}

/// The newest state saved in the run directory `run` that reads back (newer damaged ones are
/// skipped, and logged); `None` when it holds none.
pub fn load(run: &Path) -> Result<Option<Loaded<SavedRun>>> {
    let loaded = CheckpointStore::of_run(run).load_newest(from_files)?;
    for skipped in loaded.iter().flat_map(|l| &l.skipped) {
        tracing::warn!(checkpoint = %skipped.name, reason = %skipped.reason, "skipped");
    }
    Ok(loaded)
}

fn from_files(files: &BTreeMap<String, Vec<u8>>) -> Result<SavedRun> {
    let checkpoint = LearnerCheckpoint::from_files(files)?;
    if !checkpoint.has_replay() {
        anyhow::bail!(
            "it holds no replay (a learner daemon's checkpoint without --checkpoint-replay)"
        );
    }
    let trainer = files.get(TRAINER_STATE_FILE).with_context(|| {
        format!("{TRAINER_STATE_FILE} is missing: not a state `--keep-state` saved")
    })?;
    let trainer =
        serde_json::from_slice(trainer).with_context(|| format!("reading {TRAINER_STATE_FILE}"))?;
    Ok(SavedRun {
        checkpoint,
        trainer,
    })
}
