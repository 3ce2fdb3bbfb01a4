//! One error type for the crate. Messages are one line and name what was wrong (which frame,
//! which field), so the CLI can print them as they are.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum TrackError {
    /// Inputs the tracker cannot use: wrong counts, non-finite values, empty sequences.
    #[error("{what}: {reason}")]
    Input { what: &'static str, reason: String },
    /// No face in a photo, or in any frame of a video.
    #[error("no face found in {name}")]
    NoFace { name: String },
    /// The solver met a system it cannot solve (non-finite or singular); names the stage.
    #[error("fit failed ({stage}): {reason}")]
    Numerical { stage: &'static str, reason: String },
    #[error("{path}: {reason}")]
    Output { path: PathBuf, reason: String },
    #[error(transparent)]
    Flame(#[from] gagavatar_flame::FlameError),
    #[error(transparent)]
    Data(#[from] gagavatar_data::DataError),
    #[error(transparent)]
    Format(#[from] gagavatar_formats::FormatError),
}

pub type Result<T> = std::result::Result<T, TrackError>;

pub(crate) fn input(what: &'static str, reason: impl Into<String>) -> TrackError {
    TrackError::Input {
        what,
        reason: reason.into(),
    }
}
