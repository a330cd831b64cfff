//! A run's whole saved state, as `hac train --keep-state` and `hac experiment --keep-state`
//! write it and `--resume` reads it: the learner's checkpoint with its replay, and the trainer's
//! state beside it (docs/CHECKPOINTS.md, "Training on").

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result};
use hac_learner::LearnerCheckpoint;
use hac_run::checkpoints::{CheckpointStore, Loaded, Written};
use hac_serve::SavedRun;

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
