//! `hac export`: a trained run's greedy policy as one self-contained safetensors file
//! ([`hac_nn::ExportedPolicy`]; layout and metadata in docs/CHECKPOINTS.md).
//!
//! The policy comes from the run's newest valid checkpoint (`<run>/checkpoints/`, written by the
//! learner daemon; a finished run's last checkpoint holds its final weights), or `--checkpoint
//! NAME`, or else `weights/` (what `hac train` writes). Neural runs only: a grid world's policy is
//! its Q tables, already self-contained in `weights/level<i>.safetensors`. With `--best`, the
//! policy of the run's best test round (`weights/best/`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use hac_actor::SnapshotPolicy;
use hac_agent::{Agent, RunConfig};
use hac_core::EnvSpec;
use hac_learner::LearnerCheckpoint;
use hac_nn::{ActorNet, ExportedPolicy};
use hac_run::checkpoints::CheckpointStore;
use hac_run::run_dir;

#[derive(Debug, clap::Args)]
pub struct ExportArgs {
    /// A run directory (of `hac train` or `hac learner`).
    #[arg(long)]
    pub run: PathBuf,
    /// The policy file to write (safetensors).
    #[arg(long)]
    pub out: PathBuf,
    /// Export this checkpoint of the run (e.g. ckpt-000004) [default: the newest valid one, or
    /// weights/ if the run has none].
    #[arg(long, value_name = "NAME", conflicts_with = "best")]
    pub checkpoint: Option<String>,
    /// Export the weights of the run's best test round (`weights/best/`) instead of its last.
    #[arg(long)]
    pub best: bool,
}

/// Where the policy came from.
struct Source {
    run: RunConfig,
    actors: Vec<ActorNet>,
    /// Updates behind each level's actor, where known (not for the best weights).
    updates: Option<Vec<u64>>,
    weights_version: Option<u64>,
    description: String,
}

impl Source {
    fn of_agent(
        run: RunConfig,
        agent: &Agent,
        weights_version: Option<u64>,
        description: String,
    ) -> Self {
        Self {
            run,
            actors: agent.levels().iter().map(|l| l.actor().clone()).collect(),
            updates: Some(agent.levels().iter().map(|l| l.updates()).collect()),
            weights_version,
            description,
        }
    }
}

pub fn run(args: &ExportArgs) -> Result<()> {
    let source = load(args)?;
    let policy = policy(&source)?;
    run_dir::write_file(&args.out, &policy.to_safetensors())?;
    outln!(
        "exported the {}-level {} policy from {} to {}",
        source.run.levels,
        source.run.env,
        source.description,
        args.out.display()
    );
    Ok(())
}

fn load(args: &ExportArgs) -> Result<Source> {
    if args.best {
        return load_best(args);
    }
    let store = CheckpointStore::of_run(&args.run);
    let from_checkpoint = |name: String, checkpoint: LearnerCheckpoint| -> Result<Source> {
        Ok(Source::of_agent(
            checkpoint.run_config()?,
            &checkpoint.agent()?,
            Some(checkpoint.weights_version()),
            format!("checkpoint {name}"),
        ))
    };
    if let Some(name) = &args.checkpoint {
        let files = store
            .read(name)
            .map_err(|e| anyhow::anyhow!("checkpoint {name} is corrupt: {e}"))?;
        let checkpoint = LearnerCheckpoint::from_files(&files)?;
        return from_checkpoint(name.clone(), checkpoint);
    }
    if let Some(loaded) = store.load_newest(LearnerCheckpoint::from_files)? {
        for line in loaded.skipped_lines() {
            eprintln!("warning: {line}");
        }
        return from_checkpoint(loaded.name, loaded.value);
    }
    let run = neural_run(args)?;
    let env = run.make_env()?;
    let agent = Agent::load(&run_dir::weights_dir(&args.run), env.spec(), &run)
        .context("loading the run's weights")?;
    // The learner daemon records the final version in the summary; `hac train` has none.
    let weights_version = std::fs::read_to_string(args.run.join("summary.json"))
        .ok()
        .and_then(|text| serde_json::from_str::<serde_json::Value>(&text).ok())
        .and_then(|summary| summary["weights_version"].as_u64());
    Ok(Source::of_agent(
        run,
        &agent,
        weights_version,
        "weights/".into(),
    ))
}

/// The policy of the run's best test round.
fn load_best(args: &ExportArgs) -> Result<Source> {
    let run = neural_run(args)?;
    let env = run.make_env()?;
    let (record, policy) = best_policy(&args.run, &run, env.spec())?;
    Ok(Source {
        run,
        actors: policy.into_actors(),
        updates: None,
        weights_version: Some(record.weights_version),
        description: format!(
            "weights/best/ (round {}, {} episodes, {:.1}% success)",
            record.round,
            record.episodes,
            100.0 * record.success_rate
        ),
    })
}

/// The greedy policy in `weights/best/` of the run in `run_path` (`hac export --best`, `hac eval
/// --best`), checked against the run's spec and level count, with its record.
pub fn best_policy(
    run_path: &Path,
    run: &RunConfig,
    spec: &EnvSpec,
) -> Result<(run_dir::BestRecord, SnapshotPolicy)> {
    let (record, levels) = run_dir::load_best(run_path)?;
    let policy = hac_actor::best_policy(levels, record.weights_version, spec, run.levels)
        .with_context(|| format!("loading {}", run_dir::best_dir(run_path).display()))?;
    Ok((record, policy))
}

/// The run's config, refused for a grid world.
fn neural_run(args: &ExportArgs) -> Result<RunConfig> {
    let run = RunConfig::load_run(&args.run)?;
    if run.is_tabular() {
        bail!(
            "`{}` is a grid world learned by tabular HAC: its policy is its Q tables, already \
             self-contained in {}/level<i>.safetensors; export writes neural policies",
            run.env,
            run_dir::weights_dir(&args.run).display()
        );
    }
    Ok(run)
}

/// The policy file's contents: every level's actor and the metadata to run it elsewhere.
fn policy(source: &Source) -> Result<ExportedPolicy> {
    let run = &source.run;
    let env = run.make_env()?;
    let spec = env.spec();
    let list = |values: &[f32]| {
        values
            .iter()
            .map(f32::to_string)
            .collect::<Vec<_>>()
            .join(",")
    };
    let mut meta = BTreeMap::new();
    let mut put = |key: &str, value: String| {
        meta.insert(key.to_string(), value);
    };
    put("env", run.env.clone());
    put("algo", run.algo.name().into());
    put("seed", run.seed.to_string());
    put("source", source.description.clone());
    if let Some(version) = source.weights_version {
        put("weights_version", version.to_string());
    }
    put("state_dim", spec.state_dim.to_string());
    put("action_dim", spec.action_dim().to_string());
    put("action_low", list(&spec.action_bounds.low));
    put("action_high", list(&spec.action_bounds.high));
    put("end_goal_dim", spec.end_goal_dim.to_string());
    put("end_goal_thresholds", list(&spec.end_goal_thresholds));
    put("subgoal_dim", spec.subgoal_dim().to_string());
    put("subgoal_low", list(&spec.subgoal_bounds.low));
    put("subgoal_high", list(&spec.subgoal_bounds.high));
    put("subgoal_thresholds", list(&spec.subgoal_thresholds));
    // HIRO's high level proposes a goal relative to the projected state every c steps; HAC's
    // levels get H attempts each.
    let relative_goals = run.hiro().map(|h| {
        put("hiro.c", h.c.to_string());
        let r = hac_core::hiro::goal_radius(spec);
        let low: Vec<f32> = r.iter().map(|r| -r).collect();
        (low, r)
    });
    if relative_goals.is_none() {
        put("horizon", run.agent.horizon.to_string());
    }
    put("max_actions", spec.max_actions.to_string());
    put("activation", "relu".into());
    put("output", "tanh(y) * output_scale + output_offset".into());
    for (level, actor) in source.actors.iter().enumerate() {
        let dims = actor.dims();
        let (low, high) = match &relative_goals {
            Some((low, high)) if level > 0 => (low.as_slice(), high.as_slice()),
            _ => {
                let bounds = spec.level_action_bounds(level);
                (bounds.low.as_slice(), bounds.high.as_slice())
            }
        };
        put(&format!("level{level}.action_dim"), dims.action.to_string());
        put(&format!("level{level}.action_low"), list(low));
        put(&format!("level{level}.action_high"), list(high));
        if let Some(updates) = &source.updates {
            put(&format!("level{level}.updates"), updates[level].to_string());
        }
    }
    Ok(ExportedPolicy {
        actors: source.actors.clone(),
        metadata: meta,
    })
}
