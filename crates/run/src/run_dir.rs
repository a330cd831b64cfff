//! The layout of a run directory, written by `hac train`:
//!
//! - `config.toml`: the resolved configuration (feed it back with `--config` to repeat the run);
//! - `curve.csv`: one row per test round (success rate, speeds, per-level losses), appended live;
//! - `curve.svg`: the learning curve, redrawn after every round;
//! - `weights/level<i>.safetensors`: each level's actor and critic (neural agent) or Q table
//!   (tabular agent, see `hac_tabular::checkpoint`), at the end of training;
//! - `weights/best/`: the weights of the best test round (neural agent): `level<i>.safetensors`
//!   holds level `i`'s actor (what a greedy policy needs) and `best.json` the round, its
//!   training episodes, env steps, success rate and weights version ([`BestRecord`]). Written
//!   at the end of training, and by the learner daemon whenever a round beats the best;
//! - `summary.json`: headline figures (final and best success, episodes to 50% and 90%, time);
//! - `checkpoints/`: the learner daemon's checkpoints ([`crate::checkpoints`]).

use std::fs::File;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use hac_agent::{Agent, RoundReport};
use hac_proto::BestWeights;
use hac_tabular::TabularAgent;
use serde::{Deserialize, Serialize};

use crate::checkpoints::CheckpointStore;
use crate::config::RunConfig;
use crate::plot;

pub fn weights_dir(run: &Path) -> PathBuf {
    run.join("weights")
}

/// `weights/best/`: the weights of the run's best test round.
pub fn best_dir(run: &Path) -> PathBuf {
    weights_dir(run).join("best")
}

const BEST_FILE: &str = "best.json";

/// `weights/best/best.json`: which test round the best weights are from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BestRecord {
    /// 1-based, as in `curve.csv`.
    pub round: usize,
    /// Training episodes behind the weights (the curve's x).
    pub episodes: u64,
    pub env_steps: u64,
    pub success_rate: f32,
    pub weights_version: u64,
    pub levels: usize,
}

impl BestRecord {
    pub fn of(best: &BestWeights) -> Self {
        Self {
            round: best.round,
            episodes: best.episodes,
            env_steps: best.env_steps,
            success_rate: best.success_rate,
            weights_version: best.snapshot.version,
            levels: best.snapshot.levels.len(),
        }
    }
}

/// Writes `best` as `weights/best/` of the run in `run` (see [`RunDir::save_best`]), replacing the directory as a whole
/// (written beside it as `best.new`, then renamed), so a reader finds either the old or the new
/// best, never a mix.
fn write_best(run: &Path, best: &BestWeights) -> Result<()> {
    let dir = best_dir(run);
    let new = dir.with_extension("new");
    let old = dir.with_extension("old");
    for stale in [&new, &old] {
        if stale.exists() {
            std::fs::remove_dir_all(stale)
                .with_context(|| format!("removing {}", stale.display()))?;
        }
    }
    std::fs::create_dir_all(&new).with_context(|| format!("creating {}", new.display()))?;
    for (level, bytes) in best.snapshot.levels.iter().enumerate() {
        write_file(&new.join(format!("level{level}.safetensors")), bytes)?;
    }
    write_file(
        &new.join(BEST_FILE),
        serde_json::to_string_pretty(&BestRecord::of(best))?.as_bytes(),
    )?;
    if dir.exists() {
        std::fs::rename(&dir, &old).with_context(|| format!("replacing {}", dir.display()))?;
    }
    std::fs::rename(&new, &dir).with_context(|| format!("writing {}", dir.display()))?;
    if old.exists() {
        std::fs::remove_dir_all(&old).with_context(|| format!("removing {}", old.display()))?;
    }
    Ok(())
}

/// Reads `weights/best/` of the run in `run`: the record and each level's actor
/// (safetensors), level 0 first.
pub fn load_best(run: &Path) -> Result<(BestRecord, Vec<Vec<u8>>)> {
    let dir = best_dir(run);
    let record_path = dir.join(BEST_FILE);
    let text = match std::fs::read(&record_path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => anyhow::bail!(
            "{} has no best weights ({} is missing): they are written at the end of a neural \
             run's training once a test round was evaluated (and by the learner daemon as rounds \
             come)",
            run.display(),
            record_path.display()
        ),
        Err(e) => {
            return Err(e).with_context(|| format!("reading {}", record_path.display()));
        }
    };
    let record: BestRecord = serde_json::from_slice(&text)
        .with_context(|| format!("parsing {}", record_path.display()))?;
    let levels = (0..record.levels)
        .map(|level| {
            let path = dir.join(format!("level{level}.safetensors"));
            std::fs::read(&path).with_context(|| format!("reading {}", path.display()))
        })
        .collect::<Result<_>>()?;
    Ok((record, levels))
}

/// A trained agent that can write its `weights/` directory.
pub trait Weights {
    fn save(&self, dir: &Path) -> Result<()>;
}

impl Weights for Agent {
    fn save(&self, dir: &Path) -> Result<()> {
        Ok(Agent::save(self, dir)?)
    }
}

/// Writes every level's Q table as `level<i>.safetensors`.
impl Weights for TabularAgent {
    fn save(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        for level in 0..self.num_levels() {
            let bytes = self.table_to_safetensors(level)?;
            write_file(&dir.join(format!("level{level}.safetensors")), &bytes)?;
        }
        Ok(())
    }
}

/// Headline figures of a finished run.
#[derive(Debug, Serialize, Deserialize)]
pub struct Summary {
    pub env: String,
    pub levels: usize,
    pub seed: u64,
    pub episodes: u64,
    pub env_steps: u64,
    pub rounds: usize,
    pub final_success: f32,
    pub best_success: f32,
    pub episodes_to_50: Option<u64>,
    pub episodes_to_90: Option<u64>,
    pub wall_time_s: f64,
    /// What a particular entry point adds (the learner daemon: its ingest counts).
    #[serde(flatten)]
    pub extra: serde_json::Map<String, serde_json::Value>,
}

impl Summary {
    /// The one line `hac train` prints at the end of a run.
    pub fn done_line(&self, out: &Path) -> String {
        format!(
            "done: {} episodes in {:.1}s; final success {:.1}%, best {:.1}%; 90% reached {}; results in {}",
            self.episodes,
            self.wall_time_s,
            100.0 * self.final_success,
            100.0 * self.best_success,
            self.episodes_to_90
                .map_or("never".to_string(), |e| format!("after {e} episodes")),
            out.display()
        )
    }
}

#[derive(Debug)]
pub struct RunDir {
    path: PathBuf,
    config: RunConfig,
    csv: File,
    curve: Vec<(f64, f64)>,
    /// The round whose weights `weights/best/` holds, if written by this process.
    best_round: Option<usize>,
}

impl RunDir {
    /// Creates the directory and writes `config.toml` and the CSV header. A directory that
    /// already holds a run is refused unless `overwrite`, so results are never lost by accident;
    /// overwriting also removes the old run's checkpoints, which a resume would otherwise find,
    /// and its `summary.json`, so that the new run does not pass for a finished one before it
    /// is.
    pub fn create(path: &Path, config: &RunConfig, overwrite: bool) -> Result<Self> {
        if path.join("config.toml").exists() {
            if !overwrite {
                anyhow::bail!(
                    "{} already holds a run; choose another --out or pass --overwrite",
                    path.display()
                );
            }
            CheckpointStore::of_run(path).remove_all()?;
            let summary = path.join(SUMMARY_FILE);
            match std::fs::remove_file(&summary) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => {
                    return Err(e).with_context(|| format!("removing {}", summary.display()));
                }
            }
        }
        std::fs::create_dir_all(path)
            .with_context(|| format!("creating run directory {}", path.display()))?;
        Self::open(path, config, &[])
    }

    /// Continues the run in `path` from a checkpoint whose learning curve is `curve`:
    /// `config.toml` is written again, and `curve.csv` and `curve.svg` are rewritten to hold
    /// exactly `curve` (rows recorded after the checkpoint belong to the weights that were lost
    /// with it); new rounds append after them.
    pub fn resume(path: &Path, config: &RunConfig, curve: &[RoundReport]) -> Result<Self> {
        Self::open(path, config, curve)
    }

    fn open(path: &Path, config: &RunConfig, curve: &[RoundReport]) -> Result<Self> {
        write_file(
            &path.join("config.toml"),
            toml::to_string(config)?.as_bytes(),
        )?;
        let csv_path = path.join(CURVE_FILE);
        let mut text = RoundReport::csv_header(config.levels);
        text.push('\n');
        for report in curve {
            text += &report.csv_row();
            text.push('\n');
        }
        write_file(&csv_path, text.as_bytes())?;
        let csv = std::fs::OpenOptions::new()
            .append(true)
            .open(&csv_path)
            .with_context(|| format!("opening {}", csv_path.display()))?;
        let mut dir = Self {
            path: path.to_path_buf(),
            config: config.clone(),
            csv,
            curve: curve
                .iter()
                .map(|r| (r.episodes as f64, r.success_rate as f64))
                .collect(),
            best_round: None,
        };
        if !curve.is_empty() {
            dir.draw()?;
        }
        Ok(dir)
    }

    /// Appends one test round to the CSV and redraws the plot.
    pub fn record(&mut self, report: &RoundReport) -> Result<()> {
        writeln!(self.csv, "{}", report.csv_row())?;
        self.csv.flush()?;
        self.curve
            .push((report.episodes as f64, report.success_rate as f64));
        self.draw()
    }

    fn draw(&mut self) -> Result<()> {
        let title = format!(
            "{}, {} levels, seed {}",
            self.config.env, self.config.levels, self.config.seed
        );
        let svg = plot::success_chart(
            &title,
            "training episodes",
            &[plot::Series {
                label: format!("{} levels", self.config.levels),
                points: self.curve.clone(),
                band: None,
            }],
        );
        write_file(&self.path.join("curve.svg"), svg.as_bytes())
    }

    /// Writes `weights/best/` from `best`, unless it already holds that round's weights.
    pub fn save_best(&mut self, best: &BestWeights) -> Result<()> {
        if self.best_round != Some(best.round) {
            write_best(&self.path, best)?;
            self.best_round = Some(best.round);
        }
        Ok(())
    }

    /// Test rounds recorded so far.
    pub fn rounds(&self) -> usize {
        self.curve.len()
    }

    /// Saves the weights and the summary.
    pub fn finish(
        &self,
        agent: &dyn Weights,
        curve: &[RoundReport],
        wall_time_s: f64,
    ) -> Result<Summary> {
        self.finish_with(agent, curve, wall_time_s, serde_json::Map::new())
    }

    /// [`finish`](Self::finish) with `extra` fields in `summary.json`.
    pub fn finish_with(
        &self,
        agent: &dyn Weights,
        curve: &[RoundReport],
        wall_time_s: f64,
        extra: serde_json::Map<String, serde_json::Value>,
    ) -> Result<Summary> {
        agent.save(&weights_dir(&self.path))?;
        let first_at = |target: f32| {
            curve
                .iter()
                .find(|r| r.success_rate >= target)
                .map(|r| r.episodes)
        };
        let last = curve.last();
        let summary = Summary {
            env: self.config.env.clone(),
            levels: self.config.levels,
            seed: self.config.seed,
            episodes: last.map_or(0, |r| r.episodes),
            env_steps: last.map_or(0, |r| r.env_steps),
            rounds: curve.len(),
            final_success: last.map_or(0.0, |r| r.success_rate),
            best_success: curve.iter().map(|r| r.success_rate).fold(0.0, f32::max),
            episodes_to_50: first_at(0.5),
            episodes_to_90: first_at(0.9),
            wall_time_s,
            extra,
        };
        write_file(
            &self.path.join(SUMMARY_FILE),
            serde_json::to_string_pretty(&summary)?.as_bytes(),
        )?;
        Ok(summary)
    }
}

const SUMMARY_FILE: &str = "summary.json";
const CURVE_FILE: &str = "curve.csv";

/// Reads the `summary.json` of the run in `run`: written last, by [`RunDir::finish`], so a run
/// without one did not get there (it was killed, or is still training). A run stopped by
/// SIGINT/SIGTERM has one too, over the episodes it trained.
pub fn load_summary(run: &Path) -> Result<Summary> {
    let path = run.join(SUMMARY_FILE);
    let text = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_slice(&text).with_context(|| format!("parsing {}", path.display()))
}

/// Reads the `curve.csv` of the run in `run`, a run of `levels` levels: one report per test
/// round, as [`RoundReport::from_csv_row`] parses it back.
pub fn load_curve(run: &Path, levels: usize) -> Result<Vec<RoundReport>> {
    let path = run.join(CURVE_FILE);
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = text.lines();
    let header = RoundReport::csv_header(levels);
    if lines.next() != Some(header.as_str()) {
        anyhow::bail!(
            "{} does not start with the header of a {levels}-level run ({header})",
            path.display()
        );
    }
    lines
        .enumerate()
        .map(|(i, row)| {
            RoundReport::from_csv_row(row, levels)
                .map_err(|message| anyhow::anyhow!("{}, line {}: {message}", path.display(), i + 2))
        })
        .collect()
}

/// The line `hac train` prints before training `run` into `out`; `learner` names a learner other
/// than the neural default (e.g. "tabular Q-learning").
pub fn training_banner(run: &RunConfig, out: &Path, learner: Option<&str>) -> String {
    let shape = match run.hiro() {
        Some(h) => format!("HIRO, c = {}", h.c),
        None => format!("H = {}", run.agent.horizon),
    };
    format!(
        "training {} with {} level{} ({shape}{}), seed {}, {} episodes; test round every {} episodes; writing {}",
        run.env,
        run.levels,
        if run.levels == 1 { "" } else { "s" },
        learner.map(|l| format!(", {l}")).unwrap_or_default(),
        run.seed,
        run.episodes,
        run.agent.exploration_episodes,
        out.display()
    )
}

/// Writes atomically (temp file, then rename) so a reader never sees half a file.
pub fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))
}
