use std::path::PathBuf;

/// Everything the network crate can fail with.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    #[error("{0}")]
    Candle(#[from] candle_core::Error),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {reason}")]
    Format { path: PathBuf, reason: String },
    /// The weights do not fit the configuration: every missing, unexpected and misshapen key.
    #[error("checkpoint does not match the `{preset}` model: {summary}")]
    Keys { preset: String, summary: String },
    #[error("invalid model configuration: {0}")]
    Config(String),
    #[error("invalid input `{name}`: {reason}")]
    Input { name: String, reason: String },
    #[error(transparent)]
    Splat(#[from] gagavatar_splat::SplatError),
    #[error(transparent)]
    Flame(#[from] gagavatar_flame::FlameError),
}

pub type Result<T> = std::result::Result<T, NetError>;
