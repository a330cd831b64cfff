//! [`RunConfig`]: everything that defines a training run. `hac train` writes it to a run
//! directory's `config.toml`; the learner daemon hands it to every actor at registration, so the
//! learner is the run's single source of truth.

use std::path::Path;

use hac_core::hiro::{Algo, HiroConfig};
use hac_core::{AgentConfig, Bounds};
use hac_tabular::TabularConfig;
use serde::{Deserialize, Serialize};

/// Everything that defines a training run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// The algorithm: `hac` (the default, left out of the file) or `hiro` (2 levels only).
    #[serde(default, skip_serializing_if = "Algo::is_hac")]
    pub algo: Algo,
    /// Built-in environment name (`hac env list` lists them).
    pub env: String,
    /// Number of levels (1 = flat DDPG + HER).
    pub levels: usize,
    /// Seed of every random stream.
    pub seed: u64,
    /// Training episodes in total.
    pub episodes: u64,
    /// Stop once a test round reaches this success rate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_at: Option<f32>,
    /// Replay shards per level.
    pub replay_shards: usize,
    /// Episode budget in primitive actions, replacing the environment's (`hac env describe`
    /// shows it); training and test episodes alike end after this many actions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_actions: Option<usize>,
    /// Subgoal bounds replacing the environment's (`hac env describe` shows them), as
    /// `{ low = [...], high = [...] }` with one value per subgoal dimension: the box the levels
    /// above 0 propose subgoals in. Not for the grid worlds, whose subgoals are cells.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub subgoal_bounds: Option<Bounds>,
    /// HAC hyperparameters (defaults: the environment's, for this number of levels).
    pub agent: AgentConfig,
    /// The tabular learner's own settings; present exactly for the grid worlds. Set under
    /// `[tabular]` in the file, with `--set tabular.KEY=VALUE`, or `HAC_TABULAR_<KEY>`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tabular: Option<TabularConfig>,
    /// HIRO's own settings; present exactly when `algo` is `hiro`. Set under `[hiro]` in the
    /// file, with `--set hiro.KEY=VALUE`, or `HAC_HIRO_<KEY>`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hiro: Option<HiroConfig>,
}

/// Why a run configuration could not be read.
#[derive(Debug, thiserror::Error)]
pub enum RunConfigError {
    #[error("reading {path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("in {origin}: {message}")]
    Parse { origin: String, message: String },
    #[error("invalid value for `{key}`: {message}")]
    Invalid { key: &'static str, message: String },
    #[error("in {origin}: {source}")]
    Env {
        origin: String,
        #[source]
        source: hac_envs::UnknownEnv,
    },
    #[error("in {origin}: {source}")]
    Agent {
        origin: String,
        #[source]
        source: hac_core::ConfigError,
    },
}

impl RunConfig {
    /// The TOML document `config.toml` holds.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).expect("a run config is always representable in TOML")
    }

    /// Parses and [validates](Self::validate) a TOML document; `origin` names it in errors
    /// (a path, or "the learner's run config").
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, RunConfigError> {
        let config: Self = toml::from_str(text).map_err(|e| RunConfigError::Parse {
            origin: origin.to_string(),
            message: e.to_string(),
        })?;
        config.validate(origin)?;
        Ok(config)
    }

    /// Reads a run directory's `config.toml`.
    pub fn load_run(dir: &Path) -> Result<Self, RunConfigError> {
        let path = dir.join("config.toml");
        let shown = path.display().to_string();
        let text = std::fs::read_to_string(&path).map_err(|source| RunConfigError::Io {
            path: format!("{shown} (is this a run directory?)"),
            source,
        })?;
        Self::from_toml(&text, &shown)
    }

    /// Checks every field, naming the first invalid one.
    pub fn validate(&self, origin: &str) -> Result<(), RunConfigError> {
        let invalid = |key, message: String| Err(RunConfigError::Invalid { key, message });
        if self.levels == 0 || self.levels > 8 {
            return invalid("levels", format!("{} (must be 1 to 8)", self.levels));
        }
        if self.agent.levels != self.levels {
            return invalid(
                "agent.levels",
                format!(
                    "{} differs from `levels` = {}; set `levels` at the top level",
                    self.agent.levels, self.levels
                ),
            );
        }
        if self.replay_shards == 0 {
            return invalid("replay_shards", "must be at least 1".into());
        }
        if let Some(n) = self.max_actions
            && let Err(message) = check_max_actions(n)
        {
            return invalid("max_actions", message);
        }
        if let Some(s) = self.stop_at
            && !(0.0..=1.0).contains(&s)
        {
            return invalid("stop_at", format!("{s} (must be a success rate in [0, 1])"));
        }
        let env = self.make_env().map_err(|source| RunConfigError::Env {
            origin: origin.to_string(),
            source,
        })?;
        if let Some(bounds) = &self.subgoal_bounds
            && let Err(message) = check_subgoal_bounds(&self.env, bounds, env.spec().subgoal_dim())
        {
            return invalid("subgoal_bounds", message);
        }
        if self.is_tabular() != self.tabular.is_some() {
            return invalid(
                "tabular",
                format!(
                    "the `[tabular]` section is required for the grid worlds ({}) and refused for \
                     every other environment",
                    hac_tabular::names().join(", ")
                ),
            );
        }
        if (self.algo == Algo::Hiro) != self.hiro.is_some() {
            return invalid(
                "hiro",
                "the `[hiro]` section is required with `algo = \"hiro\"` and refused otherwise"
                    .into(),
            );
        }
        if let Some(hiro) = &self.hiro {
            if self.is_tabular() {
                return invalid(
                    "algo",
                    format!(
                        "HIRO learns continuous tasks; `{}` is a grid world for the tabular \
                         learner",
                        self.env
                    ),
                );
            }
            hiro.validate(self.levels, &self.agent)
                .map_err(|source| RunConfigError::Agent {
                    origin: origin.to_string(),
                    source,
                })?;
        }
        if let Some(tabular) = &self.tabular {
            tabular.validate().map_err(|source| RunConfigError::Agent {
                origin: origin.to_string(),
                source,
            })?;
        }
        let spec = env.spec();
        self.agent
            .validate(spec.action_dim(), spec.subgoal_dim())
            .map_err(|source| RunConfigError::Agent {
                origin: origin.to_string(),
                source,
            })
    }

    /// Extra values per transition of each level ([`hac_core::Transition::extra`]) on `spec`,
    /// level 0 first: none for HAC; HIRO's high level stores its packed low-level steps.
    pub fn extra_widths(&self, spec: &hac_core::EnvSpec) -> Vec<usize> {
        match &self.hiro {
            None => vec![0; self.levels],
            Some(h) => vec![0, hac_core::hiro::StepsShape::of(spec, h.c).width()],
        }
    }

    /// The run's default directory name: `<env>-<k>l-seed<s>`, with `hiro-` before the level
    /// count for a HIRO run (`pendulum-hiro-2l-seed0`).
    pub fn run_name(&self) -> String {
        let algo = match self.algo {
            Algo::Hac => String::new(),
            other => format!("{other}-"),
        };
        format!("{}-{algo}{}l-seed{}", self.env, self.levels, self.seed)
    }

    /// HIRO's settings if the run trains HIRO.
    pub fn hiro(&self) -> Option<&HiroConfig> {
        self.hiro.as_ref()
    }

    /// Whether the environment is a grid world, learned by the tabular learner rather than the
    /// neural agent.
    pub fn is_tabular(&self) -> bool {
        hac_tabular::names().contains(&self.env.as_str())
    }

    /// A fresh instance of the run's environment (continuous tasks and grid worlds alike), with
    /// the run's episode budget.
    pub fn make_env(&self) -> Result<Box<dyn hac_core::Env>, hac_envs::UnknownEnv> {
        let mut env =
            hac_envs::make(&self.env).or_else(|e| hac_tabular::make(&self.env).map_err(|_| e))?;
        self.apply_to_env(env.as_mut());
        Ok(env)
    }

    /// Gives `env` the run's episode budget and subgoal bounds, where the run sets them (for
    /// callers that build the environment themselves, like the tabular learner's concrete grid).
    pub fn apply_to_env(&self, env: &mut dyn hac_core::Env) {
        if let Some(n) = self.max_actions {
            env.set_max_actions(n);
        }
        if let Some(bounds) = &self.subgoal_bounds {
            env.set_subgoal_bounds(bounds.clone());
        }
    }
}

/// The largest episode budget a run may set: far beyond any task's need, and small enough that
/// step counters and `H^levels` stay in range.
pub const MAX_EPISODE_ACTIONS: usize = 100_000_000;

/// Checks a run's `max_actions`; the message says what is allowed.
pub fn check_max_actions(n: usize) -> Result<(), String> {
    if (1..=MAX_EPISODE_ACTIONS).contains(&n) {
        Ok(())
    } else {
        Err(format!("{n} (must be 1 to {MAX_EPISODE_ACTIONS} actions)"))
    }
}

/// Checks a run's `subgoal_bounds` for environment `env` with `dim` subgoal dimensions; the
/// message says what is wrong.
pub fn check_subgoal_bounds(env: &str, bounds: &Bounds, dim: usize) -> Result<(), String> {
    if hac_tabular::names().contains(&env) {
        return Err("the grid worlds' subgoals are cells; they take no bounds".into());
    }
    if bounds.low.len() != dim || bounds.high.len() != dim {
        return Err(format!(
            "{} low and {} high values for {dim} subgoal dimensions (need {dim} of each)",
            bounds.low.len(),
            bounds.high.len()
        ));
    }
    for (d, (lo, hi)) in bounds.low.iter().zip(&bounds.high).enumerate() {
        if !(lo.is_finite() && hi.is_finite() && lo < hi) {
            return Err(format!(
                "dimension {d}: low {lo} and high {hi} must be finite with low < high"
            ));
        }
    }
    Ok(())
}

/// Gives `env` the episode budget `n` once [`check_max_actions`] accepts it (its message
/// otherwise), for callers that set a budget before a run config exists.
pub fn set_checked_budget(env: &mut dyn hac_core::Env, n: usize) -> Result<(), String> {
    check_max_actions(n)?;
    env.set_max_actions(n);
    Ok(())
}
