//! The learner service over gRPC (tonic), both ends of it, and the operations services every
//! server carries.
//!
//! - `server`: [`LearnerGrpc`] adapts a [`Learner`](hac_learner::Learner) to the generated
//!   `hac.v1.Learner` service, and [`serve`] runs it, with status, health and reflection, on a
//!   bound listener until a shutdown future completes.
//! - `status`: [`StatusGrpc`], the `hac.v1.Status` service over any [`StatusSource`] (the
//!   learner; an actor daemon's [`ActorNodeStatus`]).
//! - `ops`: [`Health`] (`grpc.health.v1`), reflection, the token check and TLS
//!   ([`ServerSecurity`]) shared by every server, and [`serve_status`], an actor daemon's own
//!   status server.
//! - `client`: [`GrpcLink`], the [`ActorLink`](crate::ActorLink) of actors on any host: a small
//!   tokio runtime of its own behind the trait's blocking methods, with a window of unacknowledged
//!   messages, reconnects with backoff, and re-registration after a learner restart.
//!
//! # Refusals on the wire
//! Every refusal is a gRPC status whose code says what kind of problem it is and whose ASCII
//! metadata [`REJECT_REASON_KEY`] names the [`RejectReason`] it was counted under, so that a client
//! can tell refusals apart without reading messages:
//!
//! | reason                                                  | code                  |
//! |---------------------------------------------------------|-----------------------|
//! | `malformed` (bytes that do not decode, on any RPC), `invalid_batch` (also a string above its length limit), `not_finite`, `level_out_of_range` | `INVALID_ARGUMENT` |
//! | `oversized` (above the server's message size limit)     | `RESOURCE_EXHAUSTED`  |
//! | `oversized` (`batch.count` above `max_batch_transitions`) | `INVALID_ARGUMENT`  |
//! | `unknown_actor` (also a weights watch of an unregistered id) | `NOT_FOUND`         |
//! | `stale_incarnation`, `finished`                         | `FAILED_PRECONDITION` |
//! | `sequence_gap`                                          | `OUT_OF_RANGE`        |
//! | `wrong_role`                                            | `PERMISSION_DENIED`   |
//! | `unauthenticated` (token missing or wrong; any service but health) | `UNAUTHENTICATED` |
//!
//! A refused ingest message ends that actor's stream only; what was acknowledged before it stays
//! stored. A stream the server ends because it is shutting down gets `UNAVAILABLE` without a
//! reason (try again later), or `FAILED_PRECONDITION`/`finished` once the run is over.

mod client;
mod malformed;
mod ops;
mod server;
mod status;

use hac_proto::RejectReason;
use tokio::sync::watch;
use tonic::Status;

pub use client::{ConnectError, GrpcLink, GrpcLinkOptions};
pub use malformed::RefuseUndecodable;
pub use ops::{Health, LEARNER_SERVICE, STATUS_SERVICE, ServerSecurity, serve_status};
pub use server::{LearnerGrpc, ServerOptions, serve};
pub use status::{
    ActorNodeStatus, DEFAULT_WATCH_INTERVAL, MIN_WATCH_INTERVAL, StatusGrpc, StatusSource,
    learner_status, role_name,
};

/// The status metadata key naming the [`RejectReason`] of a refusal.
pub const REJECT_REASON_KEY: &str = "hac-reject-reason";

/// The [`RejectReason`] a status carries in its [`REJECT_REASON_KEY`] metadata, if any (transport
/// failures carry none).
pub fn reject_reason(status: &Status) -> Option<RejectReason> {
    let value = status.metadata().get(REJECT_REASON_KEY)?.to_str().ok()?;
    RejectReason::ALL.into_iter().find(|r| r.name() == value)
}

/// Completes once `flag` is set (or its sender is gone). Returns nothing, so that no borrow of
/// the channel outlives the wait (a `select!` holds its branches' outputs across the handler).
async fn until_set(flag: &mut watch::Receiver<bool>) {
    let _ = flag.wait_for(|&set| set).await;
}
