//! Videos in and out.
//!
//! **Reading** ([`read`]): every command reads videos through [`read::VideoReader`], a streaming
//! iterator of upright RGB frames with timestamps, plus metadata ([`read::VideoMeta`]). It uses
//! the `ffmpeg` program when it is on PATH (any codec and container), else the bundled OpenH264
//! decoder for H.264 Baseline mp4 (what this crate writes), and also takes folders of images and
//! single images. See the [`read`] module for the rules (start, fps resampling, errors).
//!
//! **Writing** (`gagavatar reenact` / `orbit`): frames in, a finished file out, written by this
//! crate alone (no ffmpeg or other external tool). The format follows the output path (see [`VideoFormat::from_path`]):
//! - `.mp4`: H.264 Constrained Baseline, yuv420p (BT.601 limited range, signalled in the SPS),
//!   a keyframe at least every 2 s, `moov` before `mdat` so browsers start playing at once.
//!   H.264 4:2:0 cannot code odd sizes, so an odd width or height is padded by one pixel that
//!   repeats the last column or row (a 511x383 input gives a 512x384 video).
//! - `.gif`: one 256-colour palette per frame, looping forever; delays are whole centiseconds
//!   that keep the average rate (30 fps: 3, 4, 3, ...), at least 2 cs because browsers slow
//!   shorter ones down, so above 50 fps a GIF plays at 50.
//! - anything else: a folder of `frame_00000.png`, `frame_00001.png`, ... (exact pixels). An
//!   existing empty folder is reused; a non-empty one is refused rather than mixed into.
//!
//! Nothing partial is ever left at the output path: everything is written beside it under a
//! hidden temporary name (`.NAME.tmpPID.N`, and `.NAME.mdat.tmpPID.N` for the mp4 samples) and
//! renamed into place by [`VideoWriter::finish`]. A writer dropped without `finish` (an error, a
//! panic, or Ctrl-C turned into an orderly exit by the caller) removes its temporary files; a
//! process killed outright cannot, and then only those hidden files remain.
//!
//! A visible "AI-generated" label is drawn on every frame unless [`VideoOptions::watermark`] is
//! false (the paper's ethics statement commits to marking generated videos).

use std::path::{Path, PathBuf};

mod gif_out;
mod h264;
pub mod mp4;
mod png_dir;
pub mod read;
mod temp;
mod watermark;
mod yuv;

pub use watermark::{draw_watermark, watermark_rect, WATERMARK_TEXT};

/// The largest frame rate accepted: above it GIF delays and H.264 levels stop making sense, and a
/// larger value is almost certainly a units mistake.
pub const MAX_FPS: f64 = 1000.0;

/// Every message names the file it is about. Causes are part of the message and deliberately not
/// a `source()`: callers print errors with their chain (`{:#}`), which would show them twice.
#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    #[error("{}: {err}", path.display())]
    Io { path: PathBuf, err: std::io::Error },
    #[error("frame has {got} bytes, expected {expected} (width * height * 3, RGB u8)")]
    BadFrame { expected: usize, got: usize },
    #[error("invalid video size {width}x{height}: {reason}")]
    BadSize {
        width: usize,
        height: usize,
        reason: String,
    },
    #[error("invalid frame rate {fps}: it must be a finite number of frames per second in (0, {MAX_FPS}]")]
    BadFps { fps: f64 },
    #[error("{}: {reason}", path.display())]
    BadPath { path: PathBuf, reason: String },
    #[error("no frames were given for {}; nothing was written", path.display())]
    NoFrames { path: PathBuf },
    #[error("encoding failed: {0}")]
    Encode(String),
    /// A file that is not a well-formed video of the kind expected (reading an mp4 back); the
    /// message starts with the file's path.
    #[error("{0}")]
    Format(String),
    #[error("decoding failed: {0}")]
    Decode(String),
    /// A video the built-in decoder cannot read correctly, where ffmpeg is absent (or was not
    /// chosen): `what` it holds, and `why` ffmpeg was not used, with how to install it.
    #[error("{}: {what} needs ffmpeg{why}", path.display())]
    NeedsFfmpeg {
        path: PathBuf,
        what: String,
        why: String,
    },
    /// ffmpeg or ffprobe failed; `message` is their own first error line.
    #[error("{}: {message}", path.display())]
    Ffmpeg { path: PathBuf, message: String },
    /// Not a video, a folder of images or an image.
    #[error("{}: {reason}", path.display())]
    NotVideo { path: PathBuf, reason: String },
    /// A video with nothing to read: no video stream, no frames, or a start past its end.
    #[error("{}: no video frames: {reason}", path.display())]
    NoVideoFrames { path: PathBuf, reason: String },
    /// A video cut short or broken: fewer frames decode than it holds.
    #[error("{}: the video is truncated or damaged: {reason}", path.display())]
    Damaged { path: PathBuf, reason: String },
    /// A reading option out of range.
    #[error("{0}")]
    BadOption(String),
}

impl VideoError {
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        VideoError::Io {
            path: path.to_path_buf(),
            err: source,
        }
    }
}

/// Frames as read, written unchanged (no watermark: they are the user's own) as
/// `frame_000000.png`, `frame_000001.png`, ... in a folder that appears complete or not at all
/// (built under a hidden sibling name, renamed by [`FrameFolder::finish`]; an existing empty
/// folder is reused, a non-empty one refused).
pub struct FrameFolder {
    sink: png_dir::PngDirSink,
    width: u32,
    height: u32,
    frames: usize,
}

impl FrameFolder {
    pub fn create(path: &Path, width: u32, height: u32) -> Result<Self, VideoError> {
        Ok(FrameFolder {
            sink: png_dir::PngDirSink::create(path, width as usize, height as usize, 6)?,
            width,
            height,
            frames: 0,
        })
    }

    /// The name frame `index` gets.
    pub fn frame_name(index: usize) -> String {
        png_dir::frame_name(index, 6)
    }

    pub fn push(&mut self, rgb: &image::RgbImage) -> Result<(), VideoError> {
        if (rgb.width(), rgb.height()) != (self.width, self.height) {
            return Err(VideoError::BadFrame {
                expected: self.width as usize * self.height as usize * 3,
                got: rgb.as_raw().len(),
            });
        }
        self.sink.push(rgb.as_raw(), self.frames)?;
        self.frames += 1;
        Ok(())
    }

    /// Adds another file (an index of the frames, say) to the folder.
    pub fn add_file(&self, name: &str, bytes: &[u8]) -> Result<(), VideoError> {
        self.sink.add_file(name, bytes)
    }

    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Moves the folder into place; with no frames written nothing is.
    pub fn finish(self) -> Result<(), VideoError> {
        if self.frames == 0 {
            return Err(VideoError::NoFrames {
                path: self.sink.target().to_path_buf(),
            });
        }
        self.sink.finish()
    }
}

/// Container chosen from the output path.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VideoFormat {
    Mp4,
    Gif,
    PngDir,
}

impl VideoFormat {
    /// `.mp4` (any case) is [`VideoFormat::Mp4`], `.gif` (any case) is [`VideoFormat::Gif`], and
    /// anything else, including a path ending in `/`, is a folder of PNGs.
    pub fn from_path(path: &Path) -> VideoFormat {
        // `Path` drops a trailing separator ("out.mp4/" has extension "mp4"), but the user asked
        // for a directory.
        let s = path.as_os_str().to_string_lossy();
        if s.ends_with('/') || s.ends_with(std::path::MAIN_SEPARATOR) {
            return VideoFormat::PngDir;
        }
        match path.extension().and_then(|e| e.to_str()) {
            Some(e) if e.eq_ignore_ascii_case("mp4") => VideoFormat::Mp4,
            Some(e) if e.eq_ignore_ascii_case("gif") => VideoFormat::Gif,
            _ => VideoFormat::PngDir,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VideoOptions {
    /// Frames per second, finite, in (0, [`MAX_FPS`]].
    pub fps: f64,
    /// Draw [`WATERMARK_TEXT`] on every frame (on by default).
    pub watermark: bool,
}

impl Default for VideoOptions {
    fn default() -> Self {
        VideoOptions {
            fps: 25.0,
            watermark: true,
        }
    }
}

enum Sink {
    // Boxed: OpenH264's encoder state is several KiB.
    Mp4(Box<mp4::Mp4Sink>),
    Gif(gif_out::GifSink),
    Png(png_dir::PngDirSink),
}

/// Writes frames to a video file or PNG folder; see the crate docs for the formats.
pub struct VideoWriter {
    path: PathBuf,
    width: usize,
    height: usize,
    opts: VideoOptions,
    frames: usize,
    sink: Sink,
    /// Watermarked copy of the current frame (the caller's frame is left untouched).
    marked: Vec<u8>,
}

impl VideoWriter {
    /// Starts a video at `path` (format from [`VideoFormat::from_path`]) of `width` x `height`
    /// RGB frames. Checks the options and creates the temporary output beside `path` at once, so
    /// a bad size, frame rate or directory fails before any frame is rendered.
    pub fn create(
        path: &Path,
        width: usize,
        height: usize,
        opts: VideoOptions,
    ) -> Result<Self, VideoError> {
        if !(opts.fps.is_finite() && opts.fps > 0.0 && opts.fps <= MAX_FPS) {
            return Err(VideoError::BadFps { fps: opts.fps });
        }
        if width == 0 || height == 0 {
            return Err(VideoError::BadSize {
                width,
                height,
                reason: "width and height must be at least 1".into(),
            });
        }
        let frame_len = width
            .checked_mul(height)
            .and_then(|n| n.checked_mul(3))
            .ok_or_else(|| VideoError::BadSize {
                width,
                height,
                reason: "too large".into(),
            })?;
        let sink = match VideoFormat::from_path(path) {
            VideoFormat::Mp4 => Sink::Mp4(Box::new(mp4::Mp4Sink::create(
                path, width, height, opts.fps,
            )?)),
            VideoFormat::Gif => Sink::Gif(gif_out::GifSink::create(path, width, height, opts.fps)?),
            VideoFormat::PngDir => Sink::Png(png_dir::PngDirSink::create(path, width, height, 5)?),
        };
        Ok(VideoWriter {
            path: path.to_path_buf(),
            width,
            height,
            opts,
            frames: 0,
            sink,
            marked: if opts.watermark {
                vec![0; frame_len]
            } else {
                Vec::new()
            },
        })
    }

    /// Appends one frame: RGB u8, row-major (height, width, 3), `len == width * height * 3`.
    /// The watermark, when on, is drawn on a copy.
    pub fn push_rgb(&mut self, rgb: &[u8]) -> Result<(), VideoError> {
        let expected = self.width * self.height * 3;
        if rgb.len() != expected {
            return Err(VideoError::BadFrame {
                expected,
                got: rgb.len(),
            });
        }
        let frame = if self.opts.watermark {
            self.marked.copy_from_slice(rgb);
            draw_watermark(&mut self.marked, self.width, self.height, WATERMARK_TEXT);
            &self.marked[..]
        } else {
            rgb
        };
        match &mut self.sink {
            Sink::Mp4(s) => s.push(frame)?,
            Sink::Gif(s) => s.push(frame, self.frames)?,
            Sink::Png(s) => s.push(frame, self.frames)?,
        }
        self.frames += 1;
        Ok(())
    }

    /// Frames pushed so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    pub fn format(&self) -> VideoFormat {
        match self.sink {
            Sink::Mp4(_) => VideoFormat::Mp4,
            Sink::Gif(_) => VideoFormat::Gif,
            Sink::Png(_) => VideoFormat::PngDir,
        }
    }

    /// Completes the file and moves it to the output path (replacing an existing file; an
    /// existing non-empty directory is refused). With no frames pushed this is an error and
    /// nothing is written.
    pub fn finish(self) -> Result<(), VideoError> {
        if self.frames == 0 {
            // Dropping the sink removes its temporary output.
            return Err(VideoError::NoFrames { path: self.path });
        }
        match self.sink {
            Sink::Mp4(s) => s.finish(),
            Sink::Gif(s) => s.finish(),
            Sink::Png(s) => s.finish(),
        }
    }
}
