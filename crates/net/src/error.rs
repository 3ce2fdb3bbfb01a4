use std::path::PathBuf;

/// Everything the network crate can fail with.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    /// The cause is part of the message and deliberately not a `source()`, which the CLI
    /// would print a second time.
    #[error("{}: {err}", path.display())]
    Io { path: PathBuf, err: std::io::Error },
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
    /// A precision this CPU cannot run (bf16 without AVX512-BF16).
    #[error(transparent)]
    Precision(#[from] gagavatar_ops::bf16::Bf16Error),
    /// A weights file that cannot be read as a torch zip or safetensors file.
    #[error(transparent)]
    File(#[from] gagavatar_formats::FormatError),
}

pub type Result<T> = std::result::Result<T, NetError>;
