//! Reading through the `ffmpeg` program: `ffprobe` for the metadata, then one `ffmpeg` child
//! per reader that decodes the video stream and writes raw RGB frames to a pipe, one after the
//! other, so memory stays at a frame or two whatever the clip's length.
//!
//! Timestamps come from the same process: the `showinfo` filter logs every frame's `pts` (in the
//! filter's time base, which it also logs) on stderr, which a thread reads while the frames
//! arrive on stdout. Frame timing is passed through untouched (`-fps_mode passthrough`), so a
//! variable-frame-rate clip gives every frame once, at its own time, and `-copyts` keeps the
//! container's timestamps, so they equal what `ffprobe -show_frames` reports. ffmpeg turns
//! rotated (phone) videos upright itself.

use std::ffi::{OsStr, OsString};
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::sync::mpsc::{channel, Receiver};
use std::sync::{Mutex, OnceLock};
use std::thread::JoinHandle;

use image::RgbImage;
use serde_json::Value;

use super::source::{Decoder, RawFrame, Source, Start, VideoMeta, PTS_EPS};
use crate::VideoError;

/// The ffmpeg and ffprobe programs found on PATH, and ffmpeg's version.
#[derive(Debug, Clone, PartialEq)]
pub struct FfmpegTools {
    pub ffmpeg: PathBuf,
    pub ffprobe: PathBuf,
    /// (major, minor); development builds without a number count as the newest.
    pub version: (u32, u32),
}

/// An executable file called `name` in one of the directories of `path_var` (PATH syntax).
pub(crate) fn find_in_path(name: &str, path_var: &OsStr) -> Option<PathBuf> {
    let file = if cfg!(windows) {
        format!("{name}.exe")
    } else {
        name.to_string()
    };
    std::env::split_paths(path_var)
        .map(|dir| dir.join(&file))
        .find(|p| is_executable(p))
}

fn is_executable(p: &Path) -> bool {
    let Ok(meta) = std::fs::metadata(p) else {
        return false;
    };
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        meta.is_file() && meta.permissions().mode() & 0o111 != 0
    }
    #[cfg(not(unix))]
    {
        meta.is_file()
    }
}

/// `ffmpeg version 5.1.9-0+deb12u1 ...`, `ffmpeg version n7.1 ...`, `ffmpeg version N-1234-g...`.
pub(crate) fn parse_version(first_line: &str) -> Option<(u32, u32)> {
    let v = first_line.split_whitespace().nth(2)?;
    let v = v.strip_prefix('n').unwrap_or(v);
    let mut parts = v.split(|c: char| !c.is_ascii_digit());
    let major: u32 = match parts.next()?.parse() {
        Ok(m) => m,
        // Git snapshots ("N-112233-g...", "git-2024-...") are newer than any release.
        Err(_) => return Some((u32::MAX, 0)),
    };
    let minor = parts.next().and_then(|m| m.parse().ok()).unwrap_or(0);
    Some((major, minor))
}

/// ffmpeg and ffprobe on the PATH given (the process's PATH when `None`), looked up once per
/// PATH value. `None` when either is missing or ffmpeg does not run.
pub fn find_ffmpeg(path_var: Option<&OsStr>) -> Option<FfmpegTools> {
    type Cache = Mutex<Vec<(OsString, Option<FfmpegTools>)>>;
    static CACHE: OnceLock<Cache> = OnceLock::new();
    let path_var: OsString = match path_var {
        Some(p) => p.to_os_string(),
        None => std::env::var_os("PATH").unwrap_or_default(),
    };
    let cache = CACHE.get_or_init(|| Mutex::new(Vec::new()));
    if let Ok(c) = cache.lock() {
        if let Some((_, tools)) = c.iter().find(|(p, _)| *p == path_var) {
            return tools.clone();
        }
    }
    let tools = (|| {
        let ffmpeg = find_in_path("ffmpeg", &path_var)?;
        let ffprobe = find_in_path("ffprobe", &path_var)?;
        let out = Command::new(&ffmpeg)
            .arg("-version")
            .stdin(Stdio::null())
            .stderr(Stdio::null())
            .output()
            .ok()?;
        let text = String::from_utf8_lossy(&out.stdout);
        let version = parse_version(text.lines().next()?)?;
        Some(FfmpegTools {
            ffmpeg,
            ffprobe,
            version,
        })
    })();
    if let Ok(mut c) = cache.lock() {
        c.push((path_var, tools.clone()));
    }
    tools
}

/// What ffprobe says about the first video stream (cover pictures in audio files skipped).
pub(crate) struct Probe {
    pub meta: VideoMeta,
    /// Absolute stream index, for `-map 0:N`.
    pub stream_index: u64,
    /// The container's start time, which `--start` seconds count from.
    pub format_start: f64,
}

fn num(v: &Value) -> Option<f64> {
    match v {
        Value::Number(n) => n.as_f64(),
        Value::String(s) => s.trim().parse().ok(),
        _ => None,
    }
    .filter(|x: &f64| x.is_finite())
}

fn ratio(v: &Value) -> Option<f64> {
    let s = v.as_str()?;
    let (a, b) = s.split_once('/')?;
    let (a, b): (f64, f64) = (a.trim().parse().ok()?, b.trim().parse().ok()?);
    (a > 0.0 && b > 0.0).then_some(a / b)
}

/// `file:PATH`: a local file even when its name looks like a protocol (`a:b.mp4`) to ffmpeg.
fn file_url(path: &Path) -> OsString {
    let mut url = OsString::from("file:");
    url.push(path.as_os_str());
    url
}

/// The last line of a tool's stderr that says something, without the "PATH: " prefix ffmpeg
/// puts before file errors.
fn last_message(stderr: &[u8], path: &Path) -> String {
    let text = String::from_utf8_lossy(stderr);
    let line = text
        .lines()
        .map(str::trim)
        .rfind(|l| !l.is_empty())
        .unwrap_or("no message");
    let line = strip_log_prefix(line);
    let p = path.display().to_string();
    line.strip_prefix(&format!("file:{p}: "))
        .or_else(|| line.strip_prefix(&format!("{p}: ")))
        .unwrap_or(line)
        .to_string()
}

/// `[h264 @ 0x55...] [error] message` -> `message` (keeps the component when it helps: the
/// decoder or demuxer name).
fn strip_log_prefix(line: &str) -> &str {
    let mut rest = line.trim_start();
    while rest.starts_with('[') {
        match rest.find(']') {
            Some(end) => rest = rest[end + 1..].trim_start(),
            None => break,
        }
    }
    rest
}

/// Runs ffprobe on `path`.
pub(crate) fn probe(tools: &FfmpegTools, path: &Path) -> Result<Probe, VideoError> {
    let out = Command::new(&tools.ffprobe)
        .args([
            "-v",
            "error",
            "-print_format",
            "json",
            "-show_streams",
            "-show_format",
        ])
        .arg("-i")
        .arg(file_url(path))
        .stdin(Stdio::null())
        .output()
        .map_err(|e| VideoError::Ffmpeg {
            path: path.to_path_buf(),
            message: format!("cannot run {}: {e}", tools.ffprobe.display()),
        })?;
    if !out.status.success() {
        return Err(VideoError::NotVideo {
            path: path.to_path_buf(),
            reason: format!(
                "not a video ffmpeg can read ({})",
                last_message(&out.stderr, path)
            ),
        });
    }
    let json: Value = serde_json::from_slice(&out.stdout).map_err(|e| VideoError::Ffmpeg {
        path: path.to_path_buf(),
        message: format!("ffprobe printed something that is not JSON: {e}"),
    })?;
    let streams = json["streams"].as_array().cloned().unwrap_or_default();
    let stream = streams.iter().find(|s| {
        s["codec_type"] == "video" && s["disposition"]["attached_pic"].as_i64() != Some(1)
    });
    let Some(s) = stream else {
        let what = if streams.is_empty() {
            "it holds no streams at all (an empty or zero-frame video)"
        } else {
            "it has no video stream"
        };
        return Err(VideoError::NoVideoFrames {
            path: path.to_path_buf(),
            reason: what.into(),
        });
    };
    let codec = s["codec_name"].as_str().unwrap_or("unknown").to_string();
    let (Some(w), Some(h)) = (num(&s["width"]), num(&s["height"])) else {
        return Err(VideoError::NotVideo {
            path: path.to_path_buf(),
            reason: format!("ffprobe finds no picture size for its {codec} stream"),
        });
    };
    if w < 1.0 || h < 1.0 || w > 65535.0 || h > 65535.0 {
        return Err(VideoError::NotVideo {
            path: path.to_path_buf(),
            reason: format!("its {codec} stream has an invalid size {w}x{h}"),
        });
    }
    // Display matrix rotation is counter-clockwise in ffprobe; the old `rotate` tag clockwise.
    let ccw = s["side_data_list"]
        .as_array()
        .and_then(|l| l.iter().find_map(|d| num(&d["rotation"])))
        .or_else(|| num(&s["tags"]["rotate"]).map(|r| -r))
        .unwrap_or(0.0);
    let rotation = ((-ccw / 90.0).round() as i64).rem_euclid(4) as u32 * 90;
    let (mut width, mut height) = (w as u32, h as u32);
    if rotation % 180 == 90 {
        std::mem::swap(&mut width, &mut height);
    }
    let fps = ratio(&s["avg_frame_rate"])
        .or_else(|| ratio(&s["r_frame_rate"]))
        .unwrap_or(0.0);
    let frames = num(&s["nb_frames"])
        .filter(|&n| n >= 0.0)
        .map(|n| n as u64)
        .or_else(|| {
            // Matroska writers often store the count as a tag.
            num(&s["tags"]["NUMBER_OF_FRAMES"]).map(|n| n as u64)
        });
    let duration = num(&s["duration"])
        .or_else(|| num(&json["format"]["duration"]))
        .filter(|&d| d >= 0.0);
    let start_time = num(&s["start_time"]).unwrap_or(0.0);
    let format_start = num(&json["format"]["start_time"]).unwrap_or(start_time);
    Ok(Probe {
        meta: VideoMeta {
            width,
            height,
            fps,
            frames,
            duration,
            codec,
            profile: s["profile"].as_str().map(str::to_string),
            rotation,
            start_time,
            decoder: Decoder::Ffmpeg,
        },
        stream_index: s["index"].as_u64().unwrap_or(0),
        format_start,
    })
}

/// Counts the packets of the video stream without decoding them: the frame count for containers
/// that do not store one (Matroska / WebM without the tag).
pub(crate) fn count_packets(
    tools: &FfmpegTools,
    path: &Path,
    stream_index: u64,
) -> Result<u64, VideoError> {
    let out = Command::new(&tools.ffprobe)
        .args(["-v", "error", "-count_packets", "-select_streams"])
        .arg(stream_index.to_string())
        .args(["-show_entries", "stream=nb_read_packets", "-of", "csv=p=0"])
        .arg("-i")
        .arg(file_url(path))
        .stdin(Stdio::null())
        .output()
        .map_err(|e| VideoError::Ffmpeg {
            path: path.to_path_buf(),
            message: format!("cannot run {}: {e}", tools.ffprobe.display()),
        })?;
    let text = String::from_utf8_lossy(&out.stdout);
    match (out.status.success(), text.trim().parse()) {
        (true, Ok(n)) => Ok(n),
        _ => Err(VideoError::Ffmpeg {
            path: path.to_path_buf(),
            message: format!(
                "ffprobe could not count its frames ({})",
                last_message(&out.stderr, path)
            ),
        }),
    }
}

/// What the stderr thread reports.
enum Event {
    TimeBase(i64, i64),
    /// A frame passed `showinfo`: its pts (`None` when it has none). (A picture size that
    /// changes midway needs no care here: ffmpeg scales every frame to the first size.)
    Frame(Option<i64>),
}

/// Error lines ffmpeg logged, kept for the message.
#[derive(Default)]
struct Log {
    errors: Vec<String>,
    /// The last few lines of any level, for a failure that logged no error line.
    tail: Vec<String>,
}

const KEEP_LINES: usize = 5;

/// How long a frame's timestamp may lag behind its pixels (normally microseconds).
const EVENT_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(60);

fn parse_stderr(stderr: impl Read, tx: std::sync::mpsc::Sender<Event>) -> Log {
    let mut log = Log::default();
    let mut reader = BufReader::new(stderr);
    let mut buf = Vec::new();
    loop {
        buf.clear();
        match reader.read_until(b'\n', &mut buf) {
            Ok(0) | Err(_) => break,
            Ok(_) => {}
        }
        let line = String::from_utf8_lossy(&buf);
        let line = line.trim_end();
        if line.contains("Parsed_showinfo_") {
            let msg = strip_log_prefix(line);
            if let Some(rest) = msg.strip_prefix("config in time_base:") {
                let tb = rest.split(',').next().unwrap_or("").trim();
                if let Some((a, b)) = tb.split_once('/') {
                    if let (Ok(a), Ok(b)) = (a.trim().parse(), b.trim().parse()) {
                        let _ = tx.send(Event::TimeBase(a, b));
                    }
                }
            } else if msg.starts_with("n:") {
                let pts = msg
                    .split_once("pts:")
                    .and_then(|(_, r)| r.split_whitespace().next())
                    .and_then(|v| v.parse().ok());
                let _ = tx.send(Event::Frame(pts));
            }
            continue;
        }
        let is_error = line.contains("] [error]")
            || line.contains("] [fatal]")
            || line.starts_with("[error]")
            || line.starts_with("[fatal]");
        if is_error && log.errors.len() < KEEP_LINES {
            log.errors.push(strip_log_prefix(line).to_string());
        }
        if !line.trim().is_empty() {
            if log.tail.len() == KEEP_LINES {
                log.tail.remove(0);
            }
            log.tail.push(strip_log_prefix(line).to_string());
        }
    }
    log
}

/// Raises the frame pipe's capacity from 64 KiB to 1 MiB (Linux), so a 1080p frame (6 MB) takes
/// a few reads instead of a hundred. Best effort: the default size works, only slower.
fn enlarge_pipe(stdout: &ChildStdout) {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        // SAFETY: F_SETPIPE_SZ on a pipe descriptor this process owns; no memory is passed.
        unsafe {
            libc::fcntl(stdout.as_raw_fd(), libc::F_SETPIPE_SZ, 1 << 20);
        }
    }
    let _ = stdout;
}

/// One ffmpeg child decoding a file to RGB frames.
pub(crate) struct FfmpegSource {
    path: PathBuf,
    child: Child,
    stdout: ChildStdout,
    events: Receiver<Event>,
    stderr_thread: Option<JoinHandle<Log>>,
    width: u32,
    height: u32,
    time_base: Option<(i64, i64)>,
    /// Frames the `select` filter removes before the first one wanted (a frame-index start).
    skip_events: u64,
    /// Frames before this time are read and dropped (a seconds start, after a keyframe seek).
    min_pts: Option<f64>,
    /// Frames that went through showinfo, wanted or not.
    seen: u64,
    fallback_fps: f64,
    last_pts: Option<f64>,
    /// Frame count from the container, when the whole stream is read.
    expected: Option<u64>,
    done: bool,
}

impl FfmpegSource {
    pub(crate) fn spawn(
        tools: &FfmpegTools,
        path: &Path,
        probe: &Probe,
        start: Start,
        threads: Option<usize>,
    ) -> Result<Self, VideoError> {
        let mut cmd = Command::new(&tools.ffmpeg);
        cmd.args([
            "-hide_banner",
            "-nostdin",
            "-nostats",
            "-loglevel",
            "level+info",
        ]);
        if let Some(n) = threads {
            cmd.arg("-threads").arg(n.to_string());
            cmd.arg("-filter_threads").arg(n.to_string());
        }
        let mut filters = vec![if tools.version >= (5, 0) {
            "showinfo=checksum=0".to_string()
        } else {
            "showinfo".to_string()
        }];
        let (mut skip_events, mut min_pts, mut expected) = (0, None, probe.meta.frames);
        match start {
            Start::Frame(0) => {}
            Start::Frame(n) => {
                filters.push(format!("select=gte(n\\,{n})"));
                skip_events = n;
            }
            Start::Seconds(t) => {
                let at = probe.format_start + t;
                // Seek to the keyframe before `at` (fast); the frames before `at` are dropped
                // here, by their exact timestamps.
                cmd.arg("-ss")
                    .arg(format!("{at:.6}"))
                    .arg("-noaccurate_seek");
                min_pts = Some(at);
                expected = None;
            }
        }
        cmd.arg("-copyts").arg("-i").arg(file_url(path));
        cmd.arg("-map").arg(format!("0:{}", probe.stream_index));
        cmd.arg("-vf").arg(filters.join(","));
        if tools.version >= (5, 1) {
            cmd.args(["-fps_mode", "passthrough"]);
        } else {
            cmd.args(["-vsync", "passthrough"]);
        }
        cmd.args(["-f", "rawvideo", "-pix_fmt", "rgb24", "pipe:1"]);
        cmd.stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        let mut child = cmd.spawn().map_err(|e| VideoError::Ffmpeg {
            path: path.to_path_buf(),
            message: format!("cannot run {}: {e}", tools.ffmpeg.display()),
        })?;
        let (Some(stdout), Some(stderr)) = (child.stdout.take(), child.stderr.take()) else {
            let _ = child.kill();
            let _ = child.wait();
            return Err(VideoError::Ffmpeg {
                path: path.to_path_buf(),
                message: "ffmpeg's output pipes were not set up".into(),
            });
        };
        enlarge_pipe(&stdout);
        let (tx, rx) = channel();
        let stderr_thread = std::thread::Builder::new()
            .name("ffmpeg-stderr".into())
            .spawn(move || parse_stderr(stderr, tx))
            .map_err(|e| VideoError::Ffmpeg {
                path: path.to_path_buf(),
                message: format!("cannot start a thread to read ffmpeg's messages: {e}"),
            });
        let stderr_thread = match stderr_thread {
            Ok(t) => t,
            Err(e) => {
                let _ = child.kill();
                let _ = child.wait();
                return Err(e);
            }
        };
        Ok(FfmpegSource {
            path: path.to_path_buf(),
            child,
            stdout,
            events: rx,
            stderr_thread: Some(stderr_thread),
            width: probe.meta.width,
            height: probe.meta.height,
            time_base: None,
            skip_events,
            min_pts,
            seen: 0,
            fallback_fps: if probe.meta.fps > 0.0 {
                probe.meta.fps
            } else {
                25.0
            },
            last_pts: None,
            expected,
            done: false,
        })
    }

    /// The next frame's pts in seconds, from the stderr thread.
    fn next_pts(&mut self) -> Result<f64, VideoError> {
        loop {
            // showinfo logs a frame before ffmpeg writes it, and stderr is unbuffered, so the
            // event is there as soon as the frame is; the timeout only turns a log format this
            // code does not understand into an error instead of a hang.
            match self.events.recv_timeout(EVENT_TIMEOUT) {
                Ok(Event::TimeBase(a, b)) => self.time_base = Some((a, b)),
                Ok(Event::Frame(pts)) => {
                    self.seen += 1;
                    if self.skip_events > 0 {
                        self.skip_events -= 1;
                        continue;
                    }
                    let secs = match (pts, self.time_base) {
                        (Some(p), Some((a, b))) if b != 0 => p as f64 * a as f64 / b as f64,
                        // A frame without a timestamp (rare: raw streams) follows the previous
                        // one by the nominal frame interval.
                        _ => self.last_pts.map_or(0.0, |t| t + 1.0 / self.fallback_fps),
                    };
                    self.last_pts = Some(secs);
                    return Ok(secs);
                }
                Err(_) => {
                    return Err(VideoError::Ffmpeg {
                        path: self.path.clone(),
                        message: "ffmpeg sent a frame without logging its timestamp (showinfo)"
                            .into(),
                    })
                }
            }
        }
    }

    /// Reads a whole frame of `n` bytes; `None` at a clean end of stream.
    fn read_frame(&mut self, n: usize) -> Result<Option<Vec<u8>>, VideoError> {
        // Read into spare capacity: no zeroing of a buffer about to be overwritten.
        let mut buf = Vec::with_capacity(n);
        let got = loop {
            match (&mut self.stdout).take(n as u64).read_to_end(&mut buf) {
                Ok(_) => break buf.len(),
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(VideoError::io(&self.path, e)),
            }
        };
        if got == 0 {
            return Ok(None);
        }
        if got < n {
            // ffmpeg stopped mid-frame: it failed; `finish` has its message.
            return Err(self.finish().err().unwrap_or_else(|| VideoError::Ffmpeg {
                path: self.path.clone(),
                message: format!("ffmpeg's output ended inside a frame ({got} of {n} bytes)"),
            }));
        }
        Ok(Some(buf))
    }

    /// After the last frame: ffmpeg's exit status and logged errors decide whether the whole
    /// stream was read.
    fn finish(&mut self) -> Result<(), VideoError> {
        self.done = true;
        let status = self
            .child
            .wait()
            .map_err(|e| VideoError::io(&self.path, e))?;
        let log = self
            .stderr_thread
            .take()
            .and_then(|t| t.join().ok())
            .unwrap_or_default();
        // Frames that showinfo logged after the last one that came through the pipe.
        while let Ok(ev) = self.events.try_recv() {
            if matches!(ev, Event::Frame(_)) {
                self.seen += 1;
            }
        }
        // A demuxer's word for a cut file says more than the decoder errors that precede it.
        let first_error = log
            .errors
            .iter()
            .find(|l| l.contains("partial file") || l.contains("prematurely"))
            .or(log.errors.first())
            .or(log.tail.last())
            .cloned()
            .unwrap_or_else(|| "no message".into());
        if !status.success() {
            return Err(VideoError::Ffmpeg {
                path: self.path.clone(),
                message: format!("ffmpeg failed ({status}): {first_error}"),
            });
        }
        if !log.errors.is_empty() {
            // ffmpeg conceals damage and exits 0; frames missing against the index (or an
            // unknown count) mean the file is cut short or broken, and a partial read would
            // silently drop the end of the clip.
            let short = match self.expected {
                Some(n) => self.seen < n,
                None => true,
            };
            if short {
                let count = match self.expected {
                    Some(n) => format!("only {} of its {n} frames decode", self.seen),
                    None => format!("{} frames decode", self.seen),
                };
                return Err(VideoError::Damaged {
                    path: self.path.clone(),
                    reason: format!("{count} (ffmpeg: {first_error})"),
                });
            }
        }
        Ok(())
    }

    fn step(&mut self) -> Result<Option<RawFrame>, VideoError> {
        loop {
            if self.done {
                return Ok(None);
            }
            let n = self.width as usize * self.height as usize * 3;
            let Some(buf) = self.read_frame(n)? else {
                self.finish()?;
                return Ok(None);
            };
            let pts = self.next_pts()?;
            if self.min_pts.is_some_and(|m| pts < m - PTS_EPS) {
                continue;
            }
            let rgb = RgbImage::from_raw(self.width, self.height, buf).ok_or_else(|| {
                VideoError::Ffmpeg {
                    path: self.path.clone(),
                    message: "frame buffer of the wrong size".into(),
                }
            })?;
            return Ok(Some(RawFrame { pts, rgb }));
        }
    }
}

impl Source for FfmpegSource {
    fn next_frame(&mut self) -> Option<Result<RawFrame, VideoError>> {
        let r = self.step();
        if r.is_err() {
            self.done = true;
        }
        r.transpose()
    }

    fn child_pid(&self) -> Option<u32> {
        Some(self.child.id())
    }
}

impl Drop for FfmpegSource {
    fn drop(&mut self) {
        // A reader dropped early (an error downstream, --max-frames) must not leave ffmpeg
        // running or a zombie behind.
        let _ = self.child.kill();
        let _ = self.child.wait();
        if let Some(t) = self.stderr_thread.take() {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn versions() {
        assert_eq!(
            parse_version("ffmpeg version 5.1.9-0+deb12u1 Copyright (c) 2000-2026"),
            Some((5, 1))
        );
        assert_eq!(parse_version("ffmpeg version n7.1 Copyright"), Some((7, 1)));
        assert_eq!(
            parse_version("ffmpeg version 4.4.2-0ubuntu0.22.04.1"),
            Some((4, 4))
        );
        assert_eq!(
            parse_version("ffmpeg version N-113412-g0b8e51b584 Copyright"),
            Some((u32::MAX, 0))
        );
        assert_eq!(parse_version("garbage"), None);
    }

    #[test]
    fn log_prefixes_are_stripped() {
        assert_eq!(
            strip_log_prefix("[h264 @ 0x55d] [error] Invalid NAL unit size (1797 > 991)."),
            "Invalid NAL unit size (1797 > 991)."
        );
        assert_eq!(
            strip_log_prefix("[error] x.mp4: Invalid data"),
            "x.mp4: Invalid data"
        );
        assert_eq!(strip_log_prefix("plain"), "plain");
    }

    #[test]
    fn missing_programs_are_not_found() {
        let empty = std::env::temp_dir().join(format!("gagavatar-nopath-{}", std::process::id()));
        std::fs::create_dir_all(&empty).unwrap();
        assert_eq!(find_in_path("ffmpeg", empty.as_os_str()), None);
        assert_eq!(find_ffmpeg(Some(empty.as_os_str())), None);
        assert_eq!(find_ffmpeg(Some(OsStr::new(""))), None);
    }

    #[test]
    fn showinfo_lines_become_events() {
        let text = "[info] Input #0, mov\n\
[Parsed_showinfo_0 @ 0x5] [info] config in time_base: 1/12288, frame_rate: 24/1\n\
[Parsed_showinfo_0 @ 0x5] [info] n:   0 pts:      0 pts_time:0       pos: 48 fmt:yuv420p sar:0/1 s:834x884 i:P\n\
[Parsed_showinfo_0 @ 0x5] [info]   side data - User Data Unregistered:\n\
[Parsed_showinfo_0 @ 0x5] [info] n:   1 pts:    512 pts_time:0.0416667 pos: 9\n\
[Parsed_showinfo_0 @ 0x5] [info] n:   2 pts:NOPTS pts_time:NOPTS\n\
[h264 @ 0x6] [error] Invalid NAL unit size (1797 > 991).\n";
        let (tx, rx) = channel();
        let log = parse_stderr(text.as_bytes(), tx);
        let events: Vec<_> = rx.try_iter().collect();
        assert!(matches!(events[0], Event::TimeBase(1, 12288)));
        assert!(matches!(events[1], Event::Frame(Some(0))));
        assert!(matches!(events[2], Event::Frame(Some(512))));
        assert!(matches!(events[3], Event::Frame(None)));
        assert_eq!(events.len(), 4);
        assert_eq!(
            log.errors,
            vec!["Invalid NAL unit size (1797 > 991).".to_string()]
        );
    }
}
