//! The built-in path: H.264 in mp4 / mov decoded by the bundled OpenH264, for the streams it
//! decodes correctly (Baseline without slice groups, which includes every mp4 this crate
//! writes). Everything else is refused before any picture is decoded, naming what the file holds,
//! so the caller can say that ffmpeg reads it.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};

use image::RgbImage;

use super::h264_params::{parse_pps, parse_sps, Sps};
use super::source::{Decoder, RawFrame, Source, Start, VideoMeta, PTS_EPS};
use crate::mp4::{open_track, param_sets_annexb, H264Decoder, SampleReader, Track};
use crate::yuv::YuvMatrix;
use crate::VideoError;

const NAL_SPS: u8 = 7;
const NAL_PPS: u8 = 8;

/// Why the built-in reader does not take a file.
pub(crate) enum Refusal {
    /// A video it cannot decode correctly: what it is, in words ("H.264 High profile video").
    NeedsFfmpeg(String),
    /// Not readable at all (I/O, a broken mp4 index, no frames).
    Error(VideoError),
}

impl From<VideoError> for Refusal {
    fn from(e: VideoError) -> Self {
        Refusal::Error(e)
    }
}

/// What the checks found: everything needed to decode.
pub(crate) struct Plan {
    pub meta: VideoMeta,
    track: Track,
    file: std::fs::File,
    /// Presentation time of every sample in seconds (decode order = display order here).
    pts: Vec<f64>,
    matrix: YuvMatrix,
}

/// The codec in words, from an ISO BMFF sample entry code.
fn codec_words(code: &[u8; 4]) -> (&'static str, String) {
    match code {
        b"hvc1" | b"hev1" => ("hevc", "HEVC (H.265) video".into()),
        b"vp09" => ("vp9", "VP9 video".into()),
        b"vp08" => ("vp8", "VP8 video".into()),
        b"av01" => ("av1", "AV1 video".into()),
        b"mp4v" => ("mpeg4", "MPEG-4 Part 2 video".into()),
        b"apch" | b"apcn" | b"apcs" | b"apco" | b"ap4h" | b"ap4x" => {
            ("prores", "Apple ProRes video".into())
        }
        b"jpeg" | b"mjpa" | b"mjpb" => ("mjpeg", "Motion JPEG video".into()),
        b"dvh1" | b"dvhe" => ("hevc", "Dolby Vision (HEVC) video".into()),
        other => (
            "unknown",
            format!("video coded as '{}'", String::from_utf8_lossy(other)),
        ),
    }
}

/// Container formats told apart by their first bytes, for the refusal message.
pub(crate) fn sniff_container(head: &[u8]) -> Option<&'static str> {
    let at = |i: usize, m: &[u8]| head.get(i..i + m.len()) == Some(m);
    if at(4, b"ftyp")
        || at(4, b"moov")
        || at(4, b"mdat")
        || at(4, b"wide")
        || at(4, b"free")
        || at(4, b"skip")
    {
        Some("mp4")
    } else if at(0, &[0x1a, 0x45, 0xdf, 0xa3]) {
        Some("a Matroska / WebM file")
    } else if at(0, b"RIFF") && at(8, b"AVI ") {
        Some("an AVI file")
    } else if at(0, b"OggS") {
        Some("an Ogg file")
    } else if at(0, b"FLV") {
        Some("an FLV file")
    } else if at(0, &[0, 0, 1, 0xba]) {
        Some("an MPEG program stream")
    } else if head.first() == Some(&0x47) && head.get(188) == Some(&0x47) {
        Some("an MPEG transport stream")
    } else if at(0, &[0, 0, 0, 1]) || at(0, &[0, 0, 1]) {
        Some("a raw H.264 / HEVC stream (no container)")
    } else {
        None
    }
}

/// The video codec of a Matroska / WebM or AVI file, from its track headers near the start, in
/// words; `None` when not found there.
pub(crate) fn sniff_codec(head: &[u8]) -> Option<&'static str> {
    // Matroska: a CodecID element (0x86, a one-byte size) holding "V_...".
    for (i, w) in head.windows(3).enumerate() {
        if w[0] == 0x86 && w[1] & 0x80 != 0 && &head[i + 2..(i + 4).min(head.len())] == b"V_" {
            let len = usize::from(w[1] & 0x7f);
            let id = head.get(i + 2..i + 2 + len)?;
            return Some(match id {
                b"V_MPEG4/ISO/AVC" => "H.264",
                b"V_MPEGH/ISO/HEVC" => "HEVC (H.265)",
                b"V_VP9" => "VP9",
                b"V_VP8" => "VP8",
                b"V_AV1" => "AV1",
                b"V_PRORES" => "ProRes",
                b"V_MPEG4/ISO/ASP" | b"V_MPEG4/ISO/SP" => "MPEG-4 Part 2",
                b"V_MJPEG" => "Motion JPEG",
                _ => "other",
            })
            .filter(|c| *c != "other");
        }
    }
    // AVI: the video stream header: 'strh', its size, 'vids', the codec's four characters.
    let at = (8..head.len().saturating_sub(8))
        .find(|&p| &head[p..p + 4] == b"vids" && &head[p - 8..p - 4] == b"strh")?;
    let handler = head.get(at + 4..at + 8)?;
    Some(match &handler.to_ascii_uppercase()[..] {
        b"H264" | b"X264" | b"AVC1" => "H.264",
        b"HEVC" | b"H265" | b"HVC1" => "HEVC (H.265)",
        b"XVID" | b"DIVX" | b"DX50" | b"FMP4" | b"MP4V" => "MPEG-4 Part 2",
        b"MJPG" => "Motion JPEG",
        _ => return None,
    })
}

/// The colour conversion a stream asks for, or `None` for one the reader does not implement
/// (full range, other matrices). Unspecified means BT.601, as ffmpeg assumes.
fn colour_matrix(sps: &Sps) -> Option<YuvMatrix> {
    if sps.full_range == Some(true) {
        return None;
    }
    match sps.matrix_coefficients {
        None | Some(2) | Some(5) | Some(6) => Some(YuvMatrix::Bt601),
        Some(1) => Some(YuvMatrix::Bt709),
        Some(_) => None,
    }
}

/// Checks one SPS or PPS NAL unit; `Err` says what the built-in decoder cannot do.
fn check_param_set(nal: &[u8], matrix: &mut Option<YuvMatrix>) -> Result<(), Refusal> {
    let bad_ps = |what: &str| {
        Refusal::Error(VideoError::Format(format!(
            "its H.264 {what} cannot be parsed"
        )))
    };
    match nal.first().map(|h| h & 0x1f) {
        Some(NAL_SPS) => {
            let sps = parse_sps(nal).ok_or_else(|| bad_ps("sequence parameter set"))?;
            if sps.profile_idc != 66 {
                return Err(Refusal::NeedsFfmpeg(format!(
                    "H.264 {} profile video",
                    sps.profile_name()
                )));
            }
            if !sps.frame_mbs_only || sps.chroma_format_idc != 1 || sps.bit_depth_luma != 8 {
                return Err(Refusal::NeedsFfmpeg(
                    "interlaced or non-4:2:0 8-bit H.264 video".into(),
                ));
            }
            let m = colour_matrix(&sps).ok_or_else(|| {
                Refusal::NeedsFfmpeg(if sps.full_range == Some(true) {
                    "full-range H.264 video".to_string()
                } else {
                    format!(
                        "H.264 video with colour matrix {}",
                        sps.matrix_coefficients.unwrap_or(0)
                    )
                })
            })?;
            if matrix.is_some_and(|old| old != m) {
                return Err(Refusal::NeedsFfmpeg(
                    "H.264 video whose colours change midway".into(),
                ));
            }
            *matrix = Some(m);
        }
        Some(NAL_PPS) => {
            let pps = parse_pps(nal).ok_or_else(|| bad_ps("picture parameter set"))?;
            if pps.entropy_coding_cabac || pps.num_slice_groups != 1 {
                return Err(Refusal::NeedsFfmpeg(
                    "H.264 video with CABAC or slice groups (FMO)".into(),
                ));
            }
        }
        _ => {}
    }
    Ok(())
}

/// NAL units of an Annex-B buffer made by [`SampleReader`] (4-byte start codes; emulation
/// prevention keeps `00 00 00 01` out of the units themselves).
fn nal_units(annexb: &[u8]) -> Vec<&[u8]> {
    let mut out = Vec::new();
    let mut rest = annexb;
    while let Some(start) = find_start(rest) {
        rest = &rest[start + 4..];
        let end = find_start(rest).unwrap_or(rest.len());
        out.push(&rest[..end]);
    }
    out
}

fn find_start(buf: &[u8]) -> Option<usize> {
    buf.windows(4).position(|w| w == [0, 0, 0, 1])
}

/// Clockwise quarter turns from a `tkhd` matrix, or `None` when it is not a pure rotation.
fn rotation_of(matrix: [i32; 4]) -> Option<u32> {
    const ONE: i32 = 0x0001_0000;
    match matrix {
        [ONE, 0, 0, ONE] => Some(0),
        [0, ONE, m, 0] if m == -ONE => Some(90),
        [m, 0, 0, n] if m == -ONE && n == -ONE => Some(180),
        [0, m, ONE, 0] if m == -ONE => Some(270),
        _ => None,
    }
}

/// Reads the index of `path` and decides whether the built-in decoder reads it correctly.
pub(crate) fn plan(path: &Path, head: &[u8]) -> Result<Plan, Refusal> {
    match sniff_container(head) {
        Some("mp4") => {}
        Some(other) => {
            return Err(Refusal::NeedsFfmpeg(match sniff_codec(head) {
                Some(codec) => format!("{codec} video in {other}"),
                None => other.to_string(),
            }))
        }
        None => {
            return Err(Refusal::Error(VideoError::NotVideo {
                path: path.to_path_buf(),
                reason: super::source::not_video_reason(head),
            }))
        }
    }
    let (file, track) = open_track(path)?;
    let Some(avc) = &track.avc else {
        let (_, words) = codec_words(&track.codec);
        return Err(Refusal::NeedsFfmpeg(words));
    };
    let mut matrix = None;
    let mut saw_sps = false;
    for ps in &avc.param_sets {
        saw_sps |= ps.first().map(|h| h & 0x1f) == Some(NAL_SPS);
        check_param_set(ps, &mut matrix).map_err(|r| in_file(path, r))?;
    }
    let frames = track.check_timing(path)?;
    if frames == 0 {
        return Err(Refusal::Error(VideoError::NoVideoFrames {
            path: path.to_path_buf(),
            reason: "its video track has no frames".into(),
        }));
    }
    if !saw_sps {
        // avc3: the parameter sets travel in the samples; check the first sample's.
        let mut samples = SampleReader::new(
            path,
            file.try_clone().map_err(|e| VideoError::io(path, e))?,
            &track,
        )?;
        let mut annexb = Vec::new();
        if let Some(r) = samples.next_sample(&mut annexb) {
            r?;
            for nal in nal_units(&annexb) {
                saw_sps |= nal.first().map(|h| h & 0x1f) == Some(NAL_SPS);
                check_param_set(nal, &mut matrix).map_err(|r| in_file(path, r))?;
            }
        }
        if !saw_sps {
            return Err(Refusal::Error(VideoError::Format(format!(
                "{}: the H.264 track has no sequence parameter set",
                path.display()
            ))));
        }
    }
    let rotation = rotation_of(track.matrix).ok_or_else(|| {
        Refusal::NeedsFfmpeg("a video with a display matrix other than a quarter turn".into())
    })?;

    // Presentation times: composition times shifted by the edit list.
    let ticks = track.composition_times();
    let media_time = match track.edits.as_deref() {
        None | Some([]) => 0,
        Some([e]) if e.media_time >= 0 && e.rate == 0x0001_0000 => {
            let end = ticks.iter().max().copied().unwrap_or(0);
            let last_delta = track.stts.last().map_or(0, |&(_, d)| i64::from(d));
            let media_left =
                (end + last_delta - e.media_time).max(0) as f64 / f64::from(track.timescale);
            let segment = if track.movie_timescale == 0 {
                f64::INFINITY
            } else {
                e.segment_duration as f64 / f64::from(track.movie_timescale)
            };
            // A segment of 0 means "the whole media" for some writers; one that ends early would
            // cut frames, which only ffmpeg handles. One tick of slack for rounding between the
            // two timescales.
            let slack = 1.0 / f64::from(track.movie_timescale.max(1));
            if e.segment_duration != 0 && segment + slack < media_left {
                return Err(Refusal::NeedsFfmpeg(
                    "an mp4 whose edit list cuts frames".into(),
                ));
            }
            e.media_time
        }
        Some(_) => {
            return Err(Refusal::NeedsFfmpeg(
                "an mp4 with a multi-part edit list".into(),
            ))
        }
    };
    if ticks.iter().any(|&t| t < media_time) {
        return Err(Refusal::NeedsFfmpeg(
            "an mp4 whose edit list hides its first frames".into(),
        ));
    }
    if ticks.windows(2).any(|w| w[1] <= w[0]) {
        return Err(Refusal::NeedsFfmpeg(
            "H.264 video with reordered (B-) frames".into(),
        ));
    }
    let timescale = f64::from(track.timescale);
    let pts: Vec<f64> = ticks
        .iter()
        .map(|&t| (t - media_time) as f64 / timescale)
        .collect();
    let total_ticks: u64 = track.stts.iter().fold(0u64, |a, &(n, d)| {
        a.saturating_add(u64::from(n) * u64::from(d))
    });
    let duration = (total_ticks as f64 - media_time as f64).max(0.0) / timescale;
    let fps = if total_ticks == 0 {
        0.0
    } else {
        frames as f64 * timescale / total_ticks as f64
    };
    let (mut width, mut height) = (track.width as u32, track.height as u32);
    if rotation % 180 == 90 {
        std::mem::swap(&mut width, &mut height);
    }
    let meta = VideoMeta {
        width,
        height,
        fps,
        frames: Some(frames as u64),
        duration: Some(duration),
        codec: "h264".into(),
        profile: avc
            .param_sets
            .iter()
            .find(|p| p.first().map(|h| h & 0x1f) == Some(NAL_SPS))
            .and_then(|p| parse_sps(p))
            .map(|s| s.profile_name()),
        rotation,
        start_time: pts.first().copied().unwrap_or(0.0),
        decoder: Decoder::OpenH264,
    };
    Ok(Plan {
        meta,
        track,
        file,
        pts,
        matrix: matrix.unwrap_or(YuvMatrix::Bt601),
    })
}

/// A refusal found in the parameter sets, with the file named in a format error.
fn in_file(path: &Path, r: Refusal) -> Refusal {
    match r {
        Refusal::Error(VideoError::Format(m)) => {
            Refusal::Error(VideoError::Format(format!("{}: {m}", path.display())))
        }
        other => other,
    }
}

/// Streams the frames of a [`Plan`].
pub(crate) struct OpenH264Source {
    path: PathBuf,
    samples: SampleReader,
    decoder: H264Decoder,
    pts: Vec<f64>,
    /// The sample decoding started at, and the first frame to hand out.
    first_sample: usize,
    start_frame: usize,
    /// Pictures decoded so far (frame index = first_sample + decoded).
    decoded: usize,
    pending: VecDeque<(usize, usize, Vec<u8>)>,
    annexb: Vec<u8>,
    matrix: Option<YuvMatrix>,
    size: (usize, usize),
    rotation: u32,
    flushed: bool,
}

impl OpenH264Source {
    /// Starts decoding at the last keyframe at or before the first frame `start` asks for.
    pub(crate) fn new(path: &Path, plan: Plan, start: Start) -> Result<Self, VideoError> {
        let Plan {
            meta,
            track,
            file,
            pts,
            matrix,
        } = plan;
        let n = pts.len();
        let start_frame = match start {
            Start::Frame(i) => usize::try_from(i).unwrap_or(usize::MAX),
            Start::Seconds(t) => {
                let target = meta.start_time + t;
                pts.iter().position(|&p| p >= target - PTS_EPS).unwrap_or(n)
            }
        };
        let first_sample = match &track.sync {
            None => start_frame.min(n),
            Some(sync) => sync
                .iter()
                .map(|&s| (s as usize).saturating_sub(1))
                .filter(|&s| s <= start_frame)
                .max()
                .unwrap_or(0),
        };
        let mut samples = SampleReader::new(path, file, &track)?;
        samples.seek_to(first_sample);
        let mut decoder = H264Decoder::new(path, matrix)?;
        let avc = track.require_avc(path)?;
        let ps = param_sets_annexb(path, avc)?;
        let mut pending = VecDeque::new();
        if !ps.is_empty() {
            if let Some(p) = decoder.decode(&ps, None)? {
                pending.push_back(p);
            }
        }
        let (mut w, mut h) = (meta.width as usize, meta.height as usize);
        if meta.rotation % 180 == 90 {
            std::mem::swap(&mut w, &mut h);
        }
        Ok(OpenH264Source {
            path: path.to_path_buf(),
            samples,
            decoder,
            pts,
            first_sample,
            start_frame,
            decoded: 0,
            pending,
            annexb: Vec::new(),
            matrix: Some(matrix),
            size: (w, h),
            rotation: meta.rotation,
            flushed: false,
        })
    }

    fn step(&mut self) -> Result<Option<RawFrame>, VideoError> {
        loop {
            if let Some((w, h, rgb)) = self.pending.pop_front() {
                let index = self.first_sample + self.decoded;
                self.decoded += 1;
                if (w, h) != self.size {
                    return Err(VideoError::Decode(format!(
                        "{}: frame {index} decodes to {w}x{h}, the track says {}x{}",
                        self.path.display(),
                        self.size.0,
                        self.size.1
                    )));
                }
                let Some(&pts) = self.pts.get(index) else {
                    return Err(VideoError::Decode(format!(
                        "{}: the decoder gave more pictures than the file has samples ({})",
                        self.path.display(),
                        self.pts.len()
                    )));
                };
                if index < self.start_frame {
                    continue;
                }
                let img = RgbImage::from_raw(w as u32, h as u32, rgb).ok_or_else(|| {
                    VideoError::Decode(format!(
                        "{}: frame {index}: short picture",
                        self.path.display()
                    ))
                })?;
                let rgb = match self.rotation {
                    90 => image::imageops::rotate90(&img),
                    180 => image::imageops::rotate180(&img),
                    270 => image::imageops::rotate270(&img),
                    _ => img,
                };
                return Ok(Some(RawFrame { pts, rgb }));
            }
            if self.flushed {
                let expected = self.samples.len() - self.first_sample;
                if self.decoded != expected {
                    return Err(VideoError::Decode(format!(
                        "{}: OpenH264 decoded {} of {expected} frames",
                        self.path.display(),
                        self.decoded
                    )));
                }
                return Ok(None);
            }
            match self.samples.next_sample(&mut self.annexb) {
                Some(i) => {
                    let i = i?;
                    // Parameter sets repeated in the stream must stay ones the decoder handles.
                    for nal in nal_units(&self.annexb) {
                        if matches!(nal.first().map(|h| h & 0x1f), Some(NAL_SPS | NAL_PPS)) {
                            check_param_set(nal, &mut self.matrix).map_err(|r| match r {
                                Refusal::NeedsFfmpeg(what) => VideoError::Decode(format!(
                                    "{}: sample {i} switches to {what}, which needs ffmpeg",
                                    self.path.display()
                                )),
                                Refusal::Error(e) => e,
                            })?;
                        }
                    }
                    if let Some(p) = self.decoder.decode(&self.annexb, Some(i))? {
                        self.pending.push_back(p);
                    }
                }
                None => {
                    self.pending.extend(self.decoder.flush()?);
                    self.flushed = true;
                }
            }
        }
    }
}

impl Source for OpenH264Source {
    fn next_frame(&mut self) -> Option<Result<RawFrame, VideoError>> {
        self.step().transpose()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quarter_turns_from_the_track_matrix() {
        const ONE: i32 = 0x0001_0000;
        assert_eq!(rotation_of([ONE, 0, 0, ONE]), Some(0));
        // The QuickTime matrix of a phone held upright: shown turned 90 degrees clockwise.
        assert_eq!(rotation_of([0, ONE, -ONE, 0]), Some(90));
        assert_eq!(rotation_of([-ONE, 0, 0, -ONE]), Some(180));
        assert_eq!(rotation_of([0, -ONE, ONE, 0]), Some(270));
        assert_eq!(rotation_of([-ONE, 0, 0, ONE]), None, "mirrored");
        assert_eq!(rotation_of([ONE / 2, 0, 0, ONE]), None, "scaled");
    }

    #[test]
    fn nal_units_are_split_at_start_codes() {
        let buf = [
            0, 0, 0, 1, 0x67, 1, 2, 0, 0, 0, 1, 0x68, 3, 0, 0, 0, 1, 0x65,
        ];
        let nals = nal_units(&buf);
        assert_eq!(nals, vec![&[0x67, 1, 2][..], &[0x68, 3][..], &[0x65][..]]);
    }

    #[test]
    fn containers_are_told_apart() {
        let mut mp4 = vec![0, 0, 0, 24];
        mp4.extend_from_slice(b"ftypisom");
        assert_eq!(sniff_container(&mp4), Some("mp4"));
        assert_eq!(
            sniff_container(&[0x1a, 0x45, 0xdf, 0xa3, 1]),
            Some("a Matroska / WebM file")
        );
        assert_eq!(
            sniff_container(b"RIFF\0\0\0\0AVI LIST"),
            Some("an AVI file")
        );
        assert_eq!(sniff_container(b"hello world"), None);
    }

    #[test]
    fn codecs_of_other_containers_are_named() {
        let mut mkv = vec![0x1a, 0x45, 0xdf, 0xa3, 0, 0, 0x86, 0x85];
        mkv.extend_from_slice(b"V_VP9");
        assert_eq!(sniff_codec(&mkv), Some("VP9"));
        let mut avi = b"RIFF\0\0\0\0AVI LIST\0\0\0\0strh\x38\0\0\0vidsH264".to_vec();
        avi.extend_from_slice(&[0; 16]);
        assert_eq!(sniff_codec(&avi), Some("H.264"));
        assert_eq!(sniff_codec(b"nothing to see"), None);
    }
}
