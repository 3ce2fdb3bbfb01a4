//! What the face crate can refuse.

/// Errors of the face models and their weights files.
#[derive(Debug, thiserror::Error)]
pub enum FaceError {
    /// The weights file could not be parsed at all.
    #[error("{label}: not a readable safetensors file ({reason})")]
    Format { label: String, reason: String },
    /// The file holds weights for another model.
    #[error("{label}: holds the weights of '{found}', expected '{expected}'")]
    WrongModel {
        label: String,
        expected: String,
        found: String,
    },
    /// A tensor is missing or has the wrong shape (the message names it).
    #[error("{label}: {reason}")]
    Weights { label: String, reason: String },
    /// Tensors the model does not use: a file for a different network.
    #[error("{label}: {count} tensors the model does not use, e.g. '{example}'")]
    UnusedWeights {
        label: String,
        count: usize,
        example: String,
    },
    /// The input image cannot be processed (empty, or too small to sample).
    #[error("{0}")]
    Input(String),
}
