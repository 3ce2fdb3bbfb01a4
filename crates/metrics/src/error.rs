use std::path::PathBuf;

/// Everything the metrics can fail with. Bad inputs (a face rectangle outside the image, a
/// degenerate rectangle or landmark set, non-finite numbers, a chip of the wrong size) are
/// errors, never panics.
#[derive(Debug, thiserror::Error)]
pub enum MetricsError {
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    /// A model file missing, unreadable, or not holding exactly the expected tensors.
    #[error("model weights {}: {reason}", .path.display())]
    Weights { path: PathBuf, reason: String },
    /// An input the metric cannot be computed on.
    #[error("invalid input `{name}`: {reason}")]
    Input { name: String, reason: String },
    /// A model file that the format readers refuse (an ONNX model that cannot be decoded).
    #[error(transparent)]
    File(#[from] gagavatar_formats::FormatError),
}

pub type Result<T> = std::result::Result<T, MetricsError>;

pub(crate) fn input_err(name: &str, reason: impl Into<String>) -> MetricsError {
    MetricsError::Input {
        name: name.to_string(),
        reason: reason.into(),
    }
}
