//! Reading videos as users have them: one streaming reader for every command.
//!
//! ```no_run
//! use gagavatar_video::read::{ReadOptions, VideoReader};
//! # fn main() -> Result<(), gagavatar_video::VideoError> {
//! let mut reader = VideoReader::open("clip.mov".as_ref(), &ReadOptions::default())?;
//! let meta = reader.meta().clone(); // size after rotation, fps, frame count, codec, ...
//! for frame in &mut reader {
//!     let frame = frame?; // Frame { index, pts (seconds), source_pts, rgb: image::RgbImage }
//!     assert_eq!((frame.rgb.width(), frame.rgb.height()), (meta.width, meta.height));
//! }
//! # Ok(()) }
//! ```
//!
//! What is read, decided by the content (never the name):
//! - **A video file**, through the `ffmpeg` program when it is on PATH (H.264 of any profile,
//!   HEVC, VP9, AV1, ProRes, ... in mp4 / mov / mkv / webm / avi): `ffprobe` for the metadata,
//!   one `ffmpeg` child streaming raw RGB frames over a pipe (see `ffmpeg.rs`). Rotated phone
//!   videos come out upright; variable-frame-rate clips give every frame once, at its own time;
//!   timestamps equal `ffprobe -show_frames`' `best_effort_timestamp_time`.
//! - Without ffmpeg, the **built-in OpenH264 decoder** reads H.264 Baseline in mp4 / mov (every
//!   mp4 this crate writes). Any other stream is refused before decoding, in one line that names
//!   what the file holds and how to install ffmpeg ([`VideoError::NeedsFfmpeg`]).
//! - **A folder of images** (png, jpg, webp, bmp; natural name order, so `frame2` comes before
//!   `frame10`) or **a single image**, shown at [`ReadOptions::fps`] (default 25).
//!
//! Memory stays bounded: frames are decoded one at a time (a 10-minute 1080p clip streams in a
//! few frames' worth of memory). Dropping the reader stops and reaps the ffmpeg child.
//!
//! Options apply in this order: [`Start`], then `fps` resampling, then `max_frames`. With `fps`
//! set (videos only), output frame k stands for time `t0 + k / fps`, `t0` the first frame's
//! pts, and shows the last source frame whose pts is at or before that time; output times run
//! while they are before the end of the last frame (its pts plus the interval before it). So
//! 30 -> 15 fps keeps every other frame, 25 -> 50 fps shows every frame twice, and the source's
//! own rate gives the source's frames.
//!
//! A read that cannot give the whole requested stream fails (a truncated or damaged file, a
//! start past the end, a video with no frames) rather than quietly ending early: the last item
//! is an error.

mod ffmpeg;
mod h264_params;
mod images;
mod openh264_reader;
mod source;

use std::path::Path;

pub use ffmpeg::{find_ffmpeg, FfmpegTools};
pub use images::{list_images, natural_cmp, IMAGE_EXTENSIONS};
pub use source::{
    Decoder, DecoderChoice, Frame, ReadOptions, Start, VideoMeta, DEFAULT_IMAGE_FPS, PTS_EPS,
};
pub(crate) use source::{RawFrame, Source};

use crate::VideoError;

fn ffmpeg_install_hint() -> &'static str {
    "install it (Debian/Ubuntu: sudo apt install ffmpeg; macOS: brew install ffmpeg; \
     Windows: winget install ffmpeg) and run again"
}

/// The decoder that reads `path`, decided from its first bytes and the options.
enum Plan {
    Images(Vec<std::path::PathBuf>),
    Ffmpeg(FfmpegTools, ffmpeg::Probe),
    OpenH264(Box<openh264_reader::Plan>),
}

fn check_options(opts: &ReadOptions) -> Result<(), VideoError> {
    if let Some(fps) = opts.fps {
        if !(fps.is_finite() && fps > 0.0 && fps <= crate::MAX_FPS) {
            return Err(VideoError::BadFps { fps });
        }
    }
    if let Start::Seconds(t) = opts.start {
        if !(t.is_finite() && t >= 0.0) {
            return Err(VideoError::BadOption(format!(
                "start time {t} s: it must be a finite number of seconds, at least 0"
            )));
        }
    }
    if opts.max_frames == Some(0) {
        return Err(VideoError::BadOption(
            "max frames 0 would read nothing: give at least 1".into(),
        ));
    }
    if opts.threads == Some(0) {
        return Err(VideoError::BadOption("threads must be at least 1".into()));
    }
    Ok(())
}

fn plan(path: &Path, opts: &ReadOptions) -> Result<Plan, VideoError> {
    check_options(opts)?;
    let meta = std::fs::metadata(path).map_err(|e| VideoError::io(path, e))?;
    if meta.is_dir() {
        return Ok(Plan::Images(list_images(path)?));
    }
    // Enough for the track headers of Matroska and AVI files, to name their codec.
    let mut head = vec![0u8; 64 << 10];
    let n = {
        use std::io::Read;
        let mut f = std::fs::File::open(path).map_err(|e| VideoError::io(path, e))?;
        let mut n = 0;
        while n < head.len() {
            match f.read(&mut head[n..]) {
                Ok(0) => break,
                Ok(k) => n += k,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(VideoError::io(path, e)),
            }
        }
        n
    };
    let head = &head[..n];
    if head.is_empty() {
        return Err(VideoError::NotVideo {
            path: path.to_path_buf(),
            reason: "the file is empty".into(),
        });
    }
    if gagavatar_formats::image::sniff(head).is_some() {
        return Ok(Plan::Images(vec![path.to_path_buf()]));
    }
    let tools = match opts.decoder {
        DecoderChoice::OpenH264 => None,
        _ => find_ffmpeg(None),
    };
    if let Some(tools) = tools {
        let probe = ffmpeg::probe(&tools, path)?;
        return Ok(Plan::Ffmpeg(tools, probe));
    }
    if opts.decoder == DecoderChoice::Ffmpeg {
        return Err(VideoError::NeedsFfmpeg {
            path: path.to_path_buf(),
            what: "reading with --decoder ffmpeg".into(),
            why: format!(", which is not on PATH; {}", ffmpeg_install_hint()),
        });
    }
    match openh264_reader::plan(path, head) {
        Ok(p) => Ok(Plan::OpenH264(Box::new(p))),
        Err(openh264_reader::Refusal::Error(e)) => Err(e),
        Err(openh264_reader::Refusal::NeedsFfmpeg(what)) => Err(VideoError::NeedsFfmpeg {
            path: path.to_path_buf(),
            what,
            why: if opts.decoder == DecoderChoice::OpenH264 {
                "; the built-in decoder (--decoder openh264) reads H.264 Baseline only".into()
            } else {
                format!(
                    ", which is not on PATH (the built-in decoder reads H.264 Baseline only); {}",
                    ffmpeg_install_hint()
                )
            },
        }),
    }
}

/// Metadata only, without starting to decode (for `video info`). For a video whose container
/// stores no frame count, `count_frames` reads its packets (no decoding) to find it.
pub fn probe(path: &Path, opts: &ReadOptions, count_frames: bool) -> Result<VideoMeta, VideoError> {
    match plan(path, opts)? {
        Plan::Images(files) => Ok(images::ImagesSource::open(
            path,
            files,
            opts.fps.unwrap_or(DEFAULT_IMAGE_FPS),
            Start::Frame(0),
        )?
        .1),
        Plan::Ffmpeg(tools, mut probe) => {
            if count_frames && probe.meta.frames.is_none() {
                probe.meta.frames = Some(ffmpeg::count_packets(&tools, path, probe.stream_index)?);
            }
            Ok(probe.meta)
        }
        Plan::OpenH264(p) => Ok(p.meta),
    }
}

/// Frames of a video, a folder of images or an image, one at a time; see the module docs.
pub struct VideoReader {
    path: std::path::PathBuf,
    meta: VideoMeta,
    source: Box<dyn Source>,
    opts: ReadOptions,
    /// Resampling: the frame shown until the next one's time, and the one after it.
    held: Option<RawFrame>,
    ahead: Option<RawFrame>,
    /// Output time origin and the last source interval (for the end of the last frame).
    t0: Option<f64>,
    interval: Option<f64>,
    source_done: bool,
    emitted: u64,
    finished: bool,
}

impl VideoReader {
    /// Opens `path` (a video file, a folder of images or an image). Errors here are about the
    /// file as a whole: missing, not a video, a codec that needs ffmpeg when it is absent.
    pub fn open(path: &Path, opts: &ReadOptions) -> Result<Self, VideoError> {
        let (meta, source): (VideoMeta, Box<dyn Source>) = match plan(path, opts)? {
            Plan::Images(files) => {
                let fps = opts.fps.unwrap_or(DEFAULT_IMAGE_FPS);
                let (src, meta) = images::ImagesSource::open(path, files, fps, opts.start)?;
                (meta, Box::new(src))
            }
            Plan::Ffmpeg(tools, probe) => {
                check_start(path, opts.start, &probe.meta)?;
                let src =
                    ffmpeg::FfmpegSource::spawn(&tools, path, &probe, opts.start, opts.threads)?;
                (probe.meta, Box::new(src))
            }
            Plan::OpenH264(p) => {
                let meta = p.meta.clone();
                check_start(path, opts.start, &meta)?;
                let src = openh264_reader::OpenH264Source::new(path, *p, opts.start)?;
                (meta, Box::new(src))
            }
        };
        let mut opts = opts.clone();
        if meta.decoder == Decoder::Image {
            // For images `fps` is the rate they are shown at, not a resampling.
            opts.fps = None;
        }
        Ok(VideoReader {
            path: path.to_path_buf(),
            meta,
            source,
            opts,
            held: None,
            ahead: None,
            t0: None,
            interval: None,
            source_done: false,
            emitted: 0,
            finished: false,
        })
    }

    pub fn meta(&self) -> &VideoMeta {
        &self.meta
    }

    /// The ffmpeg child's process id while it runs (tests check it is gone after a drop).
    #[doc(hidden)]
    pub fn ffmpeg_pid(&self) -> Option<u32> {
        self.source.child_pid()
    }

    /// The frame rate of what this reader returns: the resampling rate, else the source's.
    pub fn output_fps(&self) -> f64 {
        self.opts.fps.unwrap_or(self.meta.fps)
    }

    /// How many frames this reader will return, when that can be known before reading (for a
    /// progress bar; the count read is what counts).
    pub fn expected_frames(&self) -> Option<u64> {
        let total = match self.opts.fps {
            None => {
                let n = self.meta.frames?;
                let skip = match self.opts.start {
                    Start::Frame(i) => i,
                    Start::Seconds(t) => (t * self.meta.fps).round() as u64,
                };
                n.saturating_sub(skip)
            }
            Some(fps) => {
                let d = self.meta.duration?;
                let t = match self.opts.start {
                    Start::Frame(i) if self.meta.fps > 0.0 => i as f64 / self.meta.fps,
                    Start::Frame(_) => 0.0,
                    Start::Seconds(t) => t,
                };
                ((d - t).max(0.0) * fps).round() as u64
            }
        };
        Some(self.opts.max_frames.map_or(total, |m| m.min(total)))
    }

    fn pull(&mut self) -> Result<Option<RawFrame>, VideoError> {
        if self.source_done {
            return Ok(None);
        }
        match self.source.next_frame() {
            Some(Ok(f)) => Ok(Some(f)),
            Some(Err(e)) => {
                self.source_done = true;
                Err(e)
            }
            None => {
                self.source_done = true;
                Ok(None)
            }
        }
    }

    fn next_plain(&mut self) -> Result<Option<(f64, RawFrame)>, VideoError> {
        Ok(self.pull()?.map(|f| (f.pts, f)))
    }

    /// The next resampled frame: output time `t`, and the last source frame at or before it.
    fn next_resampled(&mut self, fps: f64) -> Result<Option<(f64, RawFrame)>, VideoError> {
        if self.held.is_none() {
            match self.pull()? {
                Some(f) => {
                    self.t0 = Some(f.pts);
                    self.held = Some(f);
                }
                None => return Ok(None),
            }
        }
        let t = self.t0.unwrap_or(0.0) + self.emitted as f64 / fps;
        loop {
            if self.ahead.is_none() && !self.source_done {
                self.ahead = self.pull()?;
            }
            match &self.ahead {
                // A later frame is due at or before t: it replaces the held one.
                Some(a) if a.pts <= t + PTS_EPS => {
                    let next = self.ahead.take();
                    if let (Some(h), Some(n)) = (&self.held, &next) {
                        if n.pts > h.pts {
                            self.interval = Some(n.pts - h.pts);
                        }
                    }
                    self.held = next;
                }
                Some(_) => break,
                None => {
                    // After the last frame: output times run until it ends.
                    let held = self.held.as_ref().map_or(0.0, |h| h.pts);
                    let last = self.interval.unwrap_or(if self.meta.fps > 0.0 {
                        1.0 / self.meta.fps
                    } else {
                        1.0 / fps
                    });
                    if t >= held + last - PTS_EPS {
                        return Ok(None);
                    }
                    break;
                }
            }
        }
        let Some(h) = &self.held else {
            return Ok(None);
        };
        Ok(Some((
            t,
            RawFrame {
                pts: h.pts,
                rgb: h.rgb.clone(),
            },
        )))
    }

    fn step(&mut self) -> Result<Option<Frame>, VideoError> {
        if self.opts.max_frames.is_some_and(|m| self.emitted >= m) {
            return Ok(None);
        }
        let next = match self.opts.fps {
            None => self.next_plain()?,
            Some(fps) => self.next_resampled(fps)?,
        };
        let Some((pts, raw)) = next else {
            if self.emitted == 0 {
                return Err(if self.opts.start == Start::Frame(0) {
                    VideoError::NoVideoFrames {
                        path: self.path.clone(),
                        reason: "no frame decodes".into(),
                    }
                } else {
                    past_end(&self.path, self.opts.start, &self.meta)
                });
            }
            return Ok(None);
        };
        let frame = Frame {
            index: self.emitted,
            pts,
            source_pts: raw.pts,
            rgb: raw.rgb,
        };
        self.emitted += 1;
        Ok(Some(frame))
    }
}

/// A frame-index start past a known frame count fails before anything is decoded.
fn check_start(path: &Path, start: Start, meta: &VideoMeta) -> Result<(), VideoError> {
    match (start, meta.frames) {
        (Start::Frame(n), Some(total)) if total > 0 && n >= total => {
            Err(past_end(path, start, meta))
        }
        _ => Ok(()),
    }
}

fn past_end(path: &Path, start: Start, meta: &VideoMeta) -> VideoError {
    let length = match (meta.frames, meta.duration) {
        (Some(n), Some(d)) => format!("it has {n} frames, {d:.2} s"),
        (Some(n), None) => format!("it has {n} frames"),
        (None, Some(d)) => format!("it lasts {d:.2} s"),
        (None, None) => "it is shorter".into(),
    };
    VideoError::NoVideoFrames {
        path: path.to_path_buf(),
        reason: format!("no frames at or after the start ({start}): {length}"),
    }
}

impl Iterator for VideoReader {
    type Item = Result<Frame, VideoError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.finished {
            return None;
        }
        match self.step() {
            Ok(Some(f)) => Some(Ok(f)),
            Ok(None) => {
                self.finished = true;
                None
            }
            Err(e) => {
                self.finished = true;
                Some(Err(e))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::RgbImage;

    /// A source of blank frames at given timestamps, each frame's first pixel = its number.
    struct Fake {
        pts: Vec<f64>,
        next: usize,
    }
    impl Source for Fake {
        fn next_frame(&mut self) -> Option<Result<RawFrame, VideoError>> {
            let i = self.next;
            let &pts = self.pts.get(i)?;
            self.next += 1;
            let mut rgb = RgbImage::new(1, 1);
            rgb.as_mut()[0] = i as u8;
            Some(Ok(RawFrame { pts, rgb }))
        }
    }

    fn reader(pts: Vec<f64>, fps: Option<f64>, max: Option<u64>, source_fps: f64) -> VideoReader {
        VideoReader {
            path: "fake".into(),
            meta: VideoMeta {
                width: 1,
                height: 1,
                fps: source_fps,
                frames: Some(pts.len() as u64),
                duration: None,
                codec: "fake".into(),
                profile: None,
                rotation: 0,
                start_time: 0.0,
                decoder: Decoder::Ffmpeg,
            },
            source: Box::new(Fake { pts, next: 0 }),
            opts: ReadOptions {
                fps,
                max_frames: max,
                ..ReadOptions::default()
            },
            held: None,
            ahead: None,
            t0: None,
            interval: None,
            source_done: false,
            emitted: 0,
            finished: false,
        }
    }

    /// (source frame number, output pts) of everything read.
    fn run(r: VideoReader) -> Vec<(u8, f64)> {
        r.map(|f| {
            let f = f.unwrap();
            (f.rgb.as_raw()[0], f.pts)
        })
        .collect()
    }

    fn at(n: usize, fps: f64) -> Vec<f64> {
        (0..n).map(|i| i as f64 / fps).collect()
    }

    #[test]
    fn own_rate_gives_the_source_frames() {
        let out = run(reader(at(10, 30.0), Some(30.0), None, 30.0));
        assert_eq!(
            out.iter().map(|o| o.0).collect::<Vec<_>>(),
            (0..10).collect::<Vec<u8>>()
        );
    }

    #[test]
    fn halving_keeps_every_other_frame() {
        let out = run(reader(at(60, 30.0), Some(15.0), None, 30.0));
        let frames: Vec<u8> = out.iter().map(|o| o.0).collect();
        assert_eq!(frames, (0..60).step_by(2).collect::<Vec<u8>>());
        for (k, (_, t)) in out.iter().enumerate() {
            assert!((t - k as f64 / 15.0).abs() < 1e-12, "output {k}: pts {t}");
        }
    }

    #[test]
    fn doubling_shows_every_frame_twice() {
        let out = run(reader(at(50, 25.0), Some(50.0), None, 25.0));
        let frames: Vec<u8> = out.iter().map(|o| o.0).collect();
        let expected: Vec<u8> = (0..50).flat_map(|i| [i, i]).collect();
        assert_eq!(frames, expected);
    }

    #[test]
    fn variable_rate_picks_the_last_frame_at_or_before_each_time() {
        // Frames at 0, 0.1, 0.15, 0.5 s; 10 fps output: t = 0, .1, .2, .3, .4, .5
        // (the last frame lasts as long as the interval before it, 0.35 s: until 0.85).
        let out = run(reader(vec![0.0, 0.1, 0.15, 0.5], Some(10.0), None, 8.0));
        let frames: Vec<u8> = out.iter().map(|o| o.0).collect();
        assert_eq!(frames, vec![0, 1, 2, 2, 2, 3, 3, 3, 3]);
    }

    #[test]
    fn max_frames_counts_output_frames() {
        let out = run(reader(at(50, 25.0), Some(50.0), Some(7), 25.0));
        assert_eq!(out.len(), 7);
        let out = run(reader(at(50, 25.0), None, Some(3), 25.0));
        assert_eq!(out.iter().map(|o| o.0).collect::<Vec<_>>(), vec![0, 1, 2]);
    }

    #[test]
    fn an_empty_source_is_an_error() {
        let mut r = reader(vec![], None, None, 25.0);
        assert!(matches!(
            r.next(),
            Some(Err(VideoError::NoVideoFrames { .. }))
        ));
        assert!(r.next().is_none());
    }

    #[test]
    fn start_parses_frames_and_times() {
        assert_eq!("120".parse::<Start>(), Ok(Start::Frame(120)));
        assert_eq!("4.5s".parse::<Start>(), Ok(Start::Seconds(4.5)));
        assert_eq!("1:02.5".parse::<Start>(), Ok(Start::Seconds(62.5)));
        assert_eq!("1:00:02".parse::<Start>(), Ok(Start::Seconds(3602.0)));
        for bad in ["", "-3", "abc", "1:75", "nans", "infs", "-1s", "1:2:3:4"] {
            assert!(bad.parse::<Start>().is_err(), "{bad:?} accepted");
        }
    }
}
