//! What the learner daemon writes, in the layout of `hac train`'s run directories:
//!
//! - `config.toml`: the resolved run configuration, at start;
//! - `curve.csv`: one row per evaluation, appended as evaluations arrive;
//! - `weights/level<i>.safetensors`: each level's networks, at the end;
//! - `summary.json`: headline figures and the learner's final counts, at the end.

use std::fs::File;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result};
use hac_agent::{RoundReport, RunConfig};
use hac_learner::FinishedRun;
use serde::Serialize;

/// Headline figures of a finished distributed run.
#[derive(Debug, Serialize)]
pub struct Summary {
    pub env: String,
    pub levels: usize,
    pub seed: u64,
    /// Training episodes of the last evaluated weights.
    pub episodes: u64,
    /// Training episodes ingested (all actors; may exceed the budget by a few).
    pub episodes_ingested: u64,
    pub env_steps: u64,
    /// Ingest messages that reached the learner core, valid or not: `messages = batches +
    /// episodes_ingested + duplicates + rejected`, counting the rejections other than
    /// `malformed`, `oversized` and `unauthenticated` (those the transport refuses first).
    pub messages: u64,
    /// Transition batches stored.
    pub batches: u64,
    /// Transitions stored (counted at ingest).
    pub transitions: u64,
    /// Transitions in the replay tables' insert counters (equal to `transitions`).
    pub transitions_in_replay: u64,
    /// Resends of stored messages, acknowledged and dropped.
    pub duplicates: u64,
    pub weights_version: u64,
    pub rounds: usize,
    pub final_success: f32,
    pub best_success: f32,
    pub episodes_to_50: Option<u64>,
    pub episodes_to_90: Option<u64>,
    pub wall_time_s: f64,
    /// Refused inputs by reason (only reasons that occurred).
    pub rejected: serde_json::Map<String, serde_json::Value>,
}

#[derive(Debug)]
pub struct RunDir {
    path: PathBuf,
    config: RunConfig,
    csv: File,
    rows: usize,
}

impl RunDir {
    /// Creates the directory with `config.toml` and the CSV header. A directory that already
    /// holds a run is refused unless `overwrite`.
    pub fn create(path: &Path, config: &RunConfig, overwrite: bool) -> Result<Self> {
        if !overwrite && path.join("config.toml").exists() {
            anyhow::bail!(
                "{} already holds a run; choose another --out or pass --overwrite",
                path.display()
            );
        }
        std::fs::create_dir_all(path)
            .with_context(|| format!("creating run directory {}", path.display()))?;
        write_file(&path.join("config.toml"), config.to_toml().as_bytes())?;
        let csv_path = path.join("curve.csv");
        let mut csv =
            File::create(&csv_path).with_context(|| format!("creating {}", csv_path.display()))?;
        writeln!(csv, "{}", RoundReport::csv_header(config.levels))?;
        csv.flush()?;
        Ok(Self {
            path: path.to_path_buf(),
            config: config.clone(),
            csv,
            rows: 0,
        })
    }

    /// Appends the points of `curve` not written yet.
    pub fn record(&mut self, curve: &[RoundReport]) -> Result<()> {
        let Some(new) = curve.get(self.rows..).filter(|new| !new.is_empty()) else {
            return Ok(());
        };
        for report in new {
            writeln!(self.csv, "{}", report.csv_row())?;
            tracing::info!(
                round = report.round,
                episodes = report.episodes,
                env_steps = report.env_steps,
                success = report.success_rate,
                "evaluation"
            );
        }
        self.csv
            .flush()
            .with_context(|| format!("writing {}", self.path.join("curve.csv").display()))?;
        self.rows = curve.len();
        Ok(())
    }

    /// Saves the weights and the summary.
    pub fn finish(&self, run: &FinishedRun, wall_time: Duration) -> Result<Summary> {
        run.agent
            .save(&self.path.join("weights"))
            .context("saving the weights")?;
        let curve = &run.curve;
        let first_at = |target: f32| {
            curve
                .iter()
                .find(|r| r.success_rate >= target)
                .map(|r| r.episodes)
        };
        let last = curve.last();
        let status = &run.status;
        let summary = Summary {
            env: self.config.env.clone(),
            levels: self.config.levels,
            seed: self.config.seed,
            episodes: last.map_or(0, |r| r.episodes),
            episodes_ingested: status.episodes,
            env_steps: status.env_steps,
            messages: status.messages,
            batches: status.batches,
            transitions: status.transitions,
            transitions_in_replay: status.levels.iter().map(|l| l.transitions_inserted).sum(),
            duplicates: status.duplicates,
            weights_version: status.weights_version,
            rounds: curve.len(),
            final_success: last.map_or(0.0, |r| r.success_rate),
            best_success: curve.iter().map(|r| r.success_rate).fold(0.0, f32::max),
            episodes_to_50: first_at(0.5),
            episodes_to_90: first_at(0.9),
            wall_time_s: wall_time.as_secs_f64(),
            rejected: status
                .rejected
                .iter()
                .filter(|&&(_, n)| n > 0)
                .map(|&(reason, n)| (reason.name().to_string(), n.into()))
                .collect(),
        };
        write_file(
            &self.path.join("summary.json"),
            serde_json::to_string_pretty(&summary)?.as_bytes(),
        )?;
        Ok(summary)
    }
}

/// Writes atomically (temp file, then rename) so a reader never sees half a file.
fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))
}
