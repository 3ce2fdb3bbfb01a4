//! One error type for the crate; every message names the option, file or frame involved.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    /// A generator setting out of range (`field` is the option's name).
    #[error("synthetic data: `{field}`: {reason}")]
    Config { field: &'static str, reason: String },
    /// Output folder problems (exists, cannot be created, cannot be moved into place).
    #[error("{path}: {reason}")]
    Output { path: PathBuf, reason: String },
    /// A mesh the rasterizer cannot draw (bad face index, non-finite vertex).
    #[error("rasterizer: {0}")]
    Mesh(String),
    #[error(transparent)]
    Flame(#[from] gagavatar_flame::FlameError),
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    #[error(transparent)]
    Data(#[from] gagavatar_data::DataError),
    #[error("interrupted; no output was written")]
    Interrupted,
}

pub type Result<T> = std::result::Result<T, SynthError>;

pub(crate) fn config_err(field: &'static str, reason: impl Into<String>) -> SynthError {
    SynthError::Config {
        field,
        reason: reason.into(),
    }
}
