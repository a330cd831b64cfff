//! How an actor reaches the learner: the [`ActorLink`] trait, and its implementations on the
//! actor's side. This crate does not depend on the learner: the learner's side of every
//! transport (the gRPC and shared-memory servers, the in-process link) is `hac-serve`, built on
//! the wire contract (`hac-proto`) and the pieces both sides share, which are here.
//!
//! [`ActorLink`] is split as Acme splits an actor's client: an [`IngestSink`] (the sending half:
//! send, flush) and a [`WeightsSource`] (the weights half: the latest weights, the learner's
//! newest version), with registration, episode turns, evaluation reports and the link's
//! counters on top.
//!
//! - [`grpc`]: the learner service over tonic, for actors on any host: the actor's side
//!   ([`grpc::GrpcLink`]), and the status, health, reflection, token and TLS pieces every server
//!   carries (the learner's and an actor daemon's own).
//! - [`shm`]: shared memory (iceoryx2) for actors on the learner's host, beside gRPC: the
//!   actor's [`shm::ShmLink`] (which keeps gRPC for registration and falls back to it when
//!   shared memory is not offered), and the services, acks and checks the learner's server
//!   shares.
//!
//! - [`security`]: the bearer token and TLS settings of servers and clients.
//! - [`metrics`]: Prometheus text exposition over HTTP (`/metrics`), and an actor daemon's
//!   metrics.
//! - [`refusal_log`]: rate-limited warnings about refused input, for every server.
//!
//! The actor loop (`hac-actor`) is written against the traits only, so every transport runs the
//! same actor code.

pub mod grpc;
mod held;
pub mod metrics;
pub mod refusal_log;
pub mod security;
pub mod shm;

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use hac_proto::Published;
use hac_proto::{Admission, IngestItem, Registration, WeightsSnapshot};

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
    /// [`IngestSink::flush`] ran out of time with this many messages unacknowledged; the link
    /// itself is fine (the learner is withholding acks, or reconnecting).
    #[error("{0} messages still unacknowledged")]
    TimedOut(usize),
}

/// One greedy test round, for [`ActorLink::report_evaluation`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EvaluationOf {
    /// The evaluated weights: their version and the learner process that published them.
    pub weights_version: u64,
    pub learner_start: u64,
    pub episodes: u32,
    pub successes: u32,
}

/// The sending half of a link: items to the learner, and waits for their acknowledgement.
/// Implementations keep every sent item until the learner acknowledges it and resend after
/// reconnecting, so an item handed to [`send`](Self::send) is stored exactly once unless the
/// actor process dies first.
pub trait IngestSink: Send {
    /// Queues one item for the learner. Blocks while the learner applies backpressure (the
    /// window of unacknowledged items is full); the link numbers items itself.
    fn send(&mut self, item: IngestItem) -> Result<(), LinkError>;

    /// Blocks until every item sent so far is acknowledged, or `timeout` passes
    /// ([`LinkError::TimedOut`]).
    fn flush(&mut self, timeout: Duration) -> Result<(), LinkError>;

    /// Blocks until every item sent so far is durable (in the learner's write-ahead log; without
    /// a log, acknowledged), or `timeout` passes. Links that do not track durability wait for
    /// acknowledgements.
    fn flush_durable(&mut self, timeout: Duration) -> Result<(), LinkError> {
        self.flush(timeout)
    }
}

/// The weights half of a link: what the learner published, as received.
pub trait WeightsSource {
    /// The latest weights the link has received, waitable.
    fn weights(&self) -> &Published<WeightsSnapshot>;

    /// The newest weights version the learner has announced (in acks), for the staleness bound.
    fn learner_version(&self) -> u64;
}

/// An episode turn the learner granted ([`ActorLink::await_turn`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GrantedTurn {
    /// Play with weights trained on at least this many episodes.
    pub trained: u64,
    /// The index of the episode the turn is for, from which the actor draws the episode's
    /// random streams (with the run's seed); `None` from a learner that sends none.
    pub episode: Option<u64>,
}

/// The actor's side of a connection to the learner: an [`IngestSink`] and a [`WeightsSource`],
/// with registration, episode turns, evaluation reports and the link's counters.
pub trait ActorLink: IngestSink + WeightsSource {
    /// Registers the actor (once; implementations re-register by themselves after a learner
    /// restart).
    fn register(&mut self, registration: &Registration) -> Result<Admission, LinkError>;

    /// Episode turns (a learner with `episodes_in_flight` > 0; see the learner's `await_turn`):
    /// waits up to about `wait` for this trainer's turn to play its next episode. `Some`:
    /// granted. `None`: not yet (ask again). A link that had to register again answers `None`
    /// at once.
    fn await_turn(&mut self, wait: Duration) -> Result<Option<GrantedTurn>, LinkError>;

    /// Reports greedy test results of `weights` (their version and learner process). `true`:
    /// on the curve. `false`: dropped because the weights came from a learner process that has
    /// since restarted (evaluate the new one's instead).
    fn report_evaluation(&mut self, report: &EvaluationOf) -> Result<bool, LinkError>;

    /// Live counters of the link for status and metrics, readable from any thread while the
    /// link is in use (`None`: the link keeps none).
    fn stats(&self) -> Option<Arc<LinkStats>> {
        None
    }

    /// The transport's name in status and metrics: "in-process", "grpc", ...
    fn transport(&self) -> &'static str {
        "unknown"
    }
}

/// A link's live counters (see [`ActorLink::stats`]).
#[derive(Debug, Default)]
pub struct LinkStats {
    incarnation: AtomicU64,
    unacked: AtomicU64,
    undurable: AtomicU64,
    reconnects: AtomicU64,
    learner_version: AtomicU64,
    /// Transitions handed to the link, and of those the ones the learner said are durable, over
    /// every incarnation.
    sent_transitions: AtomicU64,
    durable_transitions: AtomicU64,
}

impl LinkStats {
    /// The incarnation the link's messages are numbered under (0 before registration).
    pub fn incarnation(&self) -> u64 {
        self.incarnation.load(Ordering::Relaxed)
    }

    /// Messages sent and not yet acknowledged.
    pub fn unacked(&self) -> u64 {
        self.unacked.load(Ordering::Relaxed)
    }

    /// Messages acknowledged and not yet durable (the ack-durable gap), kept to be resent to a
    /// restarted learner.
    pub fn undurable(&self) -> u64 {
        self.undurable.load(Ordering::Relaxed)
    }

    /// Transitions handed to the link so far.
    pub fn sent_transitions(&self) -> u64 {
        self.sent_transitions.load(Ordering::Relaxed)
    }

    /// Transitions the learner said are durable so far (links that do not track durability
    /// report 0).
    pub fn durable_transitions(&self) -> u64 {
        self.durable_transitions.load(Ordering::Relaxed)
    }

    /// Attempts to reach the learner again after a failed call or stream.
    pub fn reconnects(&self) -> u64 {
        self.reconnects.load(Ordering::Relaxed)
    }

    /// The newest weights version the learner announced.
    pub fn learner_version(&self) -> u64 {
        self.learner_version.load(Ordering::Relaxed)
    }

    fn set_unacked(&self, n: usize) {
        self.unacked.store(n as u64, Ordering::Relaxed);
    }

    fn set_undurable(&self, n: usize) {
        self.undurable.store(n as u64, Ordering::Relaxed);
    }
}
