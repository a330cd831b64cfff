//! Why the learner refused something: starting, a registration, an ingest message or
//! evaluation report, a wait for room.

use hac_core::LimitError;
use hac_proto::{RejectReason, WireError};
use hac_replay::RateLimiterConfigError;

use crate::{CheckpointError, InvalidOption, WalError};

/// Why the learner could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    #[error(transparent)]
    Config(#[from] hac_agent::RunConfigError),
    #[error(transparent)]
    Options(#[from] InvalidOption),
    /// The run's environment is not one this learner serves (a grid world), or cannot be made.
    #[error("invalid value for `env`: {0}")]
    Env(String),
    #[error("level {level}: invalid rate limiter setting `{}`: {source}", source.field())]
    RateLimiter {
        level: usize,
        #[source]
        source: RateLimiterConfigError,
    },
    /// The checkpoint to resume from does not fit this run.
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// The write-ahead log could not be read back or opened.
    #[error(transparent)]
    Wal(#[from] WalError),
}

/// Why a registration was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RegisterError {
    #[error("register_request.actor_id is empty")]
    EmptyActorId,
    #[error("the run is finished")]
    Finished,
}

/// Why an ingest message or evaluation report was refused. Nothing of a refused message is
/// stored; the actor's earlier messages are unaffected.
#[derive(Debug, Clone, thiserror::Error)]
pub enum IngestError {
    #[error(transparent)]
    Invalid(#[from] WireError),
    #[error("unknown actor `{0}`: register first")]
    UnknownActor(String),
    #[error(
        "actor `{actor}`: incarnation {got} is not the current one ({current}); register again"
    )]
    StaleIncarnation {
        actor: String,
        got: u64,
        current: u64,
    },
    #[error("actor `{actor}`: sequence {got} skips ahead of the next expected sequence {expected}")]
    SequenceGap {
        actor: String,
        got: u64,
        expected: u64,
    },
    #[error("actor `{actor}`: {source}")]
    OutOfRange {
        actor: String,
        #[source]
        source: LimitError,
    },
    #[error(
        "actor `{actor}`: episode_summary.env_steps {got} is above the episode budget of {max} \
         primitive actions"
    )]
    EpisodeTooLong { actor: String, got: u64, max: u64 },
    #[error("actor `{0}` is an evaluator: evaluators send no transitions")]
    WrongRole(String),
    #[error(
        "actor `{0}` is a trainer and an evaluator is registered: only evaluators report \
         evaluations then"
    )]
    TrainerEvaluation(String),
    #[error("evaluation_report.weights_version {0} was never published")]
    UnknownWeightsVersion(u64),
    #[error(
        "evaluation of weights from another learner process (learner_start {got}, this one is \
         {current}): the learner restarted since; evaluate its weights instead"
    )]
    StaleWeights { got: u64, current: u64 },
    #[error("the run is finished")]
    Finished,
}

impl IngestError {
    pub fn reason(&self) -> RejectReason {
        match self {
            Self::Invalid(e) => RejectReason::of_wire(e),
            Self::UnknownActor(_) => RejectReason::UnknownActor,
            Self::StaleIncarnation { .. } => RejectReason::StaleIncarnation,
            Self::SequenceGap { .. } => RejectReason::SequenceGap,
            Self::OutOfRange { .. } | Self::EpisodeTooLong { .. } => RejectReason::OutOfRange,
            Self::WrongRole(_) | Self::TrainerEvaluation(_) => RejectReason::WrongRole,
            Self::UnknownWeightsVersion(_) => RejectReason::InvalidBatch,
            Self::StaleWeights { .. } => RejectReason::StaleWeights,
            Self::Finished => RejectReason::Finished,
        }
    }
}

/// What became of an accepted ingest message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stored {
    /// Stored now.
    New,
    /// Stored before (a resend); acknowledged again, not stored twice.
    Duplicate,
}

/// The backpressure wait ended without room.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum RoomError {
    #[error("the learner is behind; try again")]
    TimedOut,
    #[error("the run is finished")]
    Finished,
}
