//! The learner service over gRPC (tonic): the actor's end of it, and what every server
//! carries. The learner's end (`hac_serve::grpc`: the `hac.v1.Learner` service over a learner,
//! and the server that runs it with status, health and reflection) is built on the pieces here.
//!
//! - `status`: [`StatusGrpc`], the `hac.v1.Status` service over any [`StatusSource`] (the
//!   learner, in `hac-serve`; an actor daemon's [`ActorNodeStatus`]).
//! - `ops`: [`Health`] (`grpc.health.v1`), reflection, the token check and TLS
//!   ([`ServerSecurity`], [`router`], [`serve_router`]) shared by every server, and
//!   [`serve_status`], an actor daemon's own status server.
//! - `malformed`: [`RefuseUndecodable`], the same refusal for undecodable bytes on every RPC.
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
mod status;

use hac_proto::RejectReason;
use tokio::sync::watch;
use tonic::metadata::MetadataValue;
use tonic::{Code, Status};

pub use client::{ConnectError, GrpcLink, GrpcLinkOptions};
pub use malformed::{OnMalformed, RefuseUndecodable};
pub use ops::{
    Health, LEARNER_SERVICE, STATUS_SERVICE, ServerSecurity, router, serve_router, serve_status,
};
pub use status::{
    ActorNodeStatus, DEFAULT_WATCH_INTERVAL, MIN_WATCH_INTERVAL, StatusGrpc, StatusSource,
    role_name,
};

/// The status metadata key naming the [`RejectReason`] of a refusal.
pub const REJECT_REASON_KEY: &str = "hac-reject-reason";

/// The [`RejectReason`] a status carries in its [`REJECT_REASON_KEY`] metadata, if any (transport
/// failures carry none).
pub fn reject_reason(status: &Status) -> Option<RejectReason> {
    let value = status.metadata().get(REJECT_REASON_KEY)?.to_str().ok()?;
    RejectReason::ALL.into_iter().find(|r| r.name() == value)
}

/// A refusal as a gRPC status: `code`, `message`, and `reason` in the [`REJECT_REASON_KEY`]
/// metadata. Every refusal of every server is made here.
pub fn refusal_status(reason: RejectReason, code: Code, message: String) -> Status {
    let mut status = Status::new(code, message);
    status
        .metadata_mut()
        .insert(REJECT_REASON_KEY, MetadataValue::from_static(reason.name()));
    status
}

/// Completes once `flag` is set (or its sender is gone). Returns nothing, so that no borrow of
/// the channel outlives the wait (a `select!` holds its branches' outputs across the handler).
pub async fn until_set(flag: &mut watch::Receiver<bool>) {
    let _ = flag.wait_for(|&set| set).await;
}
