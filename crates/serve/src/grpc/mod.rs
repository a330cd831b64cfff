//! The learner's end of the gRPC transport (the actor's end, the wire rules and the pieces every
//! server shares are in [`hac_transport::grpc`]).
//!
//! - `server`: [`LearnerGrpc`] adapts a [`Learner`](hac_learner::Learner) to the generated
//!   `hac.v1.Learner` service, and [`serve`] runs it, with status, health and reflection, on a
//!   bound listener until a shutdown future completes.
//! - `status`: the learner's `hac.v1.Status` answer ([`learner_status`], [`LearnerSource`]).

mod server;
mod status;

pub use server::{LearnerGrpc, ServerOptions, serve};
pub use status::{LearnerSource, learner_status};
