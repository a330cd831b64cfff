//! Runs one HAC level's learner ([`LevelLearner`]) from given initial weights through given
//! minibatches and records where it goes. `reference_update_check.py`, beside this file, uses it
//! to compare the learner's update with the HAC paper's reference TensorFlow code on identical
//! inputs.
//!
//! ```sh
//! cargo run --release -p hac-nn --example update_trace -- INPUT OUTPUT
//! ```
//!
//! INPUT is a safetensors file of `f32` tensors:
//! - the initial weights, `actor.{l}.weight` and `critic.{l}.weight` (`[out, in]`, row-major, as
//!   in the learner's own files), and `actor.{l}.bias` and `critic.{l}.bias` (`[out]`);
//! - `output_scale` and `output_offset` (`[action]`): the actor's half range and centre;
//! - K minibatches of N samples each: `states` and `next_states` (`[K, N, state]`), `goals`
//!   (`[K, N, goal]`), `actions` (`[K, N, action]`), `rewards` and `terminals` (`[K, N]`,
//!   terminals 1 or 0);
//! - metadata `horizon` (H), `gamma`, and `checkpoints`: update counts, comma-separated, each at
//!   most K.
//!
//! The learner has the reference's settings ([`AgentConfig::reference`]: hidden layers 3 x 64,
//! Adam at 1e-3 for both networks, no target networks, the reference's critic slope) for a level
//! of the widths the tensors give, with the given H and gamma. It starts from the given weights
//! with fresh optimisers and updates on one thread, once per minibatch, in order.
//!
//! OUTPUT is a safetensors file holding, for each checkpoint `n`, the learner's whole state after
//! `n` updates as [`LevelLearner::to_safetensors`] writes it, every tensor's name prefixed by
//! `after{n}.` (weights `after{n}.actor.layers.{l}.weight`, Adam moments
//! `after{n}.actor_adam.m.{i}`, and so on), and the [`hac_nn::UpdateStats`] of every update:
//! `critic_loss`, `actor_loss`, `mean_q` and `mean_target` (`[K]`).

use std::collections::HashMap;
use std::error::Error;
use std::str::FromStr;

use hac_core::{AgentConfig, Batch, Bounds, LevelDims, Rng};
use hac_nn::{LearnerConfig, LevelLearner};
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};

type Result<T> = std::result::Result<T, Box<dyn Error>>;

/// An `f32` tensor read from a safetensors file.
struct Tensor {
    shape: Vec<usize>,
    values: Vec<f32>,
}

/// Tensor `name` of `file`, which must be `f32`.
fn read(file: &SafeTensors<'_>, name: &str) -> Result<Tensor> {
    let t = file.tensor(name).map_err(|e| format!("`{name}`: {e}"))?;
    if t.dtype() != Dtype::F32 {
        return Err(format!("`{name}` is {:?}, not F32", t.dtype()).into());
    }
    let values = t
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    Ok(Tensor {
        shape: t.shape().to_vec(),
        values,
    })
}

/// A minibatch field `[K, N, width]` (or `[K, N]` for width 1) and its width, checked to hold K
/// minibatches of N samples.
fn read_field(file: &SafeTensors<'_>, name: &str, k: usize, n: usize) -> Result<(Tensor, usize)> {
    let t = read(file, name)?;
    let width = match t.shape[..] {
        [a, b] if (a, b) == (k, n) => 1,
        [a, b, w] if (a, b) == (k, n) => w,
        _ => return Err(format!("`{name}` has shape {:?}, not [{k}, {n}, _]", t.shape).into()),
    };
    Ok((t, width))
}

/// Metadata entry `key`, parsed.
fn meta<T: FromStr>(metadata: &HashMap<String, String>, key: &str) -> Result<T> {
    let value = metadata
        .get(key)
        .ok_or_else(|| format!("metadata `{key}` missing"))?;
    value
        .parse()
        .map_err(|_| format!("metadata `{key}`: cannot parse `{value}`").into())
}

/// Named tensors as `(name, shape, little-endian f32 bytes)`, serialised with `metadata`.
fn serialize(
    tensors: &[(String, Vec<usize>, Vec<u8>)],
    metadata: Option<HashMap<String, String>>,
) -> Result<Vec<u8>> {
    let views = tensors
        .iter()
        .map(|(name, shape, bytes)| {
            Ok((
                name.as_str(),
                TensorView::new(Dtype::F32, shape.clone(), bytes)?,
            ))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(safetensors::serialize(views, metadata)?)
}

fn le_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// A learner for `config` with fresh optimisers and the weights of `input`: a new learner's file
/// with its network tensors (`actor.layers.{l}.*`, `critic.layers.{l}.*`) replaced by the input's
/// (`actor.{l}.*`, `critic.{l}.*`, of the same shapes), read back.
fn with_weights(config: &LearnerConfig, input: &SafeTensors<'_>) -> Result<LevelLearner> {
    let fresh = LevelLearner::new(config.clone(), &mut Rng::seed_from(0)).to_safetensors();
    let file = SafeTensors::deserialize(&fresh)?;
    let mut tensors = Vec::new();
    let mut replaced = 0;
    for (name, view) in file.tensors() {
        let bytes = match name.split_once(".layers.") {
            Some((net @ ("actor" | "critic"), rest)) => {
                let given = read(input, &format!("{net}.{rest}"))?;
                if given.shape != view.shape() {
                    return Err(format!(
                        "`{net}.{rest}` has shape {:?}, the learner's {:?}",
                        given.shape,
                        view.shape()
                    )
                    .into());
                }
                replaced += 1;
                le_bytes(&given.values)
            }
            _ => view.data().to_vec(),
        };
        tensors.push((name, view.shape().to_vec(), bytes));
    }
    let given = input
        .names()
        .into_iter()
        .filter(|n| n.starts_with("actor.") || n.starts_with("critic."))
        .count();
    if given != replaced {
        return Err(
            format!("the input has {given} network tensors, the learner {replaced}").into(),
        );
    }
    let (_, header) = SafeTensors::read_metadata(&fresh)?;
    let bytes = serialize(&tensors, header.metadata().clone())?;
    Ok(LevelLearner::from_safetensors(config.clone(), &bytes)?)
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, output] = &args[..] else {
        return Err("usage: update_trace INPUT OUTPUT".into());
    };
    let bytes = std::fs::read(input).map_err(|e| format!("{input}: {e}"))?;
    let file = SafeTensors::deserialize(&bytes)?;
    let (_, header) = SafeTensors::read_metadata(&bytes)?;
    let metadata = header.metadata().clone().unwrap_or_default();
    let horizon: f32 = meta(&metadata, "horizon")?;
    let gamma: f32 = meta(&metadata, "gamma")?;
    let checkpoints = meta::<String>(&metadata, "checkpoints")?
        .split(',')
        .map(|c| c.trim().parse::<usize>())
        .collect::<std::result::Result<Vec<_>, _>>()?;

    let rewards = read(&file, "rewards")?;
    let [k, n] = rewards.shape[..] else {
        return Err(format!("`rewards` has shape {:?}, not [K, N]", rewards.shape).into());
    };
    if let Some(c) = checkpoints.iter().find(|&&c| c == 0 || c > k) {
        return Err(format!("checkpoint {c} outside 1..={k}").into());
    }
    let (states, state) = read_field(&file, "states", k, n)?;
    let (next_states, next_state) = read_field(&file, "next_states", k, n)?;
    let (goals, goal) = read_field(&file, "goals", k, n)?;
    let (actions, action) = read_field(&file, "actions", k, n)?;
    let (terminals, terminal) = read_field(&file, "terminals", k, n)?;
    if (next_state, terminal) != (state, 1) {
        return Err("`next_states` must be as wide as `states`, `terminals` be [K, N]".into());
    }
    let dims = LevelDims {
        state,
        goal,
        action,
    };

    let scale = read(&file, "output_scale")?.values;
    let offset = read(&file, "output_offset")?.values;
    let bounds = Bounds::new(
        offset.iter().zip(&scale).map(|(c, s)| c - s).collect(),
        offset.iter().zip(&scale).map(|(c, s)| c + s).collect(),
    );
    // The reference's per-level settings, which do not depend on the level count or H.
    let reference = AgentConfig::reference(1, 1);
    let config = LearnerConfig {
        dims,
        action_bounds: bounds,
        horizon,
        gamma,
        hidden: reference.hidden_layers,
        actor_lr: reference.actor_lr,
        critic_lr: reference.critic_lr,
        target_tau: reference.target_tau,
        actor_preactivation_l2: reference.actor_preactivation_l2,
        exact_critic_slope: reference.exact_critic_slope,
        saturating_tanh: reference.saturating_tanh,
    };
    let mut learner = with_weights(&config, &file)?;
    let actor = learner.actor();
    if actor.output_scale() != scale || actor.output_offset() != offset {
        return Err(format!(
            "the bounds give the actor scale {:?} and offset {:?}, not the input's {scale:?} and \
             {offset:?}",
            actor.output_scale(),
            actor.output_offset()
        )
        .into());
    }
    learner.set_threads(1);

    let mut batch = Batch::zeros(dims, n);
    let mut stats = [const { Vec::new() }; 4];
    let mut out = Vec::new();
    for u in 0..k {
        let part = |t: &Tensor, width: usize| t.values[u * n * width..(u + 1) * n * width].to_vec();
        batch.states = part(&states, state);
        batch.next_states = part(&next_states, state);
        batch.goals = part(&goals, goal);
        batch.actions = part(&actions, action);
        batch.rewards = part(&rewards, 1);
        batch.terminals = part(&terminals, 1);
        let u_stats = learner.update(&batch);
        let values = [
            u_stats.critic_loss,
            u_stats.actor_loss,
            u_stats.mean_q,
            u_stats.mean_target,
        ];
        for (list, v) in stats.iter_mut().zip(values) {
            list.push(v);
        }
        if checkpoints.contains(&(u + 1)) {
            let snapshot = learner.to_safetensors();
            for (name, view) in SafeTensors::deserialize(&snapshot)?.tensors() {
                let name = format!("after{}.{name}", u + 1);
                out.push((name, view.shape().to_vec(), view.data().to_vec()));
            }
        }
    }
    for (name, values) in ["critic_loss", "actor_loss", "mean_q", "mean_target"]
        .into_iter()
        .zip(&stats)
    {
        out.push((name.to_string(), vec![k], le_bytes(values)));
    }
    let metadata = HashMap::from([("checkpoints".to_string(), {
        let list: Vec<String> = checkpoints.iter().map(usize::to_string).collect();
        list.join(",")
    })]);
    std::fs::write(output, serialize(&out, Some(metadata))?)
        .map_err(|e| format!("{output}: {e}"))?;
    eprintln!(
        "{k} updates of {n} samples ({dims:?}, H {horizon}, gamma {gamma}); critic loss {} at the \
         first, {} at the last; wrote {output}",
        stats[0][0],
        stats[0][k - 1]
    );
    Ok(())
}
