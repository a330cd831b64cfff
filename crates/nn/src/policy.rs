//! [`ExportedPolicy`]: the greedy policy of every level in one self-contained safetensors file, for
//! use outside this project (`hac export`).
//!
//! Tensors, all `f32`: for each level `i` (0 acts in the environment, the top level proposes
//! subgoals for the end goal), `level{i}.layers.{l}.weight` (`[out, in]`, row-major) and
//! `level{i}.layers.{l}.bias` (`[out]`) for every layer `l`, then `level{i}.output_scale` and
//! `level{i}.output_offset` (`[action_dim]`). Level `i` computes, for `x = [state, goal]`:
//! `h = relu(W_l h + b_l)` through the hidden layers, `y = W_L h + b_L` at the last, and
//! `action = tanh(y) * output_scale + output_offset` (within the level's action bounds).
//!
//! Metadata, one plain safetensors entry per key (every value a string): `format` =
//! `hac/policy`, `format_version`, `levels`, `level{i}.state_dim`, `level{i}.goal_dim`,
//! `level{i}.saturating_tanh = true` when that level's `tanh` is exactly `+-1` from `|y| >=
//! 7.9073896` on (see [`ActorNet::with_saturating_tanh`]), and whatever the caller adds (`hac export` adds the environment, bounds, thresholds and the
//! weights version; see docs/CHECKPOINTS.md).

use std::collections::BTreeMap;

use crate::checkpoint::{TensorReader, TensorWriter};
use crate::{ActorNet, NnError};

/// Value of the `format` metadata entry.
const FORMAT: &str = "hac/policy";
/// Value of the `format_version` metadata entry; bumped when the layout changes.
pub const POLICY_FORMAT_VERSION: u32 = 1;

/// Every level's actor, level 0 first, with descriptive metadata.
#[derive(Debug, Clone)]
pub struct ExportedPolicy {
    /// The actors, level 0 first.
    pub actors: Vec<ActorNet>,
    /// Extra metadata (keys other than the ones this module writes itself).
    pub metadata: BTreeMap<String, String>,
}

impl ExportedPolicy {
    /// The policy file (layout in the module docs).
    pub fn to_safetensors(&self) -> Vec<u8> {
        let mut out = TensorWriter::default();
        for (key, value) in &self.metadata {
            out.meta(key.clone(), value);
        }
        out.meta("format".into(), FORMAT);
        out.meta("format_version".into(), POLICY_FORMAT_VERSION);
        out.meta("levels".into(), self.actors.len());
        for (level, actor) in self.actors.iter().enumerate() {
            actor.write(&format!("level{level}."), &mut out);
        }
        out.finish_plain()
    }

    /// Reads a policy file; `metadata` holds every entry, including `format` and `levels`.
    pub fn from_safetensors(bytes: &[u8]) -> Result<Self, NnError> {
        let file = TensorReader::new(bytes)?;
        file.expect_format(FORMAT)?;
        let version: u32 = file.meta("format_version")?;
        if version != POLICY_FORMAT_VERSION {
            return Err(NnError::Metadata {
                key: "format_version".into(),
                reason: format!("expected {POLICY_FORMAT_VERSION}, got {version}"),
            });
        }
        let levels: usize = file.meta("levels")?;
        let actors = (0..levels)
            .map(|level| ActorNet::read(&format!("level{level}."), &file))
            .collect::<Result<_, _>>()?;
        Ok(Self {
            actors,
            metadata: file.metadata().clone(),
        })
    }
}

#[cfg(test)]
mod tests {
    use hac_core::{Bounds, LevelDims, Rng};

    use super::*;

    #[test]
    fn a_policy_file_round_trips_and_acts_the_same() {
        let mut rng = Rng::seed_from(5);
        let low = ActorNet::new(
            LevelDims {
                state: 3,
                goal: 2,
                action: 1,
            },
            &Bounds::symmetric(&[2.0]),
            &[8, 8],
            &mut rng,
        );
        let high = ActorNet::new(
            LevelDims {
                state: 3,
                goal: 1,
                action: 2,
            },
            &Bounds::new(vec![-1.0, 0.0], vec![1.0, 4.0]),
            &[8],
            &mut rng,
        );
        let policy = ExportedPolicy {
            actors: vec![low, high],
            metadata: BTreeMap::from([("env".to_string(), "test".to_string())]),
        };
        let bytes = policy.to_safetensors();
        // Plain metadata entries, readable by any safetensors reader.
        let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
        let plain = header.metadata().clone().unwrap();
        assert_eq!(plain["format"], "hac/policy");
        assert_eq!(plain["levels"], "2");
        assert_eq!(plain["env"], "test");
        assert_eq!(plain["level1.goal_dim"], "1");

        let mut back = ExportedPolicy::from_safetensors(&bytes).unwrap();
        assert_eq!(back.actors.len(), 2);
        assert_eq!(back.metadata["env"], "test");
        for (level, (a, b)) in policy.actors.iter().zip(&mut back.actors).enumerate() {
            let mut a = a.clone();
            let d = a.dims();
            let state: Vec<f32> = (0..d.state).map(|_| rng.uniform(-1.0, 1.0)).collect();
            let goal: Vec<f32> = (0..d.goal).map(|_| rng.uniform(-1.0, 1.0)).collect();
            let (mut x, mut y) = (vec![0.0; d.action], vec![0.0; d.action]);
            a.act(&state, &goal, &mut x);
            b.act(&state, &goal, &mut y);
            assert_eq!(x, y, "level {level}");
        }
        let e = ExportedPolicy::from_safetensors(&policy.actors[0].to_safetensors()).unwrap_err();
        assert!(e.to_string().contains("format"), "{e}");
    }
}
