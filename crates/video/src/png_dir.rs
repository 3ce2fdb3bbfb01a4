//! A folder of `frame_00000.png`, ... built in a hidden sibling folder and renamed into place.

use std::path::{Path, PathBuf};

use crate::temp::{check_dir_target, temp_sibling, TempPath};
use crate::VideoError;

pub(crate) struct PngDirSink {
    target: PathBuf,
    width: u32,
    height: u32,
    tmp: TempPath,
    /// Zero-padded digits in the frame names.
    digits: usize,
}

/// The file name of frame `index` (0-based) in a PNG folder.
pub(crate) fn frame_name(index: usize, digits: usize) -> String {
    format!("frame_{index:0digits$}.png")
}

impl PngDirSink {
    pub(crate) fn create(
        path: &Path,
        width: usize,
        height: usize,
        digits: usize,
    ) -> Result<Self, VideoError> {
        let too_large = || VideoError::BadSize {
            width,
            height,
            reason: "PNG sides are limited to 2^31 - 1".into(),
        };
        let w = u32::try_from(width)
            .ok()
            .filter(|&w| w < 1 << 31)
            .ok_or_else(too_large)?;
        let h = u32::try_from(height)
            .ok()
            .filter(|&h| h < 1 << 31)
            .ok_or_else(too_large)?;
        check_dir_target(path)?;
        let tmp_path = temp_sibling(path)?;
        std::fs::create_dir(&tmp_path).map_err(|e| VideoError::io(&tmp_path, e))?;
        Ok(PngDirSink {
            target: path.to_path_buf(),
            width: w,
            height: h,
            tmp: TempPath::dir(tmp_path),
            digits,
        })
    }

    pub(crate) fn push(&mut self, rgb: &[u8], index: usize) -> Result<(), VideoError> {
        let file = self.tmp.path().join(frame_name(index, self.digits));
        image::save_buffer_with_format(
            &file,
            rgb,
            self.width,
            self.height,
            image::ExtendedColorType::Rgb8,
            image::ImageFormat::Png,
        )
        .map_err(|e| match e {
            image::ImageError::IoError(io) => VideoError::io(&file, io),
            other => VideoError::Encode(format!("{}: {other}", file.display())),
        })
    }

    pub(crate) fn target(&self) -> &Path {
        &self.target
    }

    /// Adds a file beside the frames (written now, moved into place with them).
    pub(crate) fn add_file(&self, name: &str, bytes: &[u8]) -> Result<(), VideoError> {
        let file = self.tmp.path().join(name);
        std::fs::write(&file, bytes).map_err(|e| VideoError::io(&file, e))
    }

    pub(crate) fn finish(self) -> Result<(), VideoError> {
        // Checked again: the folder may have been created while the frames were rendered.
        check_dir_target(&self.target)?;
        if self.target.is_dir() {
            // Empty (just checked); rename cannot replace a directory on every platform.
            std::fs::remove_dir(&self.target).map_err(|e| VideoError::io(&self.target, e))?;
        }
        self.tmp.persist(&self.target)
    }
}
