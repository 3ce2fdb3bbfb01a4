//! Hidden temporary outputs beside the target, removed unless they were renamed into place.

use std::path::{Path, PathBuf};

use crate::VideoError;

/// A hidden name beside `path` from the project's one naming scheme
/// ([`gagavatar_formats::atomic::temp_sibling`]: same directory, unique per process and call),
/// after checking that `path` names a file at all.
pub(crate) fn temp_sibling(path: &Path) -> Result<PathBuf, VideoError> {
    if path.file_name().is_none() {
        return Err(VideoError::BadPath {
            path: path.to_path_buf(),
            reason: "the output path has no file name".into(),
        });
    }
    Ok(gagavatar_formats::atomic::temp_sibling(path))
}

/// A temporary file or directory that is deleted on drop unless [`TempPath::persist`] renamed it.
pub(crate) struct TempPath {
    path: PathBuf,
    is_dir: bool,
    armed: bool,
}

impl TempPath {
    pub(crate) fn file(path: PathBuf) -> Self {
        TempPath {
            path,
            is_dir: false,
            armed: true,
        }
    }

    pub(crate) fn dir(path: PathBuf) -> Self {
        TempPath {
            path,
            is_dir: true,
            armed: true,
        }
    }

    pub(crate) fn path(&self) -> &Path {
        &self.path
    }

    /// Renames the temporary over `target`.
    pub(crate) fn persist(mut self, target: &Path) -> Result<(), VideoError> {
        gagavatar_formats::atomic::pause_before_rename();
        std::fs::rename(&self.path, target).map_err(|e| VideoError::io(target, e))?;
        self.armed = false;
        Ok(())
    }
}

impl Drop for TempPath {
    fn drop(&mut self) {
        if self.armed {
            // Best effort: there is no one to report a failure to while unwinding.
            let _ = if self.is_dir {
                std::fs::remove_dir_all(&self.path)
            } else {
                std::fs::remove_file(&self.path)
            };
        }
    }
}

/// Refuses a target that is a directory (for a video file); an existing file is replaced.
pub(crate) fn check_file_target(path: &Path) -> Result<(), VideoError> {
    if path.is_dir() {
        return Err(VideoError::BadPath {
            path: path.to_path_buf(),
            reason: "is a directory; a video file cannot replace it".into(),
        });
    }
    Ok(())
}

/// Refuses a target that is a file or a non-empty directory (for a PNG folder), so frames are
/// never mixed with, or replace, someone else's files.
pub(crate) fn check_dir_target(path: &Path) -> Result<(), VideoError> {
    let meta = match std::fs::symlink_metadata(path) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(VideoError::io(path, e)),
    };
    if !meta.is_dir() {
        return Err(VideoError::BadPath {
            path: path.to_path_buf(),
            reason: "exists and is not a directory (a PNG frame folder was asked for: use a .mp4 \
                     or .gif extension for a video file)"
                .into(),
        });
    }
    let mut entries = std::fs::read_dir(path).map_err(|e| VideoError::io(path, e))?;
    if entries.next().is_some() {
        return Err(VideoError::BadPath {
            path: path.to_path_buf(),
            reason: "is a directory that is not empty; choose a new folder for the PNG frames"
                .into(),
        });
    }
    Ok(())
}
