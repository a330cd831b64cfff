//! The one error type of the crate: a message that does not satisfy the contract.

use std::borrow::Cow;

/// Why a wire message was refused. Every message names the offending field (as
/// `message.field`, with an index where the field is repeated) and the values involved, so that
/// the learner can return it verbatim as an `INVALID_ARGUMENT` detail.
#[derive(Debug, Clone, thiserror::Error)]
pub enum WireError {
    /// A required field is absent, empty or 0 where 0 means "unset".
    #[error("missing field {field}")]
    MissingField { field: Cow<'static, str> },
    /// A string above its limit (see the `MAX_*` constants).
    #[error("{field} is {len} bytes, above the limit of {limit} bytes")]
    TooLong {
        field: Cow<'static, str>,
        len: usize,
        limit: usize,
    },
    /// A string with a control character (a newline, an escape, ...), which would let a client
    /// forge lines in the learner's log or the operator's terminal.
    #[error("{field} has a control character (U+{code:04X}) at byte {at}")]
    ControlCharacter {
        field: Cow<'static, str>,
        code: u32,
        at: usize,
    },
    /// A repeated field with more entries than its limit.
    #[error("{field} has {count} entries, above the limit of {limit}")]
    TooMany {
        field: &'static str,
        count: usize,
        limit: usize,
    },
    #[error("ingest request has no item")]
    NoIngestItem,
    /// A count or dimension that must be positive is 0.
    #[error("{field} is 0")]
    Zero { field: Cow<'static, str> },
    #[error("batch.count {count} above the limit {limit}")]
    CountAboveLimit { count: u32, limit: usize },
    #[error("batch.level {level} out of range (levels 0..{levels})")]
    LevelOutOfRange { level: u32, levels: usize },
    /// A vector field whose length is not `count x dim`.
    #[error("{field} has {len} values, expected {expected} (count {count} x {dim_name} {dim})")]
    WrongLength {
        field: &'static str,
        len: usize,
        expected: usize,
        count: usize,
        dim_name: &'static str,
        dim: usize,
    },
    /// A per-transition field (rewards, terminals) whose length is not `count`.
    #[error("{field} has {len} values, expected one per transition (count {count})")]
    WrongCount {
        field: &'static str,
        len: usize,
        count: usize,
    },
    /// A per-level list whose length is not the number of levels.
    #[error("{field} has {len} entries, expected one per level ({levels})")]
    NotPerLevel {
        field: &'static str,
        len: usize,
        levels: usize,
    },
    /// `batch.extra` whose length is not a whole number of values per transition.
    #[error(
        "batch.extra has {len} values, not the same number for each of the {count} transitions"
    )]
    ExtraNotPerTransition { len: usize, count: usize },
    /// NaN or an infinity.
    #[error("{field}[{index}] is {value}")]
    NotFinite {
        field: &'static str,
        index: usize,
        value: f32,
    },
    #[error("batch.terminals[{index}] is {value}, expected 0 or 1")]
    BadTerminal { index: usize, value: f32 },
    #[error("weights.levels has level {level} twice")]
    DuplicateLevel { level: u32 },
    /// Levels must be exactly `0..levels`; `level` is the first one absent.
    #[error(
        "weights.levels lacks level {level} (has {levels} entries, expected levels 0..{levels})"
    )]
    MissingLevel { level: usize, levels: usize },
    #[error("{field} has unknown value {value}")]
    UnknownEnum { field: &'static str, value: i32 },
    #[error("evaluation_report.successes {successes} above episodes {episodes}")]
    SuccessesAboveEpisodes { successes: u32, episodes: u32 },
    /// Bytes in shared memory that are not a packed message (the counterpart of bytes prost
    /// cannot decode).
    #[error("packed message: {0}")]
    Packed(Cow<'static, str>),
}

impl WireError {
    pub fn missing(field: &'static str) -> Self {
        Self::MissingField {
            field: Cow::Borrowed(field),
        }
    }

    pub fn zero(field: &'static str) -> Self {
        Self::Zero {
            field: Cow::Borrowed(field),
        }
    }

    /// The same refusal of a string, named `field` (for an element of a repeated field).
    pub fn in_field(self, field: String) -> Self {
        match self {
            Self::TooLong { len, limit, .. } => Self::TooLong {
                field: Cow::Owned(field),
                len,
                limit,
            },
            Self::ControlCharacter { code, at, .. } => Self::ControlCharacter {
                field: Cow::Owned(field),
                code,
                at,
            },
            other => other,
        }
    }
}
