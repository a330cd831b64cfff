//! The grid worlds (`four-rooms`, `four-rooms-25`) in `hac`: tabular HAC from `hac_tabular`,
//! trained with the same reference schedule as the neural agent ([`crate::schedule`]), written to
//! the same run directory layout, evaluated and loaded back for rendering.
//!
//! `weights/level<i>.safetensors` holds level i's Q table, sparsely (the entries that differ from
//! the initial value; `hac_tabular::checkpoint` documents the layout). In `curve.csv` the
//! per-level columns mean: `updates` the Q-learning updates so far, `critic_loss` the mean
//! squared TD error and `mean_q` the mean value of the entries updated after the last training
//! episode; `replay_len` and `actor_loss` are 0 (no replay, no actor).

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use anyhow::{Context, Result};
use hac_agent::{LevelReport, RoundReport};
use hac_core::{Env, EpisodeOutcome, Episodes, Hierarchy, Mode, Rng};
use hac_tabular::{FourRooms, TabularAgent, TabularHac};

use crate::config::RunConfig;
use crate::run_dir::{self, RunDir, Summary};
use crate::schedule::{self, Schedule, Trained};

/// Whether `env` is a grid world trained by this module.
pub fn handles(env: &str) -> bool {
    crate::registry::is_tabular(env)
}

/// The run's grid world, with the run's episode budget.
fn grid_world(run: &RunConfig) -> Result<FourRooms> {
    let mut env = hac_tabular::four_rooms(&run.env)?;
    run.apply_to_env(&mut env);
    Ok(env)
}

/// A tabular learner with its environment and random streams: what the schedule drives.
struct TabularRun {
    env: FourRooms,
    learner: TabularHac,
    train_rng: Rng,
    test_rng: Rng,
}

impl TabularRun {
    /// Fresh tables for `run`; every random stream derives from `run.seed`.
    fn new(run: &RunConfig) -> Result<Self> {
        let env = grid_world(run)?;
        let mut root = Rng::seed_from(run.seed);
        let tabular = run.tabular.clone().unwrap_or_default();
        let learner = TabularHac::new(&env, run.agent.clone(), &tabular, &mut root)?;
        Ok(Self {
            env,
            learner,
            train_rng: root.fork(),
            test_rng: root.fork(),
        })
    }
}

impl schedule::Learner for TabularRun {
    fn rollout(&mut self) -> usize {
        self.learner
            .collect_episode(&mut self.env, &mut self.train_rng)
            .steps
    }

    fn learn(&mut self) {
        self.learner.learn();
    }

    fn test(&mut self, episodes: usize) -> f32 {
        self.learner
            .success_rate(&mut self.env, &mut self.test_rng, episodes)
    }

    fn level_reports(&self) -> Vec<LevelReport> {
        let agent = self.learner.agent();
        (0..agent.num_levels())
            .map(|level| {
                let stats = agent.level_stats(level);
                LevelReport {
                    updates: stats.updates,
                    replay_len: 0,
                    critic_loss: stats.mean_sq_td_error,
                    actor_loss: 0.0,
                    mean_q: stats.mean_q,
                }
            })
            .collect()
    }
}

/// Trains `run` into `dir` with the reference schedule (`on_round` sees every test round), then
/// saves the tables and the summary; an `interrupt` ends training between episodes.
pub fn train_into(
    run: &RunConfig,
    dir: &mut RunDir,
    interrupt: &AtomicBool,
    mut on_round: impl FnMut(&RoundReport),
) -> Result<(Trained, Summary)> {
    let mut learner = TabularRun::new(run)?;
    let schedule = Schedule {
        episodes: run.episodes,
        exploration_episodes: run.agent.exploration_episodes,
        test_episodes: run.agent.test_episodes,
        stop_at: run.stop_at,
    };
    let started = Instant::now();
    let mut write_error = None;
    let trained = schedule::run(&mut learner, &schedule, interrupt, |report| {
        on_round(report);
        if let Err(e) = dir.record(report) {
            write_error.get_or_insert(e);
        }
    });
    if let Some(e) = write_error {
        return Err(e);
    }
    let summary = dir.finish(
        learner.learner.agent(),
        &trained.curve,
        started.elapsed().as_secs_f64(),
    )?;
    Ok((trained, summary))
}

/// `hac train` for a grid world, into the already created run directory `dir` at `out`.
pub fn train(run: &RunConfig, mut dir: RunDir, out: &Path) -> Result<()> {
    let interrupt = hac_run::signals::interrupt_flag()?;
    outln!(
        "{}",
        run_dir::training_banner(run, out, Some("tabular Q-learning"))
    );
    let (trained, summary) = train_into(run, &mut dir, &interrupt, |report| {
        outln!("{}", schedule::progress_line(report));
    })?;
    if interrupt.load(Ordering::Relaxed) {
        outln!(
            "interrupted after {} episodes: saved what was learned",
            trained.episodes
        );
    }
    outln!("{}", summary.done_line(out));
    Ok(())
}

/// The trained agent of the run in `run_dir` (its tables read from `weights/`), with a fresh
/// environment. `seed` seeds the agent's tie-breaking between equal values.
pub fn load(run_dir: &Path, run: &RunConfig, seed: u64) -> Result<(FourRooms, TabularAgent)> {
    let env = grid_world(run)?;
    let tabular = run.tabular.clone().unwrap_or_default();
    let mut agent = TabularAgent::new(env.grid(), &run.agent, &tabular, Rng::seed_from(seed))?;
    let weights = run_dir::weights_dir(run_dir);
    for level in 0..run.levels {
        let path = weights.join(format!("level{level}.safetensors"));
        let bytes = std::fs::read(&path)
            .with_context(|| format!("reading {} (has the run finished?)", path.display()))?;
        agent
            .load_table(level, &bytes)
            .with_context(|| format!("loading {}", path.display()))?;
    }
    Ok((env, agent))
}

/// `hac eval` for a grid world: `episodes` episodes in `mode` (greedy test episodes, or the
/// behaviour policy of training) of the run in `run_dir`, seeded by `seed`; calls `on_episode`
/// with each outcome, final state and the rollout; returns the success rate.
pub fn evaluate(
    run_dir: &Path,
    run: &RunConfig,
    episodes: usize,
    seed: u64,
    mode: Mode,
    on_episode: impl FnMut(&EpisodeOutcome, &[f32], &Episodes),
) -> Result<f32> {
    let (mut env, mut agent) = load(run_dir, run, seed)?;
    let mut rng = Rng::seed_from(seed);
    // Consulted in the behaviour policy's episodes only (test mode is greedy at every level).
    let mut exploration = agent.exploration(&run.agent, rng.fork());
    let mut rollout = Episodes::Hac(Hierarchy::new(env.spec(), &run.agent));
    Ok(hac_agent::play_episodes(
        &mut rollout,
        &mut env,
        &mut agent,
        &mut exploration,
        &mut rng,
        episodes,
        mode,
        on_episode,
    ))
}
