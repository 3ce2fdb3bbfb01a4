//! Errors of the training run (configuration, data loading, checkpoints, the loop). The
//! numeric building blocks keep their own [`TrainError`]; a run wraps it.

use std::path::{Path, PathBuf};

use crate::error::TrainError;

#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error(transparent)]
    Train(#[from] TrainError),
    #[error(transparent)]
    Net(#[from] gagavatar_net::NetError),
    #[error(transparent)]
    Data(#[from] gagavatar_data::DataError),
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    /// A configuration file or value that cannot be used.
    #[error("{}{reason}", .path.as_ref().map(|p| format!("{}: ", p.display())).unwrap_or_default())]
    Config {
        path: Option<PathBuf>,
        reason: String,
    },
    /// FLAME asset or FLAME codes of a frame.
    #[error("FLAME{}: {reason}", .what.as_ref().map(|w| format!(" ({w})")).unwrap_or_default())]
    Flame {
        what: Option<String>,
        reason: String,
    },
    /// A frame that cannot be turned into a training sample.
    #[error("{dir}: frame `{frame}`: {reason}")]
    Sample {
        dir: PathBuf,
        frame: String,
        reason: String,
    },
    /// The cause is part of the message and deliberately not a `source()`, which the CLI
    /// would print a second time.
    #[error("{}: {action}: {err}", path.display())]
    Io {
        path: PathBuf,
        action: &'static str,
        err: std::io::Error,
    },
    /// A run folder or checkpoint that is missing, inconsistent or unreadable.
    #[error("{path}: {reason}")]
    Checkpoint { path: PathBuf, reason: String },
    /// The data-parallel ranks could not agree or talk (MPI), or another rank failed.
    #[error("data-parallel rank {rank} of {size}: {reason}")]
    Ranks {
        rank: usize,
        size: usize,
        reason: String,
    },
    /// The device running the rendering half of the step (`--device gpu`) failed.
    #[error("the rendering half on {device}")]
    Render {
        device: String,
        #[source]
        err: crate::render_half::BackendError,
    },
    /// Ctrl-C or another stop request.
    #[error("stopped at step {step}: {reason}")]
    Stopped { step: u64, reason: String },
}

pub type RunResult<T> = std::result::Result<T, RunError>;

pub(crate) fn io_err(path: &Path, action: &'static str) -> impl FnOnce(std::io::Error) -> RunError {
    let path = path.to_owned();
    move |err| RunError::Io { path, action, err }
}

pub(crate) fn config_err(path: Option<&Path>, reason: impl Into<String>) -> RunError {
    RunError::Config {
        path: path.map(Path::to_path_buf),
        reason: reason.into(),
    }
}

pub(crate) fn ckpt_err(path: &Path, reason: impl Into<String>) -> RunError {
    RunError::Checkpoint {
        path: path.to_owned(),
        reason: reason.into(),
    }
}

impl From<gagavatar_flame::FlameError> for RunError {
    fn from(e: gagavatar_flame::FlameError) -> Self {
        RunError::Flame {
            what: None,
            reason: e.to_string(),
        }
    }
}
