//! [`RejectReason`]: why an input was refused, as counted in status and metrics and named in
//! the `hac-reject-reason` metadata of a refusal.

use crate::WireError;

/// What a rejected input was, for the counts in status. Every rejection is counted under
/// exactly one reason.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum RejectReason {
    /// Bytes that do not decode as the expected message (counted by the transport).
    Malformed,
    /// A message above the size limit (counted by the transport).
    Oversized,
    /// A required field missing or a field of the wrong length or count.
    InvalidBatch,
    /// NaN or infinity in a float field.
    NotFinite,
    /// A finite value the environment or the level cannot produce (a state outside the
    /// environment's box, a reward not in {0, -1, -H}, an episode longer than the budget).
    OutOfRange,
    LevelOutOfRange,
    UnknownActor,
    StaleIncarnation,
    SequenceGap,
    /// Transitions from an evaluator, or an evaluation from an unknown actor.
    WrongRole,
    /// Credentials missing or wrong (counted by the transport).
    Unauthenticated,
    /// Input after the run finished.
    Finished,
    /// An evaluation of weights another learner process published (before a restart).
    StaleWeights,
}

impl RejectReason {
    pub const ALL: [RejectReason; 13] = [
        Self::Malformed,
        Self::Oversized,
        Self::InvalidBatch,
        Self::NotFinite,
        Self::OutOfRange,
        Self::LevelOutOfRange,
        Self::UnknownActor,
        Self::StaleIncarnation,
        Self::SequenceGap,
        Self::WrongRole,
        Self::Unauthenticated,
        Self::Finished,
        Self::StaleWeights,
    ];

    /// The snake_case name used in status and metrics.
    pub fn name(self) -> &'static str {
        match self {
            Self::Malformed => "malformed",
            Self::Oversized => "oversized",
            Self::InvalidBatch => "invalid_batch",
            Self::NotFinite => "not_finite",
            Self::OutOfRange => "out_of_range",
            Self::LevelOutOfRange => "level_out_of_range",
            Self::UnknownActor => "unknown_actor",
            Self::StaleIncarnation => "stale_incarnation",
            Self::SequenceGap => "sequence_gap",
            Self::WrongRole => "wrong_role",
            Self::Unauthenticated => "unauthenticated",
            Self::Finished => "finished",
            Self::StaleWeights => "stale_weights",
        }
    }

    /// The reason a message that failed its wire checks is counted under.
    pub fn of_wire(e: &WireError) -> Self {
        match e {
            WireError::NotFinite { .. } => Self::NotFinite,
            WireError::LevelOutOfRange { .. } => Self::LevelOutOfRange,
            WireError::CountAboveLimit { .. } => Self::Oversized,
            WireError::Packed(_) => Self::Malformed,
            _ => Self::InvalidBatch,
        }
    }
}
