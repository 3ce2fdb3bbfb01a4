//! Animated GIF: a palette per frame, infinite loop, delays that keep the average frame rate.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use crate::temp::{check_file_target, temp_sibling, TempPath};
use crate::VideoError;

/// NeuQuant sampling factor (1 = best, 30 = fastest); 10 is the gif crate's suggested balance
/// and keeps a 512x512 frame well under the time a render takes.
const QUANT_SPEED: i32 = 10;

/// Browsers replace delays of 0 or 1 centisecond by 10 (a 10x slow-down), so no frame gets less
/// than this: above 50 fps a GIF plays slower than asked.
const MIN_DELAY_CS: u64 = 2;

pub(crate) struct GifSink {
    target: PathBuf,
    width: u16,
    height: u16,
    fps: f64,
    // Declared before `tmp` so the file is closed before the guard deletes it.
    encoder: gif::Encoder<BufWriter<File>>,
    tmp: TempPath,
}

fn gif_err(path: &Path, e: gif::EncodingError) -> VideoError {
    match e {
        gif::EncodingError::Io(io) => VideoError::io(path, io),
        other => VideoError::Encode(format!("{}: {other}", path.display())),
    }
}

/// Delay of frame `index` in centiseconds: the difference of rounded frame start times, so 30 fps
/// becomes 3, 3, 4, 3, 3, 4, ... and the total length stays right.
pub(crate) fn delay_cs(index: usize, fps: f64) -> u16 {
    let start = |i: usize| (i as f64 * 100.0 / fps).round() as u64;
    let d = start(index + 1)
        .saturating_sub(start(index))
        .max(MIN_DELAY_CS);
    d.min(u16::MAX as u64) as u16
}

impl GifSink {
    pub(crate) fn create(
        path: &Path,
        width: usize,
        height: usize,
        fps: f64,
    ) -> Result<Self, VideoError> {
        let too_large = || VideoError::BadSize {
            width,
            height,
            reason: "GIF sides are limited to 65535".into(),
        };
        let w = u16::try_from(width).map_err(|_| too_large())?;
        let h = u16::try_from(height).map_err(|_| too_large())?;
        check_file_target(path)?;
        let tmp = TempPath::file(temp_sibling(path)?);
        let file = File::create(tmp.path()).map_err(|e| VideoError::io(tmp.path(), e))?;
        let mut encoder = gif::Encoder::new(BufWriter::new(file), w, h, &[])
            .map_err(|e| gif_err(tmp.path(), e))?;
        encoder
            .set_repeat(gif::Repeat::Infinite)
            .map_err(|e| gif_err(tmp.path(), e))?;
        Ok(GifSink {
            target: path.to_path_buf(),
            width: w,
            height: h,
            fps,
            encoder,
            tmp,
        })
    }

    pub(crate) fn push(&mut self, rgb: &[u8], index: usize) -> Result<(), VideoError> {
        // The length was checked by the writer, so from_rgb_speed's assertion cannot fire.
        let mut frame = gif::Frame::from_rgb_speed(self.width, self.height, rgb, QUANT_SPEED);
        frame.delay = delay_cs(index, self.fps);
        self.encoder
            .write_frame(&frame)
            .map_err(|e| gif_err(self.tmp.path(), e))
    }

    pub(crate) fn finish(self) -> Result<(), VideoError> {
        let GifSink {
            target,
            encoder,
            tmp,
            ..
        } = self;
        let writer = encoder.into_inner().map_err(|e| gif_err(tmp.path(), e))?;
        let file = writer
            .into_inner()
            .map_err(|e| VideoError::io(tmp.path(), e.into_error()))?;
        file.sync_all().map_err(|e| VideoError::io(tmp.path(), e))?;
        drop(file);
        check_file_target(&target)?;
        tmp.persist(&target)
    }
}
