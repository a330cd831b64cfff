//! [`SnapshotPolicy`]: the actor networks of one published weights version, as the rollout's
//! [`Policy`].

use hac_core::{EnvSpec, LevelDims, Policy};
use hac_nn::{ActorNet, NnError};
use hac_proto::WeightsSnapshot;

/// Why a weights snapshot could not be used.
#[derive(Debug, thiserror::Error)]
pub enum UnusableWeights {
    #[error("weights version {version} has {got} levels, the run has {expected}")]
    Levels {
        version: u64,
        got: usize,
        expected: usize,
    },
    #[error("weights version {version}, level {level}: {source}")]
    Decode {
        version: u64,
        level: usize,
        #[source]
        source: NnError,
    },
    #[error("weights version {version}, level {level}: a parameter is {value} (not finite)")]
    NotFinite {
        version: u64,
        level: usize,
        value: f32,
    },
    #[error(
        "weights version {version}, level {level}: network is for {got:?}, the run needs {expected:?}"
    )]
    Dims {
        version: u64,
        level: usize,
        got: LevelDims,
        expected: LevelDims,
    },
}

/// Inference-only policy: level `i`'s actor network from a [`WeightsSnapshot`].
#[derive(Debug)]
pub struct SnapshotPolicy {
    version: u64,
    actors: Vec<ActorNet>,
}

impl SnapshotPolicy {
    /// Decodes every level of `snapshot`, checking it against the run's level dimensions and
    /// that every parameter is finite.
    pub fn from_snapshot(
        snapshot: &WeightsSnapshot,
        dims: &[LevelDims],
    ) -> Result<Self, UnusableWeights> {
        let version = snapshot.version;
        if snapshot.levels.len() != dims.len() {
            return Err(UnusableWeights::Levels {
                version,
                got: snapshot.levels.len(),
                expected: dims.len(),
            });
        }
        let actors = snapshot
            .levels
            .iter()
            .zip(dims)
            .enumerate()
            .map(|(level, (bytes, &expected))| {
                let actor = ActorNet::from_safetensors(bytes).map_err(|source| {
                    UnusableWeights::Decode {
                        version,
                        level,
                        source,
                    }
                })?;
                if let Some(&value) = actor.mlp().tensors().flatten().find(|v| !v.is_finite()) {
                    return Err(UnusableWeights::NotFinite {
                        version,
                        level,
                        value,
                    });
                }
                if actor.dims() != expected {
                    return Err(UnusableWeights::Dims {
                        version,
                        level,
                        got: actor.dims(),
                        expected,
                    });
                }
                Ok(actor)
            })
            .collect::<Result<_, _>>()?;
        Ok(Self { version, actors })
    }

    pub fn version(&self) -> u64 {
        self.version
    }

    /// Every level's actor network, level 0 first.
    pub fn into_actors(self) -> Vec<ActorNet> {
        self.actors
    }
}

/// The policy in a run's `weights/best/` (each level's actor as safetensors, level 0 first),
/// checked against the run's `spec` and level count like a snapshot from the learner.
pub fn best_policy(
    levels: Vec<Vec<u8>>,
    weights_version: u64,
    spec: &EnvSpec,
    num_levels: usize,
) -> Result<SnapshotPolicy, UnusableWeights> {
    let dims: Vec<LevelDims> = (0..num_levels)
        .map(|level| spec.level_dims(level, num_levels))
        .collect();
    let snapshot = WeightsSnapshot {
        version: weights_version,
        levels,
        episodes: 0,
        run_finished: true,
        learner_start: 0,
    };
    SnapshotPolicy::from_snapshot(&snapshot, &dims)
}

impl Policy for SnapshotPolicy {
    fn act(&mut self, level: usize, state: &[f32], goal: &[f32], action: &mut [f32]) {
        self.actors[level].act(state, goal, action);
    }
}
