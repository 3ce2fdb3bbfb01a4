use std::path::PathBuf;

/// Everything the training building blocks can fail with. Bad inputs (wrong shapes, NaN,
/// empty sets, degenerate boxes) are errors, never panics.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    #[error(transparent)]
    Net(#[from] gagavatar_net::NetError),
    #[error("invalid input `{name}`: {reason}")]
    Input { name: String, reason: String },
    /// Perceptual-network weights missing, misshapen or unreadable.
    #[error("perceptual weights{}: {reason}", .path.as_ref().map(|p| format!(" in {}", p.display())).unwrap_or_default())]
    Weights {
        path: Option<PathBuf>,
        reason: String,
    },
    /// An optimiser state that does not fit the parameters it is loaded into.
    #[error("optimizer state: {0}")]
    State(String),
}

pub type Result<T> = std::result::Result<T, TrainError>;

pub(crate) fn input_err(name: &str, reason: impl Into<String>) -> TrainError {
    TrainError::Input {
        name: name.to_string(),
        reason: reason.into(),
    }
}
