//! One error type for the crate. Every message fits on one line and names the file, and the
//! frame / field / key involved where there is one, so a user with a broken dataset knows where
//! to look.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// The cause is part of the message and deliberately not a `source()`, which the CLI
    /// would print a second time.
    #[error("{}: {action}: {err}", path.display())]
    Io {
        path: PathBuf,
        /// What was being done ("cannot read", "cannot write", ...).
        action: &'static str,
        err: std::io::Error,
    },
    /// A file whose format (pickle, LMDB, image, ...) cannot be read; the message names it.
    #[error(transparent)]
    Format(#[from] gagavatar_formats::FormatError),
    /// A pickle that cannot be parsed, or holds something other than plain data.
    #[error("{path}: {reason}")]
    Pickle { path: PathBuf, reason: String },
    /// A tracked-frame record with a missing, misshapen or non-finite field.
    #[error("{path}: frame {frame}: field `{field}`: {reason}")]
    Record {
        path: PathBuf,
        /// How to find the frame: its name in backticks, or `#index` in a JSON list.
        frame: String,
        field: String,
        reason: String,
    },
    #[error("{path}: image `{key}`: {reason}")]
    Image {
        path: PathBuf,
        key: String,
        reason: String,
    },
    #[error("{path}: invalid JSON: {reason}")]
    Json { path: PathBuf, reason: String },
    /// A key asked for that the file does not hold.
    #[error("{path}: no entry `{key}`{}", available_suffix(.available, *.total))]
    MissingKey {
        path: PathBuf,
        key: String,
        /// A few keys that do exist, to show the naming scheme.
        available: Vec<String>,
        /// How many entries there are.
        total: usize,
    },
    /// A folder or file that is not laid out as expected (missing parts, inconsistent lists).
    #[error("{path}: {reason}")]
    Layout { path: PathBuf, reason: String },
    #[error("cannot encode an image as PNG: {reason}")]
    Encode { reason: String },
    /// Values that cannot be written (duplicate or empty keys, non-finite numbers, ...).
    #[error("{path}: cannot write: {reason}")]
    Write { path: PathBuf, reason: String },
}

fn available_suffix(available: &[String], total: usize) -> String {
    if total == 0 {
        " (the file has no entries)".into()
    } else if available.len() < total {
        format!(" ({total} entries, e.g. {}, ...)", available.join(", "))
    } else {
        format!(" (entries: {})", available.join(", "))
    }
}

pub type Result<T> = std::result::Result<T, DataError>;

pub(crate) fn io_err(
    path: impl Into<PathBuf>,
    action: &'static str,
) -> impl FnOnce(std::io::Error) -> DataError {
    let path = path.into();
    move |err| DataError::Io { path, action, err }
}
