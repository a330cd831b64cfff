//! The HAC agent and what every part of a run shares.
//!
//! - [`Agent`]: one [`LevelModel`] per level (HAC's learner, or HIRO's TD3 learner); it is the
//!   rollout's [`Policy`] (greedy outputs) and saves/loads its weights as one safetensors file
//!   per level.
//! - [`RunConfig`]: everything that defines a run (the learner hands it to actors).
//! - [`RoundReport`]: one point of the learning curve, as `curve.csv` stores it.
//! - [`evaluate`] / [`test_episodes`]: greedy test episodes.
//!
//! Training itself is the learner (`hac-learner`) fed by actors (`hac-actor`); the embedded
//! `hac train` runs both in one process.

mod run_config;

use std::path::Path;

use hac_core::hiro::HiroConfig;
use hac_core::{
    AgentConfig, ConfigError, Env, EnvSpec, EpisodeOutcome, Episodes, Exploration,
    GaussianExploration, Mode, NullSink, Policy, Rng,
};
use hac_nn::{LevelModel, NnError};
use serde::{Deserialize, Serialize};

pub use run_config::{
    MAX_EPISODE_ACTIONS, RunConfig, RunConfigError, check_max_actions, check_subgoal_bounds,
    set_checked_budget,
};

/// Why an agent could not be built, saved or loaded.
#[derive(Debug, thiserror::Error)]
pub enum AgentError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Weights {
        path: String,
        #[source]
        source: NnError,
    },
}

/// k level learners; level 0 acts in the environment, level `i > 0` proposes subgoals (HIRO's
/// level 1: relative goals).
#[derive(Debug)]
pub struct Agent {
    levels: Vec<LevelModel>,
}

impl Agent {
    /// Freshly initialised HAC networks for every level; `config` must have been validated.
    pub fn new(spec: &EnvSpec, config: &AgentConfig, rng: &mut Rng) -> Self {
        Self::with_algo(spec, config, None, rng)
    }

    /// Freshly initialised networks for every level of `run`'s algorithm.
    pub fn for_run(spec: &EnvSpec, run: &RunConfig, rng: &mut Rng) -> Self {
        Self::with_algo(spec, &run.agent, run.hiro(), rng)
    }

    /// HIRO's levels when `hiro` is given, else HAC's; each level draws from its own fork of
    /// `rng`, level 0 first.
    fn with_algo(
        spec: &EnvSpec,
        config: &AgentConfig,
        hiro: Option<&HiroConfig>,
        rng: &mut Rng,
    ) -> Self {
        let levels = (0..config.levels)
            .map(|level| LevelModel::new(config, hiro, spec, level, &mut rng.fork()))
            .collect();
        Self { levels }
    }

    /// An agent made of trained level learners, level 0 first.
    pub fn from_levels(levels: Vec<LevelModel>) -> Self {
        Self { levels }
    }

    /// The level learners, level 0 first.
    pub fn into_levels(self) -> Vec<LevelModel> {
        self.levels
    }

    pub fn levels(&self) -> &[LevelModel] {
        &self.levels
    }

    /// Writes `level<i>.safetensors` (actor, critic) for every level into `dir`.
    pub fn save(&self, dir: &Path) -> Result<(), AgentError> {
        std::fs::create_dir_all(dir).map_err(|source| AgentError::Io {
            path: dir.display().to_string(),
            source,
        })?;
        for (i, level) in self.levels.iter().enumerate() {
            let path = dir.join(format!("level{i}.safetensors"));
            let tmp = path.with_extension("safetensors.tmp");
            let io = |source| AgentError::Io {
                path: path.display().to_string(),
                source,
            };
            std::fs::write(&tmp, level.to_safetensors()).map_err(io)?;
            std::fs::rename(&tmp, &path).map_err(io)?;
        }
        Ok(())
    }

    /// Reads the weights `save` wrote, checking them against the run's config.
    pub fn load(dir: &Path, spec: &EnvSpec, run: &RunConfig) -> Result<Self, AgentError> {
        let config = &run.agent;
        let mut levels = Vec::with_capacity(config.levels);
        for level in 0..config.levels {
            let path = dir.join(format!("level{level}.safetensors"));
            let shown = path.display().to_string();
            let bytes = std::fs::read(&path).map_err(|source| AgentError::Io {
                path: shown.clone(),
                source,
            })?;
            let learner = LevelModel::from_safetensors(config, run.hiro(), spec, level, &bytes)
                .map_err(|source| AgentError::Weights {
                    path: shown.clone(),
                    source,
                })?;
            levels.push(learner);
        }
        Ok(Self { levels })
    }
}

impl Policy for Agent {
    fn act(&mut self, level: usize, state: &[f32], goal: &[f32], action: &mut [f32]) {
        self.levels[level].act(state, goal, action);
    }
}

/// One level's training statistics at a test round.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct LevelReport {
    /// Updates done so far.
    pub updates: u64,
    /// Transitions in replay.
    pub replay_len: usize,
    /// Statistics of the last update (zero before the first).
    pub critic_loss: f32,
    pub actor_loss: f32,
    pub mean_q: f32,
}

/// One point of the learning curve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoundReport {
    /// 1-based test round.
    pub round: usize,
    /// Training episodes so far.
    pub episodes: u64,
    /// Primitive actions in training episodes so far.
    pub env_steps: u64,
    /// Greedy test success rate of this round.
    pub success_rate: f32,
    /// Seconds since training started.
    pub elapsed_s: f64,
    /// Training rollout speed since the last round (primitive actions per second).
    pub env_steps_per_s: f64,
    /// Update speed since the last round (updates per second, all levels).
    pub updates_per_s: f64,
    pub levels: Vec<LevelReport>,
}

impl RoundReport {
    /// Header of the learning-curve CSV for `levels` levels.
    pub fn csv_header(levels: usize) -> String {
        let mut h = String::from(
            "round,episodes,env_steps,success_rate,elapsed_s,env_steps_per_s,updates_per_s",
        );
        for l in 0..levels {
            for f in [
                "updates",
                "replay_len",
                "critic_loss",
                "actor_loss",
                "mean_q",
            ] {
                h.push_str(&format!(",level{l}_{f}"));
            }
        }
        h
    }

    /// The report's row of the learning-curve CSV, under [`csv_header`](Self::csv_header).
    pub fn csv_row(&self) -> String {
        let mut r = format!(
            "{},{},{},{:.4},{:.3},{:.1},{:.1}",
            self.round,
            self.episodes,
            self.env_steps,
            self.success_rate,
            self.elapsed_s,
            self.env_steps_per_s,
            self.updates_per_s
        );
        for l in &self.levels {
            r.push_str(&format!(
                ",{},{},{},{},{}",
                l.updates, l.replay_len, l.critic_loss, l.actor_loss, l.mean_q
            ));
        }
        r
    }

    /// Parses a row written by [`csv_row`](Self::csv_row), of a run with `levels` levels. The
    /// success rate and the timings come back as rounded in the row (4 decimals for the rate);
    /// an error counts the columns when there are too few or too many, or names the one that is
    /// not a number.
    pub fn from_csv_row(row: &str, levels: usize) -> Result<Self, String> {
        let header = Self::csv_header(levels);
        let names: Vec<&str> = header.split(',').collect();
        let fields: Vec<&str> = row.trim_end().split(',').collect();
        if fields.len() != names.len() {
            return Err(format!(
                "{} columns, expected {} ({levels} level{})",
                fields.len(),
                names.len(),
                if levels == 1 { "" } else { "s" }
            ));
        }
        fn parse<T: std::str::FromStr>(
            fields: &[&str],
            names: &[&str],
            i: usize,
        ) -> Result<T, String> {
            fields[i]
                .parse()
                .map_err(|_| format!("`{}` is not a valid {}", fields[i], names[i]))
        }
        let level = |l: usize| -> Result<LevelReport, String> {
            let at = 7 + 5 * l;
            Ok(LevelReport {
                updates: parse(&fields, &names, at)?,
                replay_len: parse(&fields, &names, at + 1)?,
                critic_loss: parse(&fields, &names, at + 2)?,
                actor_loss: parse(&fields, &names, at + 3)?,
                mean_q: parse(&fields, &names, at + 4)?,
            })
        };
        Ok(Self {
            round: parse(&fields, &names, 0)?,
            episodes: parse(&fields, &names, 1)?,
            env_steps: parse(&fields, &names, 2)?,
            success_rate: parse(&fields, &names, 3)?,
            elapsed_s: parse(&fields, &names, 4)?,
            env_steps_per_s: parse(&fields, &names, 5)?,
            updates_per_s: parse(&fields, &names, 6)?,
            levels: (0..levels).map(level).collect::<Result<_, _>>()?,
        })
    }
}

/// Episodes of a saved agent (or any policy, such as a run's best weights): greedy test episodes
/// in `Mode::Test`, the behaviour policy of training (exploration and subgoal testing, nothing
/// stored or learned) in `Mode::Train`. Calls `on_episode` with each outcome, the final state and
/// the rollout (its end goal, what each level did); returns the success rate.
pub fn evaluate(
    env: &mut dyn Env,
    agent: &mut impl Policy,
    run: &RunConfig,
    episodes: usize,
    seed: u64,
    mode: Mode,
    on_episode: impl FnMut(&EpisodeOutcome, &[f32], &Episodes),
) -> f32 {
    let spec = env.spec().clone();
    let mut rng = Rng::seed_from(seed);
    // Never consulted in test mode, where every level acts greedily.
    let mut exploration = GaussianExploration::new(&spec, &run.agent, rng.fork());
    let mut episodes_of = Episodes::new(&spec, &run.agent, run.hiro());
    play_episodes(
        &mut episodes_of,
        env,
        agent,
        &mut exploration,
        &mut rng,
        episodes,
        mode,
        on_episode,
    )
}

/// Runs `episodes` episodes of `policy` in `mode` (greedy test episodes in `Mode::Test`, which
/// never consults `exploration`; its behaviour policy in `Mode::Train`), storing nothing; calls `on_episode` after each with its outcome, the final
/// state and the rollout; returns the success rate.
#[allow(clippy::too_many_arguments)] // the rollout's collaborators, as `Episodes::run_episode`
pub fn play_episodes(
    rollout: &mut Episodes,
    env: &mut dyn Env,
    agent: &mut impl Policy,
    exploration: &mut impl Exploration,
    rng: &mut Rng,
    episodes: usize,
    mode: Mode,
    mut on_episode: impl FnMut(&EpisodeOutcome, &[f32], &Episodes),
) -> f32 {
    let mut successes = 0usize;
    for _ in 0..episodes {
        let outcome = rollout.run_episode(env, agent, exploration, mode, rng, &mut NullSink);
        successes += usize::from(outcome.success);
        on_episode(&outcome, env.state(), rollout);
    }
    successes as f32 / episodes.max(1) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_curve_row_parses_back_as_written() {
        let report = RoundReport {
            round: 3,
            episodes: 150,
            env_steps: 12_345,
            success_rate: 0.75,
            elapsed_s: 12.5,
            env_steps_per_s: 987.5,
            updates_per_s: 60.0,
            levels: vec![
                LevelReport {
                    updates: 40,
                    replay_len: 900,
                    critic_loss: 0.123_456_79,
                    actor_loss: -1.5,
                    mean_q: f32::NAN,
                },
                LevelReport::default(),
            ],
        };
        let parsed = RoundReport::from_csv_row(&report.csv_row(), 2).unwrap();
        assert!(parsed.levels[0].mean_q.is_nan());
        let nan_free = |mut r: RoundReport| {
            r.levels[0].mean_q = 0.0;
            r
        };
        assert_eq!(nan_free(parsed), nan_free(report.clone()));
        let err = RoundReport::from_csv_row(&report.csv_row(), 1).unwrap_err();
        assert!(err.contains("17 columns, expected 12"), "{err}");
        let bad = report.csv_row().replacen("150", "x", 1);
        let err = RoundReport::from_csv_row(&bad, 2).unwrap_err();
        assert_eq!(err, "`x` is not a valid episodes");
    }
}
