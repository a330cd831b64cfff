//! HAC networks: the actor and critic of every level, how they learn, and how they are saved.
//!
//! - [`mlp`]: [`Mlp`], a dense ReLU network evaluated and differentiated on whole batches (one
//!   matrix product per layer and pass), with its reusable [`MlpWorkspace`] and [`MlpGrads`].
//! - [`adam`]: the [`Adam`] optimiser, one moment pair per parameter tensor.
//! - [`actor`]: [`ActorNet`], `pi(s, g)` squashed into the level's bounds; cheap single-sample
//!   [`ActorNet::act`] for rollouts, safetensors round trip for shipping weights to remote actors.
//! - [`critic`]: [`CriticNet`], `Q(s, g, a)` bounded to `[-H, 0]`, initially optimistic.
//! - [`learner`]: [`LevelLearner`], one level's DDPG-style update (critic step, then actor step
//!   through the updated critic), optional target networks, whole-state checkpoints. The
//!   minibatch is cut into up to [`GRADIENT_CHUNKS`] chunks (by its size alone) whose gradients
//!   may be computed on several threads and are summed in a fixed order, so the weights do not
//!   depend on the thread count.
//! - [`td3`]: [`Td3Learner`], TD3's twin-critic update (HIRO's learner at both levels), with
//!   whole-state checkpoints and undoing of diverged updates.
//! - [`hiro`]: [`BatchedCorrection`], HIRO's off-policy correction of a minibatch of high-level
//!   transitions with the low-level actor evaluated in batched forward passes.
//! - [`policy`]: [`ExportedPolicy`], every level's actor in one self-contained file for use
//!   elsewhere.
//! - `kernels`: the matrix products (a packing-free fused multiply-add kernel on AVX2 or
//!   AVX-512, chosen at run time; matrixmultiply's `sgemm` through nalgebra elsewhere), the
//!   thin-matrix loops, and the run-time SIMD dispatch of the elementwise loops;
//!   `checkpoint`: safetensors reading and writing.
//!
//! Matrices are column-major with one sample per column, as in [`hac_core::Batch`].

#![warn(missing_docs)]

pub mod actor;
pub mod adam;
mod checkpoint;
pub mod critic;
mod error;
pub mod hiro;
mod kernels;
pub mod learner;
mod level;
pub mod mlp;
pub mod policy;
pub mod td3;
#[cfg(test)]
mod testing;

pub use actor::ActorNet;
pub use adam::Adam;
pub use critic::CriticNet;
pub use error::NnError;
pub use hiro::BatchedCorrection;
pub use kernels::{hidden_layer_sgemm_gflops, simd_extension};
pub use learner::{
    Diverged, GRADIENT_CHUNKS, LearnerBackup, LearnerConfig, LevelLearner, MIN_CHUNK_SAMPLES,
    PARAMETER_LIMIT, UpdateStats, UpdateTiming,
};
pub use level::LevelModel;
pub use mlp::{Mlp, MlpGrads, MlpWorkspace};
pub use policy::ExportedPolicy;
pub use td3::{Td3Config, Td3Learner};
