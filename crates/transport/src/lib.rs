//! How an actor reaches the learner: the [`ActorLink`] trait, and its implementations.
//!
//! - [`InProcess`]: direct calls into a [`Learner`] in the same process (the embedded `hac train`
//!   and tests). Nothing is lost in transit, so every message is acknowledged as it is stored.
//! - [`grpc`]: the learner service over tonic, for actors on any host: the server adapter
//!   ([`grpc::serve`], [`grpc::LearnerGrpc`]) and the actor's side ([`grpc::GrpcLink`]).
//! - [`shm`]: shared memory (iceoryx2) for actors on the learner's host, beside gRPC: the
//!   learner's [`shm::ShmServer`] and the actor's [`shm::ShmLink`] (which keeps gRPC for
//!   registration and falls back to it when shared memory is not offered).
//!
//! The actor loop (`hac-actor`) is written against the trait only, so every transport runs the
//! same actor code.

pub mod grpc;
mod in_process;
pub mod shm;

use std::time::Duration;

use hac_learner::Published;
use hac_proto::{Admission, IngestItem, Registration, WeightsSnapshot};

pub use in_process::InProcess;

/// Why a link operation failed.
#[derive(Debug, Clone, thiserror::Error)]
pub enum LinkError {
    /// The run is over: the actor should stop.
    #[error("the run is finished")]
    Finished,
    /// The learner refused a message or registration: a bug or misconfiguration on the actor's
    /// side, not worth retrying.
    #[error("the learner refused: {0}")]
    Refused(String),
    /// The learner could not be reached within the link's retry policy.
    #[error("the learner is unreachable: {0}")]
    Unavailable(String),
    /// The link was shut down.
    #[error("the link is closed")]
    Closed,
    /// [`ActorLink::flush`] ran out of time with this many messages unacknowledged; the link
    /// itself is fine (the learner is withholding acks, or reconnecting).
    #[error("{0} messages still unacknowledged")]
    TimedOut(usize),
}

/// The actor's side of a connection to the learner. Implementations keep every sent item until
/// the learner acknowledges it and resend after reconnecting, so an item handed to
/// [`send`](Self::send) is stored exactly once unless the actor process dies first.
pub trait ActorLink: Send {
    /// Registers the actor (once; implementations re-register by themselves after a learner
    /// restart).
    fn register(&mut self, registration: &Registration) -> Result<Admission, LinkError>;

    /// Queues one item for the learner. Blocks while the learner applies backpressure (the
    /// window of unacknowledged items is full); the link numbers items itself.
    fn send(&mut self, item: IngestItem) -> Result<(), LinkError>;

    /// Blocks until every item sent so far is acknowledged, or `timeout` passes
    /// ([`LinkError::TimedOut`]).
    fn flush(&mut self, timeout: Duration) -> Result<(), LinkError>;

    /// The latest weights the link has received, waitable.
    fn weights(&self) -> &Published<WeightsSnapshot>;

    /// The newest weights version the learner has announced (in acks), for the staleness bound.
    fn learner_version(&self) -> u64;

    /// Reports greedy test results of weights `weights_version`.
    fn report_evaluation(
        &mut self,
        weights_version: u64,
        episodes: u32,
        successes: u32,
    ) -> Result<(), LinkError>;
}
