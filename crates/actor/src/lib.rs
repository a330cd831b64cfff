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
//!
//! The actor depends on the wire contract (`hac-proto`) and the link traits (`hac-transport`),
//! not on the learner: the embedded run (learner and actor in one process) is
//! `hac_serve::train_embedded`.

mod actor;
mod adder;
mod policy;

pub use actor::{ActorError, ActorOptions, ActorSummary, EvaluationEvent, TrainerState, run_actor};
pub use adder::Adder;
pub use policy::{SnapshotPolicy, UnusableWeights, best_policy};
