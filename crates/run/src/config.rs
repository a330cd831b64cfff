//! The run configuration: environment defaults, then a TOML file, then `HAC_*` environment
//! variables, then command-line flags. Unknown keys and invalid values are rejected by name.

use std::path::Path;

use anyhow::{Context, Result, anyhow, bail};
use hac_core::hiro::{Algo, HiroConfig};
use hac_core::{AgentConfig, Bounds};
use hac_tabular::TabularConfig;
use serde::Deserialize;

pub use hac_agent::RunConfig;

use crate::registry;

/// The top level of a config file: every key optional.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileConfig {
    algo: Option<Algo>,
    env: Option<String>,
    levels: Option<usize>,
    seed: Option<u64>,
    episodes: Option<u64>,
    stop_at: Option<f32>,
    replay_shards: Option<usize>,
    max_actions: Option<usize>,
    subgoal_bounds: Option<Bounds>,
    agent: Option<toml::Table>,
    tabular: Option<toml::Table>,
    hiro: Option<toml::Table>,
    /// The daemons' tables, checked key by key against their flags by [`crate::daemon`]; the
    /// run itself does not read them.
    #[serde(rename = "learner")]
    _learner: Option<toml::Table>,
    #[serde(rename = "actor")]
    _actor: Option<toml::Table>,
}

/// Checks a config file's top level: only run keys, `[agent]`, `[tabular]`, `[hiro]` and the daemons'
/// tables, with values of the right types (the rest is checked by [`resolve`] and
/// [`crate::daemon`]).
pub(crate) fn check_top_level(table: &toml::Table) -> Result<()> {
    table.clone().try_into::<FileConfig>()?;
    Ok(())
}

/// Values given on the command line or through `HAC_*` variables (clap reads both).
#[derive(Debug, Default)]
pub struct Overrides {
    /// The algorithm (`hac` when no source names one).
    pub algo: Option<Algo>,
    pub env: Option<String>,
    pub levels: Option<usize>,
    pub seed: Option<u64>,
    pub episodes: Option<u64>,
    pub stop_at: Option<f32>,
    pub replay_shards: Option<usize>,
    /// Episode budget replacing the environment's.
    pub max_actions: Option<usize>,
    /// `KEY=VALUE` agent overrides (`tabular.KEY=VALUE` for the tabular learner,
    /// `hiro.KEY=VALUE` for HIRO), VALUE in TOML syntax.
    pub set: Vec<String>,
    /// Leave HIRO's settings (the file's `[hiro]` table, `hiro.KEY` in `set`) out of a HAC run
    /// instead of refusing them: for a grid of both algorithms sharing one set of settings.
    pub hiro_settings_for_hiro_only: bool,
}

pub const DEFAULT_ENV: &str = "pendulum";
pub const DEFAULT_LEVELS: usize = 2;
pub const DEFAULT_EPISODES: u64 = 1000;

/// Resolves the run configuration from all sources, validating it completely.
pub fn resolve(file: Option<&Path>, flags: Overrides) -> Result<RunConfig> {
    let file_config = match file {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading config file {}", path.display()))?;
            toml::from_str::<FileConfig>(&text)
                .with_context(|| format!("in config file {}", path.display()))?
        }
        None => FileConfig::default(),
    };
    let env_name = flags
        .env
        .or(file_config.env)
        .unwrap_or_else(|| DEFAULT_ENV.to_string());
    let mut env = registry::make(&env_name)?;
    let max_actions = flags.max_actions.or(file_config.max_actions);
    if let Some(n) = max_actions {
        // Before the defaults: an H derived from the budget follows the run's.
        hac_agent::set_checked_budget(env.as_mut(), n)
            .map_err(|message| anyhow!("invalid value for `max_actions`: {message}"))?;
    }
    if let Some(bounds) = &file_config.subgoal_bounds {
        hac_agent::check_subgoal_bounds(&env_name, bounds, env.spec().subgoal_dim())
            .map_err(|message| anyhow!("invalid value for `subgoal_bounds`: {message}"))?;
        env.set_subgoal_bounds(bounds.clone());
    }
    let levels = flags
        .levels
        .or(file_config.levels)
        .unwrap_or(DEFAULT_LEVELS);
    if levels == 0 || levels > 8 {
        bail!("invalid value for `levels`: {levels} (must be 1 to 8)");
    }

    let algo = flags.algo.or(file_config.algo).unwrap_or_default();

    // Agent: environment defaults (with HIRO's own where it differs), then the file's [agent]
    // table, then HAC_AGENT_* variables, then --set flags; deserialising the merged table
    // rejects unknown keys by name.
    let mut defaults = env.default_config(levels);
    if algo == Algo::Hiro {
        HiroConfig::agent_defaults(&mut defaults);
    }
    let mut agent = toml::Table::try_from(defaults).context("encoding default config")?;
    if let Some(table) = file_config.agent {
        for (key, value) in table {
            agent.insert(key, value);
        }
    }
    let mut sets = variables("HAC_AGENT_");
    let mut tabular_sets = variables("HAC_TABULAR_");
    let mut hiro_sets = variables("HAC_HIRO_");
    let mut tabular_flags = false;
    let mut hiro_flags = false;
    for kv in &flags.set {
        let (key, value) = kv
            .split_once('=')
            .with_context(|| format!("--set expects KEY=VALUE, got `{kv}`"))?;
        let (key, value) = (key.trim(), value.trim().to_string());
        if let Some(key) = key.strip_prefix("tabular.") {
            tabular_sets.push((key.to_string(), value));
            tabular_flags = true;
        } else if let Some(key) = key.strip_prefix("hiro.") {
            hiro_sets.push((key.to_string(), value));
            hiro_flags = true;
        } else {
            sets.push((key.trim_start_matches("agent.").to_string(), value));
        }
    }
    for (key, value) in sets {
        agent.insert(key.clone(), parse_value(&key, &value)?);
    }
    let agent: AgentConfig = agent.try_into().context("in the agent configuration")?;
    // Keep the level count in one place: the run's.
    if agent.levels != levels {
        bail!("invalid value for `agent.levels`: set `levels` at the top level instead");
    }
    let spec = env.spec();
    agent.validate(spec.action_dim(), spec.subgoal_dim())?;

    // The tabular learner's settings: its defaults, the file's [tabular] table, then
    // HAC_TABULAR_* variables and --set tabular.KEY flags.
    let tabular = if registry::is_tabular(&env_name) {
        let mut table =
            toml::Table::try_from(TabularConfig::default()).context("encoding default config")?;
        table.extend(file_config.tabular.unwrap_or_default());
        for (key, value) in tabular_sets {
            let value = parse_value(&format!("tabular.{key}"), &value)?;
            table.insert(key, value);
        }
        let tabular: TabularConfig = table.try_into().context("in the tabular configuration")?;
        tabular.validate().context("in the tabular configuration")?;
        Some(tabular)
    } else {
        if file_config.tabular.is_some() || tabular_flags {
            bail!(
                "`tabular` settings apply to the grid worlds only ({}), not to `{env_name}`",
                hac_tabular::names().join(", ")
            );
        }
        None
    };

    // HIRO's settings: its defaults, the file's [hiro] table, then HAC_HIRO_* variables and
    // --set hiro.KEY flags.
    let hiro = if algo == Algo::Hiro {
        let mut table =
            toml::Table::try_from(HiroConfig::default()).context("encoding default config")?;
        table.extend(file_config.hiro.unwrap_or_default());
        for (key, value) in hiro_sets {
            let value = parse_value(&format!("hiro.{key}"), &value)?;
            table.insert(key, value);
        }
        let hiro: HiroConfig = table.try_into().context("in the hiro configuration")?;
        hiro.validate(levels, &agent)
            .context("in the hiro configuration")?;
        Some(hiro)
    } else {
        if (file_config.hiro.is_some() || hiro_flags) && !flags.hiro_settings_for_hiro_only {
            bail!("`hiro` settings apply to `algo = \"hiro\"` only (this run trains HAC)");
        }
        None
    };
    if hiro.is_some() && registry::is_tabular(&env_name) {
        bail!(
            "invalid value for `algo`: HIRO learns continuous tasks; `{env_name}` is a grid \
             world for the tabular learner"
        );
    }

    let config = RunConfig {
        algo,
        env: env_name,
        levels,
        seed: flags.seed.or(file_config.seed).unwrap_or(0),
        episodes: flags
            .episodes
            .or(file_config.episodes)
            .unwrap_or(DEFAULT_EPISODES),
        stop_at: flags.stop_at.or(file_config.stop_at),
        replay_shards: flags
            .replay_shards
            .or(file_config.replay_shards)
            .unwrap_or(1),
        max_actions,
        subgoal_bounds: file_config.subgoal_bounds,
        agent,
        tabular,
        hiro,
    };
    if config.replay_shards == 0 {
        bail!("invalid value for `replay_shards`: must be at least 1");
    }
    if let Some(s) = config.stop_at
        && !(0.0..=1.0).contains(&s)
    {
        bail!("invalid value for `stop_at`: {s} (must be a success rate in [0, 1])");
    }
    Ok(config)
}

/// `(key, value)` of every environment variable `<prefix><KEY>`, key lowercased, sorted.
fn variables(prefix: &str) -> Vec<(String, String)> {
    let mut vars: Vec<(String, String)> = std::env::vars()
        .filter_map(|(k, v)| k.strip_prefix(prefix).map(|key| (key.to_lowercase(), v)))
        .collect();
    vars.sort();
    vars
}

/// Parses one override's value as TOML (`10`, `0.5`, `[64, 64]`, `"text"`); a bare word that is
/// not TOML (`distance`) is taken as a string, so that choices need no quotes on the command line.
fn parse_value(key: &str, value: &str) -> Result<toml::Value> {
    let bare_word = value.starts_with(|ch: char| ch.is_ascii_alphabetic())
        && value
            .chars()
            .all(|ch| ch.is_ascii_alphanumeric() || ch == '_' || ch == '-');
    match toml::from_str::<toml::Table>(&format!("v = {value}")) {
        Ok(table) => Ok(table["v"].clone()),
        Err(_) if bare_word => Ok(toml::Value::String(value.to_string())),
        Err(e) => Err(e)
            .with_context(|| format!("invalid value for `{key}`: `{value}` is not a TOML value")),
    }
}

/// Reads a run directory's `config.toml`.
pub fn load_run(dir: &Path) -> Result<RunConfig> {
    Ok(RunConfig::load_run(dir)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use hac_core::hiro::{CriticLoss, TaskReward};

    fn write(text: &str) -> tempfile_like::TempFile {
        tempfile_like::TempFile::new(text)
    }

    /// A minimal temp file helper (std only).
    mod tempfile_like {
        pub struct TempFile(pub std::path::PathBuf);
        impl TempFile {
            pub fn new(text: &str) -> Self {
                static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
                let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let path = std::env::temp_dir()
                    .join(format!("hac-config-test-{}-{n}.toml", std::process::id()));
                std::fs::write(&path, text).unwrap();
                Self(path)
            }
        }
        impl Drop for TempFile {
            fn drop(&mut self) {
                let _ = std::fs::remove_file(&self.0);
            }
        }
    }

    #[test]
    fn defaults_come_from_the_environment() {
        let c = resolve(
            None,
            Overrides {
                env: Some("pendulum".into()),
                levels: Some(3),
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(c.agent.horizon, 10);
        assert_eq!(c.agent.levels, 3);
    }

    #[test]
    fn file_then_flags() {
        let f = write("env = \"pendulum\"\nlevels = 2\nseed = 5\n[agent]\nhorizon = 7\n");
        let c = resolve(
            Some(&f.0),
            Overrides {
                seed: Some(9),
                set: vec!["gamma=0.9".into()],
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!((c.env.as_str(), c.levels, c.seed), ("pendulum", 2, 9));
        assert_eq!(c.agent.horizon, 7);
        assert_eq!(c.agent.gamma, 0.9);
    }

    #[test]
    fn hiro_takes_its_reference_settings_and_refuses_what_it_cannot_run() {
        let hiro = |levels, env: &str, set: Vec<String>| {
            resolve(
                None,
                Overrides {
                    algo: Some(Algo::Hiro),
                    env: Some(env.into()),
                    levels: Some(levels),
                    set,
                    ..Default::default()
                },
            )
        };
        let c = hiro(2, "pendulum", vec!["hiro.c=5".into()]).unwrap();
        assert_eq!(c.algo, Algo::Hiro);
        let h = c.hiro.as_ref().expect("a [hiro] section");
        assert_eq!((h.c, h.candidates, h.policy_delay), (5, 8, 2));
        assert_eq!(
            (c.agent.batch_size, c.agent.gamma, c.agent.target_tau),
            (100, 0.99, Some(0.005))
        );
        // The resolved config says what it trains, and reads back the same.
        let text = toml::to_string(&c).unwrap();
        assert!(
            text.contains("algo = \"hiro\"") && text.contains("[hiro]"),
            "{text}"
        );
        assert_eq!(RunConfig::from_toml(&text, "test").unwrap(), c);
        assert_eq!(h.task_reward, TaskReward::Sparse);
        // The dense task reward is a choice named without quotes; other words are refused.
        let dense = hiro(2, "pendulum", vec!["hiro.task_reward=distance".into()]).unwrap();
        assert_eq!(dense.hiro.unwrap().task_reward, TaskReward::Distance);
        // The critics' loss: the squared error unless asked, and then written down, so that a
        // resumed run keeps it; the default is left out, so older runs keep their digest.
        assert_eq!(h.critic_loss, CriticLoss::Mse);
        assert!(!text.contains("critic_loss"), "{text}");
        let huber = hiro(2, "pendulum", vec!["hiro.critic_loss=huber".into()]).unwrap();
        let huber_text = toml::to_string(&huber).unwrap();
        assert!(
            huber_text.contains("critic_loss = \"huber\""),
            "{huber_text}"
        );
        assert_eq!(RunConfig::from_toml(&huber_text, "test").unwrap(), huber);
        assert_eq!(huber.hiro.unwrap().critic_loss, CriticLoss::Huber);

        for (levels, env, set, named) in [
            (3, "pendulum", vec![], "HIRO has exactly 2 levels"),
            (1, "pendulum", vec![], "HIRO has exactly 2 levels"),
            (2, "four-rooms", vec![], "grid world"),
            (2, "pendulum", vec!["hiro.c=0".into()], "hiro.c"),
            (2, "pendulum", vec!["hiro.cc=3".into()], "cc"),
            (
                2,
                "pendulum",
                vec!["hiro.task_reward=dense".into()],
                "`dense`",
            ),
            (2, "pendulum", vec!["hiro.critic_loss=l1".into()], "`l1`"),
        ] {
            let e = format!("{:#}", hiro(levels, env, set).unwrap_err());
            assert!(e.contains(named), "{e}");
        }
        // HIRO's settings on a HAC run are refused, not ignored.
        let e = format!(
            "{:#}",
            resolve(
                None,
                Overrides {
                    set: vec!["hiro.c=3".into()],
                    ..Default::default()
                },
            )
            .unwrap_err()
        );
        assert!(e.contains("algo = \"hiro\""), "{e}");
        // ... unless they are for the HIRO runs of the same grid: then the HAC run leaves them out.
        let hac = resolve(
            None,
            Overrides {
                set: vec!["hiro.critic_loss=huber".into()],
                hiro_settings_for_hiro_only: true,
                ..Default::default()
            },
        )
        .unwrap();
        assert!(hac.hiro.is_none());
        assert_eq!(hac, resolve(None, Overrides::default()).unwrap());
        // A HAC run's config.toml does not mention the algorithm (the same file as before).
        let hac = resolve(None, Overrides::default()).unwrap();
        assert!(!toml::to_string(&hac).unwrap().contains("algo"));
    }

    #[test]
    fn unknown_and_invalid_keys_are_named() {
        let f = write("levls = 2\n");
        let e = format!(
            "{:#}",
            resolve(Some(&f.0), Overrides::default()).unwrap_err()
        );
        assert!(e.contains("levls"), "{e}");
        let f = write("[agent]\nhorizn = 2\n");
        let e = format!(
            "{:#}",
            resolve(Some(&f.0), Overrides::default()).unwrap_err()
        );
        assert!(e.contains("horizn"), "{e}");
        let e = format!(
            "{:#}",
            resolve(
                None,
                Overrides {
                    set: vec!["gamma=2".into()],
                    ..Default::default()
                }
            )
            .unwrap_err()
        );
        assert!(e.contains("gamma"), "{e}");
        let e = format!(
            "{:#}",
            resolve(
                None,
                Overrides {
                    env: Some("nope".into()),
                    ..Default::default()
                }
            )
            .unwrap_err()
        );
        assert!(e.contains("nope") && e.contains("pendulum"), "{e}");
    }

    #[test]
    fn grid_worlds_get_tabular_settings_and_only_they_do() {
        let f = write("env = \"four-rooms\"\nlevels = 3\n[tabular]\nlearning_rate = 0.5\n");
        let c = resolve(
            Some(&f.0),
            Overrides {
                set: vec!["tabular.initial_q=\"optimistic\"".into()],
                ..Default::default()
            },
        )
        .unwrap();
        let t = c.tabular.as_ref().unwrap();
        assert_eq!(t.learning_rate, 0.5);
        assert_eq!(t.initial_q, hac_tabular::InitialQ::Optimistic);
        assert_eq!(c.agent.horizon, 4, "four-rooms' own H for 3 levels");
        let text = toml::to_string(&c).unwrap();
        assert!(text.contains("[tabular]"), "{text}");
        assert_eq!(toml::from_str::<RunConfig>(&text).unwrap(), c);

        let neural = resolve(None, Overrides::default()).unwrap();
        assert_eq!(neural.tabular, None);
        assert!(!toml::to_string(&neural).unwrap().contains("tabular"));
        for (file, set) in [
            ("[tabular]\nlearning_rate = 0.5\n", vec![]),
            ("", vec!["tabular.learning_rate=0.5".to_string()]),
        ] {
            let f = write(file);
            let e = format!(
                "{:#}",
                resolve(
                    Some(&f.0),
                    Overrides {
                        set,
                        ..Default::default()
                    }
                )
                .unwrap_err()
            );
            assert!(e.contains("tabular") && e.contains("pendulum"), "{e}");
        }
        let e = format!(
            "{:#}",
            resolve(
                None,
                Overrides {
                    env: Some("four-rooms".into()),
                    set: vec!["tabular.learning_rate=2".into()],
                    ..Default::default()
                }
            )
            .unwrap_err()
        );
        assert!(e.contains("learning_rate"), "{e}");
    }

    #[test]
    fn a_run_budget_replaces_the_environments_and_the_h_derived_from_it() {
        let run = |env: &str, levels, max_actions, file: Option<&Path>| {
            resolve(
                file,
                Overrides {
                    env: Some(env.into()),
                    levels: Some(levels),
                    max_actions,
                    ..Default::default()
                },
            )
        };
        // Four-rooms 10 x 10: budget 54 by default (H = 4 covers it with 3 levels); 180 takes
        // H = 6 (5^3 = 125 < 180 <= 216), and the environment the run makes has the budget.
        let default = run("four-rooms", 3, None, None).unwrap();
        assert_eq!((default.max_actions, default.agent.horizon), (None, 4));
        assert_eq!(default.make_env().unwrap().spec().max_actions, 54);
        let long = run("four-rooms", 3, Some(180), None).unwrap();
        assert_eq!((long.max_actions, long.agent.horizon), (Some(180), 6));
        assert_eq!(long.make_env().unwrap().spec().max_actions, 180);
        let text = long.to_toml();
        assert!(text.contains("max_actions = 180"), "{text}");
        assert_eq!(RunConfig::from_toml(&text, "test").unwrap(), long);
        assert!(!default.to_toml().contains("max_actions"));

        // Pendulum: the flat agent's H is the budget; the task's H for 3 levels stays.
        assert_eq!(
            run("pendulum", 1, Some(500), None).unwrap().agent.horizon,
            500
        );
        assert_eq!(
            run("pendulum", 3, Some(500), None).unwrap().agent.horizon,
            10
        );

        // From the file; the flag wins over it.
        let f = write("env = \"ur5-reacher\"\nmax_actions = 300\n");
        let c = run("ur5-reacher", 3, None, Some(&f.0)).unwrap();
        assert_eq!(c.max_actions, Some(300));
        let c = run("ur5-reacher", 3, Some(400), Some(&f.0)).unwrap();
        assert_eq!(c.max_actions, Some(400));

        // Out of range: refused by name, here and in a run config read back.
        for bad in [0, hac_agent::MAX_EPISODE_ACTIONS + 1] {
            let e = format!("{:#}", run("pendulum", 2, Some(bad), None).unwrap_err());
            assert!(
                e.contains("max_actions") && e.contains(&bad.to_string()),
                "{e}"
            );
        }
        let e = RunConfig::from_toml(&text.replace("= 180", "= 0"), "test")
            .unwrap_err()
            .to_string();
        assert!(e.contains("max_actions"), "{e}");
    }

    #[test]
    fn run_subgoal_bounds_replace_the_environments() {
        use std::f32::consts::PI;
        let from = |text: &str| {
            let f = write(text);
            resolve(Some(&f.0), Overrides::default())
        };
        let c = from(
            "env = \"ur5-reacher\"\nlevels = 3\n\
             subgoal_bounds = { low = [-3.1415927, -3.1415927, -3.1415927, -4, -4, -4], \
             high = [3.1415927, 3.1415927, 3.1415927, 4, 4, 4] }\n",
        )
        .unwrap();
        let env = c.make_env().unwrap();
        let bounds = &env.spec().subgoal_bounds;
        assert_eq!(bounds.high, [PI, PI, PI, 4.0, 4.0, 4.0]);
        assert_eq!(env.spec().level_action_bounds(1), bounds);
        // Kept in config.toml and read back the same.
        let text = c.to_toml();
        assert!(text.contains("subgoal_bounds"), "{text}");
        assert_eq!(RunConfig::from_toml(&text, "test").unwrap(), c);
        // Absent: the environment's own (+-2 pi on the angles), and nothing written.
        let plain = from("env = \"ur5-reacher\"\n").unwrap();
        assert_eq!(
            plain.make_env().unwrap().spec().subgoal_bounds.high[0],
            2.0 * PI
        );
        assert!(!plain.to_toml().contains("subgoal_bounds"));

        // Refused by name: a wrong dimension count, low >= high, a non-finite value, a grid world;
        // in a file and in a run config read back.
        for (text, needle) in [
            (
                "env = \"pendulum\"\nsubgoal_bounds = { low = [-1], high = [1] }\n",
                "2 subgoal dimensions",
            ),
            (
                "env = \"pendulum\"\nsubgoal_bounds = { low = [-1, 2], high = [1, 2] }\n",
                "dimension 1",
            ),
            (
                "env = \"pendulum\"\nsubgoal_bounds = { low = [-1, -nan], high = [1, 2] }\n",
                "dimension 1",
            ),
            (
                "env = \"four-rooms\"\nsubgoal_bounds = { low = [0, 0], high = [1, 1] }\n",
                "cells",
            ),
        ] {
            let e = format!("{:#}", from(text).unwrap_err());
            assert!(e.contains("subgoal_bounds") && e.contains(needle), "{e}");
        }
        let bad = text.replace("high = [\n    3.1415927,", "high = [\n    -4.0,");
        assert_ne!(bad, text);
        let e = RunConfig::from_toml(&bad, "test").unwrap_err().to_string();
        assert!(
            e.contains("subgoal_bounds") && e.contains("dimension 0"),
            "{e}"
        );
    }

    #[test]
    fn resolved_config_round_trips_through_toml() {
        let c = resolve(None, Overrides::default()).unwrap();
        let text = toml::to_string(&c).unwrap();
        assert_eq!(toml::from_str::<RunConfig>(&text).unwrap(), c);
    }
}
