//! The learner's side of every transport: what serves a [`Learner`](hac_learner::Learner) to
//! actors. Actor binaries do not link this crate (nor the learner); they reach the learner
//! through the [`ActorLink`](hac_transport::ActorLink) implementations of `hac-transport`.
//!
//! - [`grpc`]: the `hac.v1.Learner` service over a learner ([`grpc::LearnerGrpc`]) and the server
//!   that runs it with status, health and reflection ([`grpc::serve`]).
//! - [`shm`]: the learner's shared-memory server ([`shm::ShmServer`]), beside gRPC.
//! - [`InProcess`]: an [`ActorLink`](hac_transport::ActorLink) of direct calls into a learner in
//!   the same process. Nothing is lost in transit, so every message is acknowledged as it is
//!   stored.
//! - [`metrics`]: the learner's Prometheus metrics.
//! - [`train_embedded`]: learner + one actor in one process over [`InProcess`]: the `hac train`
//!   default.

mod embedded;
pub mod grpc;
mod in_process;
pub mod metrics;
pub mod shm;

pub use embedded::{
    EmbeddedError, EmbeddedRun, SavedRun, train_embedded, train_embedded_from, train_embedded_with,
};
pub use in_process::InProcess;
