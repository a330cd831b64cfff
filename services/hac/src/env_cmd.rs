//! `hac env`: list the built-in environments, describe one, and step one by hand.

use std::io::{BufRead, Read as _, Write};

use anyhow::{Context, Result, bail};
use hac_core::{Env, Rng};
use serde_json::json;

use crate::registry;

/// The longest line `hac env rollout` reads from stdin, in bytes.
const MAX_LINE: usize = 1 << 20;

/// `hac env list`: one line per environment.
pub fn list() -> Result<()> {
    for name in registry::names() {
        let env = registry::make(name)?;
        outln!("{name:<14} {}", env.spec().description);
    }
    Ok(())
}

/// `hac env describe NAME`: spaces, bounds, thresholds and defaults per level count, for the
/// environment's own episode budget or `max_actions`.
pub fn describe(name: &str, json_out: bool, max_actions: Option<usize>) -> Result<()> {
    let mut env = registry::make(name)?;
    if let Some(n) = max_actions {
        hac_agent::set_checked_budget(env.as_mut(), n)
            .map_err(|message| anyhow::anyhow!("invalid value for `--max-actions`: {message}"))?;
    }
    let spec = env.spec();
    let defaults: Vec<_> = (1..=3).map(|k| env.default_config(k)).collect();
    let tabular = registry::is_tabular(name).then(hac_tabular::TabularConfig::default);
    if json_out {
        let mut description = json!({"spec": spec, "defaults": defaults});
        if let Some(t) = &tabular {
            description["tabular"] = serde_json::to_value(t)?;
        }
        outln!("{}", serde_json::to_string_pretty(&description)?);
        return Ok(());
    }
    let fmt = |v: &[f32]| {
        v.iter()
            .map(|x| format!("{x:.4}"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    outln!("{} — {}", spec.name, spec.description);
    outln!("  state dimension           {}", spec.state_dim);
    outln!(
        "  primitive action bounds   low [{}]  high [{}]",
        fmt(&spec.action_bounds.low),
        fmt(&spec.action_bounds.high)
    );
    outln!("  end goal dimension        {}", spec.end_goal_dim);
    outln!(
        "  end-goal thresholds       [{}]",
        fmt(&spec.end_goal_thresholds)
    );
    outln!(
        "  subgoal bounds            low [{}]  high [{}]",
        fmt(&spec.subgoal_bounds.low),
        fmt(&spec.subgoal_bounds.high)
    );
    outln!(
        "  subgoal thresholds        [{}]",
        fmt(&spec.subgoal_thresholds)
    );
    let angle_dims = |flags: &[bool]| {
        let dims: Vec<String> = (0..flags.len())
            .filter(|&d| flags[d])
            .map(|d| d.to_string())
            .collect();
        dims.join(", ")
    };
    if spec.end_goal_angles.contains(&true) || spec.subgoal_angles.contains(&true) {
        outln!(
            "  angle dims (circular)     end goal [{}]  subgoal [{}]",
            angle_dims(&spec.end_goal_angles),
            angle_dims(&spec.subgoal_angles)
        );
    }
    // The boxes the learner admits transitions by (each widened by 10% of its width).
    for (label, bounds) in [
        ("state box (admission)    ", &spec.state_bounds),
        ("end-goal box (admission) ", &spec.end_goal_bounds),
        ("achieved subgoal box     ", &spec.achieved_subgoal_bounds),
    ] {
        if !bounds.is_empty() {
            outln!(
                "  {label} low [{}]  high [{}]",
                fmt(&bounds.low),
                fmt(&bounds.high)
            );
        }
    }
    outln!(
        "  max primitive actions     {}{}",
        spec.max_actions,
        if max_actions.is_some() {
            " (as given; runs set it with --max-actions)"
        } else {
            " (a run's --max-actions / max_actions replaces it)"
        }
    );
    outln!(
        "  physics steps per action  {}",
        spec.physics_steps_per_action
    );
    outln!("  defaults per number of levels:");
    outln!(
        "    levels  H     lambda  noise (action / subgoal)              gamma  batch  updates/ep  hidden"
    );
    for c in &defaults {
        outln!(
            "    {:<7} {:<5} {:<7} {:<37} {:<6} {:<6} {:<11} {:?}",
            c.levels,
            c.horizon,
            c.subgoal_test_prob,
            format!("{} / {}", noise(&c.action_noise), noise(&c.subgoal_noise)),
            c.gamma,
            c.batch_size,
            c.updates_per_episode,
            c.hidden_layers
        );
    }
    if let Some(t) = &tabular {
        outln!(
            "  learner: tabular Q-learning (the network keys above are unused); [tabular] defaults: \
             learning_rate {}, initial_q {}, max_table_entries {}, replay_updates {}, \
             replay_capacity {}, all_goals {}, all_segments {}",
            t.learning_rate,
            serde_json::to_string(&t.initial_q)?,
            t.max_table_entries,
            t.replay_updates,
            t.replay_capacity,
            t.all_goals,
            t.all_segments
        );
    }
    outln!(
        "  (all keys: hac train --print-config --env {} --levels K)",
        spec.name
    );
    Ok(())
}

fn noise(n: &hac_core::Noise) -> String {
    match n {
        hac_core::Noise::Relative(f) => format!("{f} x half range"),
        hac_core::Noise::Absolute(v) => format!("std {v:?}"),
    }
}

/// `hac env rollout`: reset (or set the physical state), then apply one JSON action per stdin
/// line, printing one JSON object per state. Actions are clipped to the action bounds, as the
/// agent's are. The first bad line ends the command with an error naming the line.
pub fn rollout(name: &str, seed: u64, state: Option<&str>) -> Result<()> {
    let mut env = registry::make(name)?;
    let mut rng = Rng::seed_from(seed);
    env.reset(&mut rng);
    if let Some(text) = state {
        let values: Vec<f64> = serde_json::from_str(text)
            .with_context(|| format!("--state must be a JSON array of numbers, got `{text}`"))?;
        env.set_physical_state(&values)?;
    }
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    emit(&mut out, 0, env.as_ref())?;
    let action_dim = env.spec().action_dim();
    let mut action = vec![0.0f32; action_dim];
    let mut stdin = std::io::stdin().lock();
    let mut line = String::new();
    for i in 0.. {
        line.clear();
        // At most MAX_LINE bytes per line: input without line breaks is refused, not buffered
        // until memory runs out.
        let read = (&mut stdin)
            .take(MAX_LINE as u64 + 1)
            .read_line(&mut line)
            .context("reading stdin")?;
        if read == 0 {
            break;
        }
        if line.len() > MAX_LINE {
            bail!(
                "line {}: longer than {MAX_LINE} bytes; an action is one JSON array of \
                 {action_dim} numbers per line",
                i + 1
            );
        }
        let line = line.trim_end_matches(['\n', '\r']);
        if line.trim().is_empty() {
            continue;
        }
        let values: Vec<f64> = serde_json::from_str(line).with_context(|| {
            format!(
                "line {}: an action must be a JSON array of {action_dim} numbers, got `{line}`",
                i + 1
            )
        })?;
        if values.len() != action_dim {
            bail!(
                "line {}: {name} actions have {action_dim} values, got {}",
                i + 1,
                values.len()
            );
        }
        for (a, v) in action.iter_mut().zip(&values) {
            *a = *v as f32;
        }
        env.spec().action_bounds.clip(&mut action);
        env.step(&action);
        emit(&mut out, i + 1, env.as_ref())?;
    }
    Ok(())
}

fn emit(out: &mut impl Write, step: usize, env: &dyn Env) -> Result<()> {
    // Written by hand so the keys keep the documented order: step, state[, terminated].
    let state = serde_json::to_string(env.state())?;
    let terminated = if env.terminated() {
        ",\"terminated\":true"
    } else {
        ""
    };
    writeln!(out, "{{\"step\":{step},\"state\":{state}{terminated}}}")?;
    out.flush()?;
    Ok(())
}
