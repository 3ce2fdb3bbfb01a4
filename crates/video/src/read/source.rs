//! What every decoding backend (ffmpeg, OpenH264, images) and the reader share: the options,
//! the metadata, the frames, and the `Source` each backend implements.

use std::str::FromStr;

use image::RgbImage;

use crate::VideoError;

/// Timestamps closer than this are the same instant: far below any frame interval (a 1 MHz
/// rate), far above the rounding of tick counts times a time base in f64.
pub const PTS_EPS: f64 = 1e-6;

/// The frame rate of image sequences when none is given.
pub const DEFAULT_IMAGE_FPS: f64 = 25.0;

/// Where reading starts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Start {
    /// The first frame with this index (0-based, in presentation order).
    Frame(u64),
    /// The first frame whose pts is at least this many seconds after the stream's start.
    Seconds(f64),
}

impl Default for Start {
    fn default() -> Self {
        Start::Frame(0)
    }
}

impl FromStr for Start {
    type Err = String;

    /// `120` is frame 120; `4.5s`, `1:02.5` (m:s) and `0:01:02.5` (h:m:s) are times.
    fn from_str(s: &str) -> Result<Self, String> {
        let s = s.trim();
        let bad = || {
            format!(
                "`{s}` is not a start: give a frame index (120) or a time (4.5s, 1:02.5, 0:01:02.5)"
            )
        };
        if let Ok(n) = s.parse::<u64>() {
            return Ok(Start::Frame(n));
        }
        let secs = if let Some(t) = s.strip_suffix('s') {
            t.trim().parse::<f64>().map_err(|_| bad())?
        } else if s.contains(':') {
            let parts: Vec<&str> = s.split(':').collect();
            if parts.len() > 3 {
                return Err(bad());
            }
            let mut total = 0.0;
            for (i, p) in parts.iter().enumerate() {
                let v: f64 = p.trim().parse().map_err(|_| bad())?;
                if v < 0.0 || (i > 0 && v >= 60.0) {
                    return Err(bad());
                }
                total = total * 60.0 + v;
            }
            total
        } else {
            return Err(bad());
        };
        if !(secs.is_finite() && secs >= 0.0) {
            return Err(bad());
        }
        Ok(Start::Seconds(secs))
    }
}

impl std::fmt::Display for Start {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Start::Frame(n) => write!(f, "frame {n}"),
            Start::Seconds(t) => write!(f, "{t} s"),
        }
    }
}

/// Which decoder reads a video file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DecoderChoice {
    /// ffmpeg when it is on PATH, else the built-in OpenH264 path.
    #[default]
    Auto,
    /// ffmpeg, or an error saying how to install it.
    Ffmpeg,
    /// The built-in path only (refuses what it cannot decode correctly).
    OpenH264,
}

impl FromStr for DecoderChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "auto" => Ok(DecoderChoice::Auto),
            "ffmpeg" => Ok(DecoderChoice::Ffmpeg),
            "openh264" | "builtin" | "built-in" => Ok(DecoderChoice::OpenH264),
            _ => Err(format!("`{s}` is not a decoder: auto, ffmpeg or openh264")),
        }
    }
}

/// How to read.
#[derive(Debug, Clone, PartialEq)]
pub struct ReadOptions {
    pub start: Start,
    /// Stop after this many frames (after resampling).
    pub max_frames: Option<u64>,
    /// For a video: resample to this rate by timestamps (see the module docs). For images: the
    /// rate they are shown at ([`DEFAULT_IMAGE_FPS`] when `None`).
    pub fps: Option<f64>,
    /// Decoder threads for ffmpeg (`None`: ffmpeg's choice, all cores).
    pub threads: Option<usize>,
    pub decoder: DecoderChoice,
}

impl Default for ReadOptions {
    fn default() -> Self {
        ReadOptions {
            start: Start::Frame(0),
            max_frames: None,
            fps: None,
            threads: None,
            decoder: DecoderChoice::Auto,
        }
    }
}

/// Who decodes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Decoder {
    Ffmpeg,
    OpenH264,
    /// A still image or a folder of them.
    Image,
}

impl Decoder {
    pub fn as_str(self) -> &'static str {
        match self {
            Decoder::Ffmpeg => "ffmpeg",
            Decoder::OpenH264 => "openh264",
            Decoder::Image => "image",
        }
    }
}

/// What a video is, as stored (before `start`, `fps` or `max_frames`).
#[derive(Debug, Clone, PartialEq)]
pub struct VideoMeta {
    /// Size of the frames the reader gives: after rotation (a portrait phone clip is taller than
    /// wide).
    pub width: u32,
    pub height: u32,
    /// Average frames per second (frames / duration); 0 when the file does not say.
    pub fps: f64,
    /// The container's frame count, when it stores one (mp4, mov, avi; not always mkv / webm).
    pub frames: Option<u64>,
    /// Seconds.
    pub duration: Option<f64>,
    /// ffmpeg's codec name (`h264`, `hevc`, `vp9`, `av1`, `prores`, ...; `png` / `jpeg` / ...
    /// for images).
    pub codec: String,
    /// `High`, `Main 10`, `Constrained Baseline`, ... when known.
    pub profile: Option<String>,
    /// Degrees clockwise the stored frames are turned for display (0, 90, 180, 270); frames
    /// are returned already turned. A phone held upright records 90.
    pub rotation: u32,
    /// The first frame's timestamp in seconds (`Start::Seconds` counts from it).
    pub start_time: f64,
    pub decoder: Decoder,
}

impl VideoMeta {
    fn json_view(&self) -> MetaJson<'_> {
        MetaJson {
            width: self.width,
            height: self.height,
            fps: self.fps,
            frames: self.frames,
            duration: self.duration,
            codec: &self.codec,
            profile: self.profile.as_deref(),
            rotation: self.rotation,
            start_time: self.start_time,
            decoder: self.decoder.as_str(),
        }
    }

    /// The metadata as a JSON object (`width`, `height`, `fps`, `frames`, `duration`, `codec`,
    /// `profile`, `rotation`, `start_time`, `decoder`; unknown values are null).
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::to_value(self.json_view()).unwrap_or(serde_json::Value::Null)
    }

    /// The same object as pretty-printed text with the fields in that order, as
    /// `gagavatar video info` prints it.
    pub fn to_json_string(&self) -> String {
        serde_json::to_string_pretty(&self.json_view()).unwrap_or_default()
    }
}

#[derive(serde::Serialize)]
struct MetaJson<'a> {
    width: u32,
    height: u32,
    fps: f64,
    frames: Option<u64>,
    duration: Option<f64>,
    codec: &'a str,
    profile: Option<&'a str>,
    rotation: u32,
    start_time: f64,
    decoder: &'a str,
}

/// One frame as read.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Position in what this reader returns: 0, 1, 2, ... (after start and resampling).
    pub index: u64,
    /// Presentation time in seconds: the source frame's timestamp, or with `fps` resampling the
    /// output time `t0 + index / fps`.
    pub pts: f64,
    /// The timestamp of the source frame shown (equal to `pts` without resampling).
    pub source_pts: f64,
    /// Upright RGB, `meta().width` x `meta().height`.
    pub rgb: RgbImage,
}

/// A decoded frame before resampling.
pub(crate) struct RawFrame {
    pub pts: f64,
    pub rgb: RgbImage,
}

/// A stream of decoded frames in presentation order, already started at the requested
/// [`Start`].
pub(crate) trait Source: Send {
    fn next_frame(&mut self) -> Option<Result<RawFrame, VideoError>>;
    /// The decoding process, for sources that run one.
    fn child_pid(&self) -> Option<u32> {
        None
    }
}

/// Why a file's first bytes are not a video, in words.
pub(crate) fn not_video_reason(head: &[u8]) -> String {
    if head.is_empty() {
        return "the file is empty".into();
    }
    let printable = head
        .iter()
        .filter(|&&b| b == b'\n' || b == b'\r' || b == b'\t' || (0x20..0x7f).contains(&b))
        .count();
    if printable * 10 >= head.len() * 9 {
        "not a video or image: it holds text".into()
    } else {
        "not a video or image file this program recognises".into()
    }
}
