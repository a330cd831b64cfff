//! What the learner daemon writes: a run directory in `hac train`'s layout
//! ([`hac_run::run_dir::RunDir`]): `config.toml` at start, `curve.csv` and `curve.svg` as
//! evaluations arrive, `weights/best/` whenever a round beats the best, `weights/` and
//! `summary.json` at the end. The summary adds the learner's
//! ingest counts to the usual headline figures:
//!
//! - `episodes_ingested`: training episodes ingested (all actors; may exceed the budget by a few);
//!   `env_steps_ingested`: the primitive actions their summaries reported;
//! - `messages`: ingest messages that reached the learner core, valid or not: `messages = batches
//!   + episodes_ingested + duplicates + rejected`, counting the rejections other than
//!   `malformed`, `oversized` and `unauthenticated` (those the transport refuses first);
//! - `batches`, `transitions`: stored; `transitions_in_replay`: the replay tables' insert counters
//!   (equal to `transitions`, unless the run resumed from a checkpoint without its replay: then
//!   they count from the resume); `duplicates`: resends of stored messages, acknowledged and
//!   dropped;
//! - `levels`: per level, level 0 first, its `updates` and the `transitions` stored in its
//!   replay;
//! - `weights_version`, and `rejected`: refused inputs by reason (only reasons that occurred);
//! - `episode_turns`: `episodes_in_flight` (0: no turns), turns `granted` and `expired`.

use anyhow::Result;
use hac_agent::RoundReport;
use hac_learner::{BestWeights, FinishedRun};
use hac_run::run_dir::{RunDir, Summary};
use serde_json::{Map, Value, json};

/// Appends the points of `curve` not recorded yet, and writes `weights/best/` when a round beat
/// the best.
pub fn record_new(
    dir: &mut RunDir,
    curve: &[RoundReport],
    best: Option<&BestWeights>,
) -> Result<()> {
    if let Some(best) = best {
        dir.save_best(best)?;
    }
    for report in curve.get(dir.rounds()..).unwrap_or_default() {
        dir.record(report)?;
        tracing::info!(
            round = report.round,
            episodes = report.episodes,
            env_steps = report.env_steps,
            success = report.success_rate,
            "evaluation"
        );
    }
    Ok(())
}

/// Saves the weights and the summary with the learner's counts.
pub fn finish(dir: &RunDir, run: &FinishedRun, wall_time_s: f64) -> Result<Summary> {
    let status = &run.status;
    let rejected: Map<String, Value> = status
        .rejected
        .iter()
        .filter(|&&(_, n)| n > 0)
        .map(|&(reason, n)| (reason.name().to_string(), n.into()))
        .collect();
    let extra = json!({
        "episodes_ingested": status.episodes,
        "env_steps_ingested": status.env_steps,
        "messages": status.messages,
        "batches": status.batches,
        "transitions": status.transitions,
        "transitions_in_replay": status.levels.iter().map(|l| l.transitions_inserted).sum::<u64>(),
        "duplicates": status.duplicates,
        "levels": status
            .levels
            .iter()
            .map(|l| json!({"updates": l.updates, "transitions": l.transitions_inserted}))
            .collect::<Vec<_>>(),
        "weights_version": status.weights_version,
        "rejected": rejected,
        "episode_turns": {
            "episodes_in_flight": status.turns.limit,
            "granted": status.turns.granted,
            "expired": status.turns.expired,
        },
    });
    let Value::Object(extra) = extra else {
        unreachable!("a JSON object literal")
    };
    dir.finish_with(&run.agent, &run.curve, wall_time_s, extra)
}
