//! A minimal MP4 (ISO BMFF, ISO/IEC 14496-12 and -15) muxer for one H.264 video track, and a
//! reader of the same structure for checks ([`read_mp4_info`], [`decode_mp4`]).
//!
//! Layout written: `ftyp`, `moov`, `mdat`. The index (`moov`) comes first ("faststart") so a
//! browser can start playing before the whole file has arrived; the samples are therefore first
//! streamed to a hidden data file and copied behind the index in `finish`. Samples are
//! length-prefixed NAL units (4-byte lengths); SPS and PPS live in `avcC`; keyframes are listed in
//! `stss`; one chunk holds about one second of samples (`co64` offsets when a file passes 4 GiB).

use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::h264::{H264Encoder, NAL_PPS, NAL_SPS};
use crate::temp::{check_file_target, temp_sibling, TempPath};
use crate::yuv::{i420_to_rgb_with, I420};
use crate::VideoError;

/// What [`read_mp4_info`] finds in the first video track.
#[derive(Debug, Clone, PartialEq)]
pub struct Mp4Info {
    /// Coded size (odd input sizes are padded to even).
    pub width: usize,
    pub height: usize,
    pub frames: usize,
    /// Frames per second from the sample durations (total frames / total duration).
    pub fps: f64,
    /// Sync samples (IDR pictures); every frame when the file has no `stss`.
    pub keyframes: usize,
}

// ---------------------------------------------------------------------------------------------
// Timing

/// `(timescale, sample_delta)` with `timescale / sample_delta == fps` exactly when fps is a
/// ratio with denominator up to 1001 (25, 30000/1001, 29.97, 12.5, ...), else to 1/90000 s.
pub(crate) fn timing(fps: f64) -> (u32, u32) {
    for d in 1..=1001u32 {
        let n = fps * d as f64;
        if n >= 1.0 && (n - n.round()).abs() <= 1e-6 {
            let n = u64::from(n.round() as u32);
            // A timescale that is a multiple of 1000 (else at least 1000) keeps durations exact
            // in milliseconds for tools that round to them.
            let lcm = n / gcd(n, 1000) * 1000;
            let m = if lcm <= 1_000_000 {
                lcm / n
            } else {
                1000u64.div_ceil(n)
            };
            return ((n * m) as u32, (u64::from(d) * m) as u32);
        }
    }
    (90_000, ((90_000.0 / fps).round() as u32).max(1))
}

fn gcd(a: u64, b: u64) -> u64 {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

// ---------------------------------------------------------------------------------------------
// Writing

/// Appends boxes to a buffer, patching each size when the box is closed.
struct BoxBuf {
    buf: Vec<u8>,
    open: Vec<usize>,
}

impl BoxBuf {
    fn new() -> Self {
        BoxBuf {
            buf: Vec::new(),
            open: Vec::new(),
        }
    }
    fn begin(&mut self, kind: &[u8; 4]) {
        self.open.push(self.buf.len());
        self.buf.extend_from_slice(&[0; 4]);
        self.buf.extend_from_slice(kind);
    }
    fn begin_full(&mut self, kind: &[u8; 4], version: u8, flags: u32) {
        self.begin(kind);
        self.u32((u32::from(version) << 24) | (flags & 0x00ff_ffff));
    }
    fn end(&mut self) {
        if let Some(start) = self.open.pop() {
            // The index boxes stay far below 4 GiB (a few bytes per frame).
            let size = (self.buf.len() - start) as u32;
            self.buf[start..start + 4].copy_from_slice(&size.to_be_bytes());
        }
    }
    fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }
    fn u16(&mut self, v: u16) {
        self.buf.extend_from_slice(&v.to_be_bytes());
    }
    fn u32(&mut self, v: u32) {
        self.buf.extend_from_slice(&v.to_be_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.buf.extend_from_slice(&v.to_be_bytes());
    }
    fn bytes(&mut self, v: &[u8]) {
        self.buf.extend_from_slice(v);
    }
    /// 32-bit or 64-bit time field, as the box version says.
    fn time(&mut self, v1: bool, v: u64) {
        if v1 {
            self.u64(v);
        } else {
            self.u32(v as u32);
        }
    }
    fn unity_matrix(&mut self) {
        for v in [0x0001_0000u32, 0, 0, 0, 0x0001_0000, 0, 0, 0, 0x4000_0000] {
            self.u32(v);
        }
    }
}

/// The parts of the index that `finish` has gathered.
struct Index<'a> {
    width: u16,
    height: u16,
    timescale: u32,
    delta: u32,
    sizes: &'a [u32],
    /// 1-based sample numbers.
    sync: &'a [u32],
    sps: &'a [u8],
    pps: &'a [u8],
    samples_per_chunk: usize,
}

fn ftyp() -> Vec<u8> {
    let mut b = BoxBuf::new();
    b.begin(b"ftyp");
    b.bytes(b"isom");
    b.u32(0x200);
    for brand in [b"isom", b"iso2", b"avc1", b"mp41"] {
        b.bytes(brand);
    }
    b.end();
    b.buf
}

/// `moov` with chunk offsets counted from `data_start` (the first sample byte in the file).
fn moov(ix: &Index<'_>, data_start: u64, co64: bool) -> Vec<u8> {
    let n = ix.sizes.len();
    let duration = n as u64 * u64::from(ix.delta);
    let v1 = duration > u64::from(u32::MAX);
    let version = u8::from(v1);
    let mut b = BoxBuf::new();
    b.begin(b"moov");

    b.begin_full(b"mvhd", version, 0);
    b.time(v1, 0); // creation time: left 0 so the same frames give the same bytes
    b.time(v1, 0); // modification time
    b.u32(ix.timescale);
    b.time(v1, duration);
    b.u32(0x0001_0000); // rate 1.0
    b.u16(0x0100); // volume 1.0
    b.bytes(&[0; 10]);
    b.unity_matrix();
    b.bytes(&[0; 24]);
    b.u32(2); // next track id
    b.end();

    b.begin(b"trak");
    b.begin_full(b"tkhd", version, 0x3); // enabled, in movie
    b.time(v1, 0);
    b.time(v1, 0);
    b.u32(1); // track id
    b.u32(0);
    b.time(v1, duration);
    b.bytes(&[0; 8]);
    b.u16(0); // layer
    b.u16(0); // alternate group
    b.u16(0); // volume: 0 for video
    b.u16(0);
    b.unity_matrix();
    b.u32(u32::from(ix.width) << 16);
    b.u32(u32::from(ix.height) << 16);
    b.end();

    b.begin(b"mdia");
    b.begin_full(b"mdhd", version, 0);
    b.time(v1, 0);
    b.time(v1, 0);
    b.u32(ix.timescale);
    b.time(v1, duration);
    b.u16(0x55c4); // language "und", ISO-639-2/T packed in 5-bit letters
    b.u16(0);
    b.end();
    b.begin_full(b"hdlr", 0, 0);
    b.u32(0);
    b.bytes(b"vide");
    b.bytes(&[0; 12]);
    b.bytes(b"VideoHandler\0");
    b.end();

    b.begin(b"minf");
    b.begin_full(b"vmhd", 0, 1);
    b.bytes(&[0; 8]);
    b.end();
    b.begin(b"dinf");
    b.begin_full(b"dref", 0, 0);
    b.u32(1);
    b.begin_full(b"url ", 0, 1); // flag 1: the media data is in this file
    b.end();
    b.end();
    b.end();

    b.begin(b"stbl");
    b.begin_full(b"stsd", 0, 0);
    b.u32(1);
    b.begin(b"avc1");
    b.bytes(&[0; 6]);
    b.u16(1); // data reference index
    b.bytes(&[0; 16]);
    b.u16(ix.width);
    b.u16(ix.height);
    b.u32(0x0048_0000); // 72 dpi
    b.u32(0x0048_0000);
    b.u32(0);
    b.u16(1); // frames per sample
    let mut name = [0u8; 32];
    let label = b"gagavatar OpenH264";
    name[0] = label.len() as u8;
    name[1..1 + label.len()].copy_from_slice(label);
    b.bytes(&name);
    b.u16(0x0018); // depth: colour, no alpha
    b.u16(0xffff); // pre_defined = -1
    b.begin(b"avcC");
    b.u8(1);
    b.u8(ix.sps.get(1).copied().unwrap_or(66)); // profile
    b.u8(ix.sps.get(2).copied().unwrap_or(0)); // constraint flags
    b.u8(ix.sps.get(3).copied().unwrap_or(30)); // level
    b.u8(0xfc | 3); // 4-byte NAL lengths
    b.u8(0xe0 | 1); // one SPS
    b.u16(ix.sps.len() as u16);
    b.bytes(ix.sps);
    b.u8(1); // one PPS
    b.u16(ix.pps.len() as u16);
    b.bytes(ix.pps);
    b.end();
    // The same colour description as the SPS VUI, for players that read the container.
    b.begin(b"colr");
    b.bytes(b"nclx");
    b.u16(1); // BT.709 (= sRGB) primaries
    b.u16(13); // sRGB transfer
    b.u16(6); // BT.601 matrix
    b.u8(0); // limited range
    b.end();
    b.begin(b"pasp");
    b.u32(1);
    b.u32(1);
    b.end();
    b.end(); // avc1
    b.end(); // stsd

    b.begin_full(b"stts", 0, 0);
    b.u32(1);
    b.u32(n as u32);
    b.u32(ix.delta);
    b.end();

    b.begin_full(b"stss", 0, 0);
    b.u32(ix.sync.len() as u32);
    for &s in ix.sync {
        b.u32(s);
    }
    b.end();

    let spc = ix.samples_per_chunk;
    let chunks = n.div_ceil(spc);
    let last = n - (chunks - 1) * spc;
    b.begin_full(b"stsc", 0, 0);
    if last == spc || chunks == 1 {
        b.u32(1);
        b.u32(1);
        b.u32(if chunks == 1 { last } else { spc } as u32);
        b.u32(1);
    } else {
        b.u32(2);
        b.u32(1);
        b.u32(spc as u32);
        b.u32(1);
        b.u32(chunks as u32);
        b.u32(last as u32);
        b.u32(1);
    }
    b.end();

    b.begin_full(b"stsz", 0, 0);
    b.u32(0); // sizes differ
    b.u32(n as u32);
    for &s in ix.sizes {
        b.u32(s);
    }
    b.end();

    b.begin_full(if co64 { b"co64" } else { b"stco" }, 0, 0);
    b.u32(chunks as u32);
    let mut offset = data_start;
    for c in ix.sizes.chunks(spc) {
        if co64 {
            b.u64(offset);
        } else {
            b.u32(offset as u32);
        }
        offset += c.iter().map(|&s| u64::from(s)).sum::<u64>();
    }
    b.end();

    b.end(); // stbl
    b.end(); // minf
    b.end(); // mdia
    b.end(); // trak
    b.end(); // moov
    b.buf
}

/// Streams encoded samples to a hidden data file; `finish` writes the playable file.
pub(crate) struct Mp4Sink {
    target: PathBuf,
    enc: H264Encoder,
    timescale: u32,
    delta: u32,
    samples_per_chunk: usize,
    // Declared before its guard so the file is closed before the guard deletes it.
    data: BufWriter<File>,
    data_tmp: TempPath,
    data_len: u64,
    sizes: Vec<u32>,
    sync: Vec<u32>,
}

impl Mp4Sink {
    pub(crate) fn create(
        path: &Path,
        width: usize,
        height: usize,
        fps: f64,
    ) -> Result<Self, VideoError> {
        let enc = H264Encoder::new(width, height, fps)?;
        check_file_target(path)?;
        let data_tmp = TempPath::file(temp_sibling(path)?);
        // Read back in `finish`, hence read + write.
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .open(data_tmp.path())
            .map_err(|e| VideoError::io(data_tmp.path(), e))?;
        let (timescale, delta) = timing(fps);
        Ok(Mp4Sink {
            target: path.to_path_buf(),
            enc,
            timescale,
            delta,
            samples_per_chunk: (fps.round() as usize).max(1),
            data: BufWriter::new(file),
            data_tmp,
            data_len: 0,
            sizes: Vec::new(),
            sync: Vec::new(),
        })
    }

    pub(crate) fn push(&mut self, rgb: &[u8]) -> Result<(), VideoError> {
        if self.sizes.len() >= u32::MAX as usize {
            return Err(VideoError::Encode(
                "an mp4 holds at most 2^32 - 1 frames".into(),
            ));
        }
        let sample = self.enc.encode(rgb)?;
        self.data
            .write_all(&sample.data)
            .map_err(|e| VideoError::io(self.data_tmp.path(), e))?;
        self.data_len += sample.data.len() as u64;
        self.sizes.push(sample.data.len() as u32);
        if sample.keyframe {
            self.sync.push(self.sizes.len() as u32);
        }
        Ok(())
    }

    pub(crate) fn finish(self) -> Result<(), VideoError> {
        let Mp4Sink {
            target,
            enc,
            timescale,
            delta,
            samples_per_chunk,
            data,
            data_tmp,
            data_len,
            sizes,
            sync,
        } = self;
        let (Some(sps), Some(pps)) = (enc.sps.as_deref(), enc.pps.as_deref()) else {
            return Err(VideoError::Encode(
                "OpenH264 produced no SPS/PPS parameter sets".into(),
            ));
        };
        let (w, h) = enc.coded_size();
        let ix = Index {
            // check_size keeps both sides <= 3840.
            width: w as u16,
            height: h as u16,
            timescale,
            delta,
            sizes: &sizes,
            sync: &sync,
            sps,
            pps,
            samples_per_chunk,
        };
        let mut data = data
            .into_inner()
            .map_err(|e| VideoError::io(data_tmp.path(), e.into_error()))?;

        let ftyp = ftyp();
        let mdat_header = if data_len + 8 > u64::from(u32::MAX) {
            16
        } else {
            8
        };
        // The index size does not depend on the offsets in it, only on their width.
        let mut co64 = false;
        let mut start = ftyp.len() as u64 + moov(&ix, 0, false).len() as u64 + mdat_header;
        if start + data_len > u64::from(u32::MAX) {
            co64 = true;
            start = ftyp.len() as u64 + moov(&ix, 0, true).len() as u64 + mdat_header;
        }
        let moov = moov(&ix, start, co64);

        let tmp = TempPath::file(temp_sibling(&target)?);
        let io = |e| VideoError::io(tmp.path(), e);
        let mut out = BufWriter::new(File::create(tmp.path()).map_err(io)?);
        out.write_all(&ftyp).map_err(io)?;
        out.write_all(&moov).map_err(io)?;
        if mdat_header == 16 {
            out.write_all(&1u32.to_be_bytes()).map_err(io)?;
            out.write_all(b"mdat").map_err(io)?;
            out.write_all(&(data_len + 16).to_be_bytes()).map_err(io)?;
        } else {
            out.write_all(&((data_len + 8) as u32).to_be_bytes())
                .map_err(io)?;
            out.write_all(b"mdat").map_err(io)?;
        }
        data.seek(SeekFrom::Start(0))
            .map_err(|e| VideoError::io(data_tmp.path(), e))?;
        let copied = std::io::copy(&mut data, &mut out).map_err(io)?;
        if copied != data_len {
            return Err(VideoError::Encode(format!(
                "{}: copied {copied} sample bytes, expected {data_len}",
                data_tmp.path().display()
            )));
        }
        let out = out.into_inner().map_err(|e| io(e.into_error()))?;
        out.sync_all().map_err(io)?;
        drop(out);
        drop(data);
        check_file_target(&target)?;
        tmp.persist(&target)
        // data_tmp is removed when it goes out of scope here.
    }
}

// ---------------------------------------------------------------------------------------------
// Reading

fn bad(path: &Path, reason: impl std::fmt::Display) -> VideoError {
    VideoError::Format(format!("{}: {reason}", path.display()))
}

/// Child boxes of a box body: `(type, body)`.
fn children<'a>(
    path: &'a Path,
    mut buf: &'a [u8],
) -> impl Iterator<Item = Result<([u8; 4], &'a [u8]), VideoError>> + 'a {
    std::iter::from_fn(move || {
        if buf.is_empty() {
            return None;
        }
        let item = (|| {
            if buf.len() < 8 {
                return Err(bad(path, "truncated box header"));
            }
            let size32 = u32::from_be_bytes([buf[0], buf[1], buf[2], buf[3]]) as u64;
            let kind = [buf[4], buf[5], buf[6], buf[7]];
            let (header, size) = match size32 {
                0 => (8, buf.len() as u64),
                1 => {
                    if buf.len() < 16 {
                        return Err(bad(path, "truncated 64-bit box header"));
                    }
                    let mut b = [0; 8];
                    b.copy_from_slice(&buf[8..16]);
                    (16, u64::from_be_bytes(b))
                }
                s => (8, s),
            };
            if size < header as u64 || size > buf.len() as u64 {
                return Err(bad(
                    path,
                    format!(
                        "box '{}' of {size} bytes does not fit in its parent",
                        String::from_utf8_lossy(&kind)
                    ),
                ));
            }
            let body = &buf[header..size as usize];
            buf = &buf[size as usize..];
            Ok((kind, body))
        })();
        if item.is_err() {
            buf = &[];
        }
        Some(item)
    })
}

fn child<'a>(
    path: &'a Path,
    buf: &'a [u8],
    kind: &[u8; 4],
) -> Result<Option<&'a [u8]>, VideoError> {
    for c in children(path, buf) {
        let (k, body) = c?;
        if &k == kind {
            return Ok(Some(body));
        }
    }
    Ok(None)
}

fn need<'a>(
    path: &'a Path,
    buf: &'a [u8],
    kind: &[u8; 4],
    parent: &str,
) -> Result<&'a [u8], VideoError> {
    child(path, buf, kind)?.ok_or_else(|| {
        bad(
            path,
            format!("no '{}' box in '{parent}'", String::from_utf8_lossy(kind)),
        )
    })
}

/// Big-endian reads that fail with a format error instead of panicking.
struct Cursor<'a> {
    path: &'a Path,
    what: &'static str,
    buf: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    fn new(path: &'a Path, what: &'static str, buf: &'a [u8]) -> Self {
        Cursor {
            path,
            what,
            buf,
            pos: 0,
        }
    }
    fn take(&mut self, n: usize) -> Result<&'a [u8], VideoError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.buf.len());
        let end = end.ok_or_else(|| bad(self.path, format!("'{}' box is truncated", self.what)))?;
        let s = &self.buf[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8, VideoError> {
        Ok(self.take(1)?[0])
    }
    fn u16(&mut self) -> Result<u16, VideoError> {
        let b = self.take(2)?;
        Ok(u16::from_be_bytes([b[0], b[1]]))
    }
    fn u32(&mut self) -> Result<u32, VideoError> {
        let b = self.take(4)?;
        Ok(u32::from_be_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn u64(&mut self) -> Result<u64, VideoError> {
        let b = self.take(8)?;
        let mut a = [0; 8];
        a.copy_from_slice(b);
        Ok(u64::from_be_bytes(a))
    }
    /// Entry count of a table whose entries take `entry_bytes`, checked against the box size
    /// before anything is allocated for it.
    fn count(&mut self, entry_bytes: usize) -> Result<usize, VideoError> {
        let n = self.u32()? as usize;
        if n.saturating_mul(entry_bytes) > self.buf.len() - self.pos {
            return Err(bad(
                self.path,
                format!(
                    "'{}' box lists {n} entries but is too short for them",
                    self.what
                ),
            ));
        }
        Ok(n)
    }
}

/// One entry of a track's edit list (`elst`): `segment_duration` in the movie timescale,
/// `media_time` in the track timescale (-1 for an empty edit, a pause before the media).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Edit {
    pub segment_duration: u64,
    pub media_time: i64,
    /// 16.16 fixed point; 1.0 plays at normal speed.
    pub rate: i32,
}

/// What `avcC` says about an H.264 track.
#[derive(Debug, Clone)]
pub(crate) struct AvcConfig {
    pub nal_length_size: usize,
    /// Parameter sets in the order stored (SPS first, then PPS), each without a start code.
    pub param_sets: Vec<Vec<u8>>,
}

/// The sample table of the first video track.
pub(crate) struct Track {
    /// The sample entry's four-character code (`avc1`, `hvc1`, `vp09`, ...).
    pub codec: [u8; 4],
    pub width: usize,
    pub height: usize,
    pub timescale: u32,
    /// The movie header's timescale, which `elst` segment durations use.
    pub movie_timescale: u32,
    /// (sample count, delta) runs.
    pub stts: Vec<(u32, u32)>,
    /// (sample count, composition offset) runs; empty when the file has no `ctts`.
    pub ctts: Vec<(u32, i64)>,
    pub sizes: Vec<u64>,
    /// 1-based sync sample numbers; `None` when every sample is a sync sample (no `stss`).
    pub sync: Option<Vec<u32>>,
    /// (first chunk, samples per chunk) runs, 1-based chunks.
    stsc: Vec<(u32, u32)>,
    chunk_offsets: Vec<u64>,
    /// `None` for tracks that are not H.264.
    pub avc: Option<AvcConfig>,
    /// `tkhd` matrix entries a, b, c, d (16.16 fixed point).
    pub matrix: [i32; 4],
    /// `None` when the track has no edit list.
    pub edits: Option<Vec<Edit>>,
}

/// Reads the top-level boxes, returning the `moov` body. `mdat` is skipped, not read.
fn read_moov(path: &Path, file: &mut File) -> Result<Vec<u8>, VideoError> {
    let io = |e| VideoError::io(path, e);
    let len = file.metadata().map_err(io)?.len();
    let mut pos = 0u64;
    while pos < len {
        file.seek(SeekFrom::Start(pos)).map_err(io)?;
        let mut h = [0u8; 8];
        file.read_exact(&mut h).map_err(io)?;
        let kind = [h[4], h[5], h[6], h[7]];
        let (header, size) = match u32::from_be_bytes([h[0], h[1], h[2], h[3]]) {
            0 => (8, len - pos),
            1 => {
                let mut b = [0u8; 8];
                file.read_exact(&mut b).map_err(io)?;
                (16, u64::from_be_bytes(b))
            }
            s => (8, u64::from(s)),
        };
        if size < header {
            return Err(bad(
                path,
                format!(
                    "top-level box '{}' at byte {pos} has a bad size {size}",
                    String::from_utf8_lossy(&kind)
                ),
            ));
        }
        if size > len - pos {
            return Err(bad(
                path,
                format!(
                    "the file is truncated: box '{}' at byte {pos} needs {size} bytes, the \
                     file ends after {}",
                    String::from_utf8_lossy(&kind),
                    len - pos
                ),
            ));
        }
        if &kind == b"moov" {
            let mut body = vec![0u8; (size - header) as usize];
            file.read_exact(&mut body).map_err(io)?;
            return Ok(body);
        }
        pos += size;
    }
    Err(bad(
        path,
        "no 'moov' box: not an mp4 file, or an unfinished one",
    ))
}

/// The first video track of an mp4 / mov file, its sample table read (not its samples).
pub(crate) fn open_track(path: &Path) -> Result<(File, Track), VideoError> {
    let mut file = File::open(path).map_err(|e| VideoError::io(path, e))?;
    let file_len = file.metadata().map_err(|e| VideoError::io(path, e))?.len();
    let moov = read_moov(path, &mut file)?;
    let track = read_track(path, &moov, file_len)?;
    Ok((file, track))
}

fn read_track(path: &Path, moov: &[u8], file_len: u64) -> Result<Track, VideoError> {
    let movie_timescale = match child(path, moov, b"mvhd")? {
        Some(mvhd) => {
            let mut c = Cursor::new(path, "mvhd", mvhd);
            let version = c.u8()?;
            c.take(3)?;
            c.take(if version == 1 { 16 } else { 8 })?;
            c.u32()?
        }
        None => 0,
    };
    for c in children(path, moov) {
        let (kind, trak) = c?;
        if &kind != b"trak" {
            continue;
        }
        let mdia = need(path, trak, b"mdia", "trak")?;
        let hdlr = need(path, mdia, b"hdlr", "mdia")?;
        if hdlr.get(8..12) != Some(b"vide") {
            continue;
        }
        let mut track = parse_video_track(path, mdia, file_len)?;
        track.movie_timescale = movie_timescale;
        if let Some(tkhd) = child(path, trak, b"tkhd")? {
            let mut c = Cursor::new(path, "tkhd", tkhd);
            let version = c.u8()?;
            c.take(3)?;
            // Times, track id, reserved, duration; then reserved, layer, group, volume.
            c.take(if version == 1 { 32 } else { 20 })?;
            c.take(16)?;
            let a = c.u32()? as i32;
            let b = c.u32()? as i32;
            c.u32()?;
            let cc = c.u32()? as i32;
            let d = c.u32()? as i32;
            track.matrix = [a, b, cc, d];
        }
        if let Some(edts) = child(path, trak, b"edts")? {
            if let Some(elst) = child(path, edts, b"elst")? {
                let mut c = Cursor::new(path, "elst", elst);
                let version = c.u8()?;
                c.take(3)?;
                let n = c.count(if version == 1 { 20 } else { 12 })?;
                let mut edits = Vec::with_capacity(n);
                for _ in 0..n {
                    let (segment_duration, media_time) = if version == 1 {
                        (c.u64()?, c.u64()? as i64)
                    } else {
                        (u64::from(c.u32()?), i64::from(c.u32()? as i32))
                    };
                    let rate = c.u32()? as i32;
                    edits.push(Edit {
                        segment_duration,
                        media_time,
                        rate,
                    });
                }
                track.edits = Some(edits);
            }
        }
        return Ok(track);
    }
    Err(VideoError::NoVideoFrames {
        path: path.to_path_buf(),
        reason: "it has no video track".into(),
    })
}

fn parse_video_track(path: &Path, mdia: &[u8], file_len: u64) -> Result<Track, VideoError> {
    let mut c = Cursor::new(path, "mdhd", need(path, mdia, b"mdhd", "mdia")?);
    let version = c.u8()?;
    c.take(3)?;
    let timescale = if version == 1 {
        c.take(16)?;
        c.u32()?
    } else {
        c.take(8)?;
        c.u32()?
    };
    if timescale == 0 {
        return Err(bad(path, "'mdhd' timescale is 0"));
    }
    let minf = need(path, mdia, b"minf", "mdia")?;
    let stbl = need(path, minf, b"stbl", "minf")?;

    let mut c = Cursor::new(path, "stsd", need(path, stbl, b"stsd", "stbl")?);
    c.take(4)?;
    if c.u32()? == 0 {
        return Err(bad(path, "'stsd' has no sample description"));
    }
    let entries = c.take(c.buf.len() - c.pos)?;
    let (codec, entry) = children(path, entries)
        .next()
        .ok_or_else(|| bad(path, "'stsd' is empty"))??;
    // Every visual sample entry starts with the same 78 bytes; the size is at 24..28.
    let mut c = Cursor::new(path, "visual sample entry", entry);
    c.take(24)?;
    let width = c.u16()? as usize;
    let height = c.u16()? as usize;
    c.take(50)?;
    let avc = if &codec == b"avc1" || &codec == b"avc3" {
        let rest = c.take(entry.len() - c.pos)?;
        match child(path, rest, b"avcC")? {
            Some(avcc) => Some(parse_avcc(path, avcc)?),
            // avc3 may carry its parameter sets in the samples only.
            None if &codec == b"avc3" => Some(AvcConfig {
                nal_length_size: 4,
                param_sets: Vec::new(),
            }),
            None => return Err(bad(path, "no 'avcC' box in 'avc1'")),
        }
    } else {
        None
    };

    let mut c = Cursor::new(path, "stts", need(path, stbl, b"stts", "stbl")?);
    c.take(4)?;
    let n = c.count(8)?;
    let stts = (0..n)
        .map(|_| Ok((c.u32()?, c.u32()?)))
        .collect::<Result<Vec<_>, VideoError>>()?;

    let ctts = match child(path, stbl, b"ctts")? {
        Some(ctts) => {
            let mut c = Cursor::new(path, "ctts", ctts);
            c.take(4)?;
            let n = c.count(8)?;
            (0..n)
                .map(|_| {
                    let count = c.u32()?;
                    // Version 0 offsets are unsigned on paper, but writers store negative ones
                    // there too; both versions are read as signed, as ffmpeg does.
                    let offset = i64::from(c.u32()? as i32);
                    Ok((count, offset))
                })
                .collect::<Result<Vec<_>, VideoError>>()?
        }
        None => Vec::new(),
    };

    let mut c = Cursor::new(path, "stsz", need(path, stbl, b"stsz", "stbl")?);
    c.take(4)?;
    let constant = c.u32()?;
    let sizes = if constant == 0 {
        let n = c.count(4)?;
        (0..n)
            .map(|_| Ok(u64::from(c.u32()?)))
            .collect::<Result<Vec<_>, VideoError>>()?
    } else {
        let n = c.u32()? as usize;
        // Without a table the count is only bounded by the bytes the samples would fill.
        if (n as u64).saturating_mul(u64::from(constant)) > file_len {
            return Err(bad(
                path,
                format!("'stsz' claims {n} samples of {constant} bytes, more than the file holds"),
            ));
        }
        vec![u64::from(constant); n]
    };

    let sync = match child(path, stbl, b"stss")? {
        Some(stss) => {
            let mut c = Cursor::new(path, "stss", stss);
            c.take(4)?;
            let n = c.count(4)?;
            Some(
                (0..n)
                    .map(|_| c.u32())
                    .collect::<Result<Vec<_>, VideoError>>()?,
            )
        }
        None => None,
    };

    let mut c = Cursor::new(path, "stsc", need(path, stbl, b"stsc", "stbl")?);
    c.take(4)?;
    let n = c.count(12)?;
    let stsc = (0..n)
        .map(|_| {
            let first = c.u32()?;
            let per = c.u32()?;
            c.u32()?;
            Ok((first, per))
        })
        .collect::<Result<Vec<_>, VideoError>>()?;

    let chunk_offsets = if let Some(stco) = child(path, stbl, b"stco")? {
        let mut c = Cursor::new(path, "stco", stco);
        c.take(4)?;
        let n = c.count(4)?;
        (0..n)
            .map(|_| Ok(u64::from(c.u32()?)))
            .collect::<Result<Vec<_>, VideoError>>()?
    } else {
        let co64 = child(path, stbl, b"co64")?
            .ok_or_else(|| bad(path, "no 'stco' or 'co64' box in 'stbl'"))?;
        let mut c = Cursor::new(path, "co64", co64);
        c.take(4)?;
        let n = c.count(8)?;
        (0..n)
            .map(|_| c.u64())
            .collect::<Result<Vec<_>, VideoError>>()?
    };

    Ok(Track {
        codec,
        width,
        height,
        timescale,
        movie_timescale: 0,
        stts,
        ctts,
        sizes,
        sync,
        stsc,
        chunk_offsets,
        avc,
        matrix: [0x0001_0000, 0, 0, 0x0001_0000],
        edits: None,
    })
}

fn parse_avcc(path: &Path, avcc: &[u8]) -> Result<AvcConfig, VideoError> {
    let mut c = Cursor::new(path, "avcC", avcc);
    c.take(4)?;
    let nal_length_size = (c.u8()? & 3) as usize + 1;
    let mut param_sets = Vec::new();
    let n_sps = c.u8()? & 0x1f;
    for _ in 0..n_sps {
        let n = c.u16()? as usize;
        param_sets.push(c.take(n)?.to_vec());
    }
    let n_pps = c.u8()?;
    for _ in 0..n_pps {
        let n = c.u16()? as usize;
        param_sets.push(c.take(n)?.to_vec());
    }
    Ok(AvcConfig {
        nal_length_size,
        param_sets,
    })
}

impl Track {
    /// The H.264 configuration, or a format error naming the codec the track holds.
    pub(crate) fn require_avc(&self, path: &Path) -> Result<&AvcConfig, VideoError> {
        self.avc.as_ref().ok_or_else(|| {
            bad(
                path,
                format!(
                    "video codec '{}' is not H.264 (avc1)",
                    String::from_utf8_lossy(&self.codec)
                ),
            )
        })
    }

    fn info(&self, path: &Path) -> Result<Mp4Info, VideoError> {
        self.require_avc(path)?;
        let frames = self.check_timing(path)?;
        let duration = self.stts.iter().fold(0u64, |a, &(n, d)| {
            a.saturating_add(u64::from(n) * u64::from(d))
        });
        let fps = if duration == 0 {
            0.0
        } else {
            frames as f64 * f64::from(self.timescale) / duration as f64
        };
        Ok(Mp4Info {
            width: self.width,
            height: self.height,
            frames,
            fps,
            keyframes: self.sync.as_ref().map_or(frames, Vec::len),
        })
    }

    /// Checks that the time tables cover exactly the samples; returns the sample count.
    pub(crate) fn check_timing(&self, path: &Path) -> Result<usize, VideoError> {
        let frames = self.sizes.len();
        let stts_frames = self
            .stts
            .iter()
            .fold(0u64, |a, &(n, _)| a.saturating_add(u64::from(n)));
        if stts_frames != frames as u64 {
            return Err(bad(
                path,
                format!("'stts' times {stts_frames} samples but 'stsz' lists {frames}"),
            ));
        }
        if !self.ctts.is_empty() {
            let ctts_frames = self
                .ctts
                .iter()
                .fold(0u64, |a, &(n, _)| a.saturating_add(u64::from(n)));
            if ctts_frames != frames as u64 {
                return Err(bad(
                    path,
                    format!("'ctts' covers {ctts_frames} samples but 'stsz' lists {frames}"),
                ));
            }
        }
        Ok(frames)
    }

    /// Composition time of every sample (decode order), in track timescale ticks.
    pub(crate) fn composition_times(&self) -> Vec<i64> {
        let mut out = Vec::with_capacity(self.sizes.len());
        let mut dts = 0i64;
        for &(n, delta) in &self.stts {
            for _ in 0..n {
                out.push(dts);
                dts = dts.saturating_add(i64::from(delta));
            }
        }
        let mut i = 0usize;
        for &(n, offset) in &self.ctts {
            for _ in 0..n {
                if let Some(t) = out.get_mut(i) {
                    *t = t.saturating_add(offset);
                }
                i += 1;
            }
        }
        out
    }

    /// File offset of every sample, from the chunk table and the sample-to-chunk runs.
    pub(crate) fn sample_offsets(&self, path: &Path) -> Result<Vec<u64>, VideoError> {
        let mut offsets = Vec::with_capacity(self.sizes.len());
        let mut sample = 0usize;
        for (ci, &chunk_start) in self.chunk_offsets.iter().enumerate() {
            let chunk = ci as u64 + 1;
            let per = self
                .stsc
                .iter()
                .rev()
                .find(|&&(first, _)| u64::from(first) <= chunk)
                .map(|&(_, per)| per)
                .ok_or_else(|| bad(path, "'stsc' does not cover the first chunk"))?;
            let mut at = chunk_start;
            for _ in 0..per {
                let Some(&size) = self.sizes.get(sample) else {
                    return Err(bad(path, "chunks hold more samples than 'stsz' lists"));
                };
                offsets.push(at);
                at = at.saturating_add(size);
                sample += 1;
            }
        }
        if sample != self.sizes.len() {
            return Err(bad(
                path,
                format!(
                    "chunks hold {sample} samples but 'stsz' lists {}",
                    self.sizes.len()
                ),
            ));
        }
        Ok(offsets)
    }
}

/// Reads the samples of an H.264 track one by one as Annex-B access units (start codes instead
/// of length prefixes), checking every sample lies inside the file.
pub(crate) struct SampleReader {
    path: PathBuf,
    file: File,
    file_len: u64,
    offsets: Vec<u64>,
    sizes: Vec<u64>,
    nal_length_size: usize,
    next: usize,
    sample: Vec<u8>,
}

impl SampleReader {
    pub(crate) fn new(path: &Path, file: File, track: &Track) -> Result<Self, VideoError> {
        let avc = track.require_avc(path)?;
        let file_len = file.metadata().map_err(|e| VideoError::io(path, e))?.len();
        Ok(SampleReader {
            path: path.to_path_buf(),
            file,
            file_len,
            offsets: track.sample_offsets(path)?,
            sizes: track.sizes.clone(),
            nal_length_size: avc.nal_length_size,
            next: 0,
            sample: Vec::new(),
        })
    }

    pub(crate) fn len(&self) -> usize {
        self.sizes.len()
    }

    /// Continues from sample `i` (0-based).
    pub(crate) fn seek_to(&mut self, i: usize) {
        self.next = i.min(self.sizes.len());
    }

    /// The next sample's NAL units, appended to `annexb` (cleared first) with 4-byte start
    /// codes; `None` after the last sample.
    pub(crate) fn next_sample(
        &mut self,
        annexb: &mut Vec<u8>,
    ) -> Option<Result<usize, VideoError>> {
        let i = self.next;
        let (&offset, &size) = (self.offsets.get(i)?, self.sizes.get(i)?);
        self.next += 1;
        Some(self.read(i, offset, size, annexb).map(|()| i))
    }

    fn read(
        &mut self,
        i: usize,
        offset: u64,
        size: u64,
        annexb: &mut Vec<u8>,
    ) -> Result<(), VideoError> {
        let path = &self.path;
        if offset
            .checked_add(size)
            .is_none_or(|end| end > self.file_len)
        {
            return Err(bad(
                path,
                format!(
                    "sample {i} ({size} bytes at {offset}) lies past the end of the file: the file \
                     is truncated"
                ),
            ));
        }
        self.sample.resize(size as usize, 0);
        self.file
            .seek(SeekFrom::Start(offset))
            .map_err(|e| VideoError::io(path, e))?;
        self.file
            .read_exact(&mut self.sample)
            .map_err(|e| VideoError::io(path, e))?;
        annexb.clear();
        let mut rest = &self.sample[..];
        let ls = self.nal_length_size;
        while !rest.is_empty() {
            if rest.len() < ls {
                return Err(bad(path, format!("sample {i}: truncated NAL length")));
            }
            let n = rest[..ls]
                .iter()
                .fold(0usize, |a, &b| (a << 8) | b as usize);
            rest = &rest[ls..];
            if n > rest.len() {
                return Err(bad(
                    path,
                    format!("sample {i}: NAL unit runs past the sample"),
                ));
            }
            annexb.extend_from_slice(&[0, 0, 0, 1]);
            annexb.extend_from_slice(&rest[..n]);
            rest = &rest[n..];
        }
        Ok(())
    }
}

/// The `avcC` parameter sets as one Annex-B buffer (what the decoder is fed first).
pub(crate) fn param_sets_annexb(path: &Path, avc: &AvcConfig) -> Result<Vec<u8>, VideoError> {
    let mut annexb = Vec::new();
    for ps in &avc.param_sets {
        if !matches!(ps.first().map(|h| h & 0x1f), Some(NAL_SPS | NAL_PPS)) {
            return Err(bad(
                path,
                "'avcC' holds a NAL unit that is not an SPS or PPS",
            ));
        }
        annexb.extend_from_slice(&[0, 0, 0, 1]);
        annexb.extend_from_slice(ps);
    }
    Ok(annexb)
}

/// A decoded OpenH264 picture as RGB u8 HWC.
fn yuv_to_rgb(
    path: &Path,
    yuv: &openh264::decoder::DecodedYUV<'_>,
    matrix: crate::yuv::YuvMatrix,
) -> Result<(usize, usize, Vec<u8>), VideoError> {
    use openh264::formats::YUVSource;
    let (w, h) = yuv.dimensions();
    let (ys, us, vs) = yuv.strides();
    let fits = |plane: &[u8], stride: usize, rows: usize, cols: usize| {
        rows == 0 || (stride >= cols && plane.len() >= (rows - 1) * stride + cols)
    };
    let (cw, ch) = (w.div_ceil(2), h.div_ceil(2));
    if us != vs
        || !fits(yuv.y(), ys, h, w)
        || !fits(yuv.u(), us, ch, cw)
        || !fits(yuv.v(), vs, ch, cw)
    {
        return Err(VideoError::Decode(format!(
            "{}: decoder returned inconsistent planes for a {w}x{h} picture",
            path.display()
        )));
    }
    let rgb = i420_to_rgb_with(
        &I420 {
            y: yuv.y(),
            u: yuv.u(),
            v: yuv.v(),
            y_stride: ys,
            uv_stride: us,
            width: w,
            height: h,
        },
        matrix,
    );
    Ok((w, h, rgb))
}

/// An OpenH264 decoder fed one access unit at a time; pictures come out as RGB.
pub(crate) struct H264Decoder {
    path: PathBuf,
    decoder: openh264::decoder::Decoder,
    matrix: crate::yuv::YuvMatrix,
}

/// A decoded picture: width, height, RGB u8 HWC.
pub(crate) type Picture = (usize, usize, Vec<u8>);

impl H264Decoder {
    pub(crate) fn new(path: &Path, matrix: crate::yuv::YuvMatrix) -> Result<Self, VideoError> {
        use openh264::decoder::{Decoder, DecoderConfig};
        use openh264::OpenH264API;
        let decoder = Decoder::with_api_config(OpenH264API::from_source(), DecoderConfig::new())
            .map_err(|e| VideoError::Decode(format!("OpenH264 setup: {e}")))?;
        Ok(H264Decoder {
            path: path.to_path_buf(),
            decoder,
            matrix,
        })
    }

    /// Decodes one access unit (`sample` names it in errors; `None` for the parameter sets).
    pub(crate) fn decode(
        &mut self,
        annexb: &[u8],
        sample: Option<usize>,
    ) -> Result<Option<Picture>, VideoError> {
        let path = &self.path;
        let yuv = self.decoder.decode(annexb).map_err(|e| {
            VideoError::Decode(match sample {
                Some(i) => format!("{} sample {i}: {e}", path.display()),
                None => format!("{} parameter sets: {e}", path.display()),
            })
        })?;
        yuv.map(|yuv| yuv_to_rgb(path, &yuv, self.matrix))
            .transpose()
    }

    /// The pictures still buffered after the last access unit.
    pub(crate) fn flush(&mut self) -> Result<Vec<Picture>, VideoError> {
        let path = &self.path;
        let matrix = self.matrix;
        let rest = self
            .decoder
            .flush_remaining()
            .map_err(|e| VideoError::Decode(format!("{} flushing: {e}", path.display())))?;
        rest.iter()
            .map(|yuv| yuv_to_rgb(path, yuv, matrix))
            .collect()
    }
}

/// Size, frame count, frame rate and keyframe count of the first video track of an mp4.
pub fn read_mp4_info(path: &Path) -> Result<Mp4Info, VideoError> {
    let (_, track) = open_track(path)?;
    track.info(path)
}

/// Demuxes the first video track without decoding it: the box tree, the sample tables, the
/// timing checks and every sample's NAL units read (as Annex-B). Returns the sample count. The
/// container half of [`decode_mp4`], for checks and fuzzing.
pub fn demux_mp4(path: &Path) -> Result<usize, VideoError> {
    let (file, track) = open_track(path)?;
    track.check_timing(path)?;
    let _ = track.composition_times();
    let avc = track.require_avc(path)?;
    param_sets_annexb(path, avc)?;
    let mut samples = SampleReader::new(path, file, &track)?;
    let mut annexb = Vec::new();
    let mut n = 0;
    while let Some(i) = samples.next_sample(&mut annexb) {
        i?;
        n += 1;
    }
    Ok(n)
}

/// Decodes every frame of the first video track (H.264, via OpenH264) to RGB u8 HWC of the
/// coded size, in decode order, all in memory: a check for the files this crate writes. Other
/// videos are read with [`crate::read::VideoReader`], which streams, checks the stream is one
/// OpenH264 decodes correctly, and uses ffmpeg when it is not.
pub fn decode_mp4(path: &Path) -> Result<Vec<Vec<u8>>, VideoError> {
    let (file, track) = open_track(path)?;
    let avc = track.require_avc(path)?;
    let mut samples = SampleReader::new(path, file, &track)?;
    let mut decoder = H264Decoder::new(path, crate::yuv::YuvMatrix::Bt601)?;
    let mut frames = Vec::with_capacity(track.sizes.len());
    let annexb = param_sets_annexb(path, avc)?;
    if !annexb.is_empty() {
        if let Some((_, _, rgb)) = decoder.decode(&annexb, None)? {
            frames.push(rgb);
        }
    }
    let mut annexb = Vec::new();
    while let Some(i) = samples.next_sample(&mut annexb) {
        let i = i?;
        if let Some((_, _, rgb)) = decoder.decode(&annexb, Some(i))? {
            frames.push(rgb);
        }
    }
    frames.extend(decoder.flush()?.into_iter().map(|(_, _, rgb)| rgb));
    Ok(frames)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Indexes that only a very long or very large file needs: 64-bit chunk offsets and
    /// version-1 (64-bit) durations, written and read back without the gigabytes.
    #[test]
    fn co64_and_long_durations_round_trip() {
        let sizes = [100u32, 200, 300, 400, 500];
        let sync = [1u32, 4];
        let ix = Index {
            width: 64,
            height: 48,
            timescale: 1000,
            // 5 frames of 2^31 ticks: over u32::MAX in total.
            delta: 1 << 31,
            sizes: &sizes,
            sync: &sync,
            sps: &[0x67, 66, 0xc0, 30],
            pps: &[0x68, 0xce],
            samples_per_chunk: 2,
        };
        let start = 5u64 << 32;
        let moov = moov(&ix, start, true);
        let body = &moov[8..];
        let path = Path::new("synthetic.mp4");
        let track = read_track(path, body, u64::MAX).unwrap();
        let expected = [start, start + 100, start + 300, start + 600, start + 1000];
        assert_eq!(track.sample_offsets(path).unwrap(), expected);
        let info = track.info(path).unwrap();
        assert_eq!(
            (info.width, info.height, info.frames, info.keyframes),
            (64, 48, 5, 2)
        );
        let fps = 1000.0 / f64::from(1u32 << 31);
        assert!(
            (info.fps - fps).abs() < 1e-15,
            "fps {} expected {fps}",
            info.fps
        );
        let has = |kind: &[u8]| body.windows(4).any(|w| w == kind);
        assert!(has(b"co64") && !has(b"stco"), "64-bit chunk offsets");
    }

    #[test]
    fn timing_is_exact_for_common_rates() {
        for (fps, ts, delta) in [
            (25.0, 1000, 40),
            (30.0, 3000, 100),
            (30000.0 / 1001.0, 30000, 1001),
            (29.97, 2997, 100),
            (12.5, 1000, 80),
            (60.0, 3000, 50),
            (24.0, 3000, 125),
            (0.5, 1000, 2000),
        ] {
            let (t, d) = timing(fps);
            assert_eq!((t, d), (ts, delta), "fps {fps}");
            assert!(
                (t as f64 / d as f64 - fps).abs() < 1e-9,
                "fps {fps}: {t}/{d}"
            );
        }
    }
}
