//! The HAC actor: the behaviour policy's rollouts, streamed to the learner.
//!
//! - [`run_actor`]: registers through an [`ActorLink`](hac_transport::ActorLink), takes the
//!   run's config from the learner, rolls out training episodes (trainers) or greedy test
//!   episodes (evaluators), and applies new weights between episodes. A trainer gets them from
//!   one weights gate, which respects the staleness bound (or, with `lockstep`, waits for the
//!   updates its own episodes earned; or, when the learner schedules episode turns, waits for
//!   its turn and plays with the weights it names).
//! - [`Adder`]: packs transitions into per-level batches.
//! - [`SnapshotPolicy`]: a published weights version as the rollout's policy.
//! - [`train_embedded`]: learner + one actor in one process over the in-process transport: the
//!   `hac train` default.

mod actor;
mod adder;
mod embedded;
mod policy;

pub use actor::{ActorError, ActorOptions, ActorSummary, EvaluationEvent, run_actor};
pub use adder::Adder;
pub use embedded::{EmbeddedError, EmbeddedRun, train_embedded};
pub use policy::{SnapshotPolicy, UnusableWeights, best_policy};
