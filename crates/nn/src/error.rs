//! Errors of this crate: all of them come from reading checkpoints.

/// A safetensors buffer that cannot be turned into the requested networks.
#[derive(Debug, thiserror::Error)]
pub enum NnError {
    /// Not a safetensors buffer (truncated, corrupt header, inconsistent offsets).
    #[error("invalid safetensors data: {0}")]
    Format(#[from] safetensors::SafeTensorError),
    /// A tensor the networks need is absent.
    #[error("missing tensor `{0}`")]
    MissingTensor(String),
    /// A tensor is not stored as `f32`.
    #[error("tensor `{name}` has dtype {found}, expected F32")]
    Dtype {
        /// The tensor's name in the file.
        name: String,
        /// The dtype found.
        found: String,
    },
    /// A tensor's shape does not fit the network it belongs to.
    #[error("tensor `{name}` has shape {found:?}, expected {expected}")]
    Shape {
        /// The tensor's name in the file.
        name: String,
        /// What would fit, in words.
        expected: String,
        /// The shape found.
        found: Vec<usize>,
    },
    /// A metadata entry is absent or unreadable.
    #[error("metadata `{key}`: {reason}")]
    Metadata {
        /// The entry's key.
        key: String,
        /// What is wrong with it.
        reason: String,
    },
    /// The file is well formed but describes other networks than the configuration asks for.
    #[error("checkpoint does not match the configuration: {what} are {found}, expected {expected}")]
    Mismatch {
        /// Which property differs.
        what: String,
        /// The configuration's value.
        expected: String,
        /// The file's value.
        found: String,
    },
}
