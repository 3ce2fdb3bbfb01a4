//! The tracked folder: the release layout (TRACKING.md section 6, GAGAVATAR.md section 10) plus
//! our `track.json`.
//!
//! * `img_lmdb/`: LMDB, key `<name>_<i>` (i = frame index, every frame kept), value the 512
//!   crop as a JPEG of quality 95 (the release's `encode_jpeg(..., quality=95)`).
//! * `optim.pkl`: dict key -> the six float32 arrays `bbox [4]`, `shapecode [300]`,
//!   `expcode [100]`, `posecode [6]`, `eyecode [6]`, `transform_matrix [3,4]` (the raw fits;
//!   frames without a face interpolated).
//! * `smoothed.pkl` (video only): the same with the smoothed records; the release's driver
//!   loader prefers it.
//! * `track.json`: per frame the final record, the crop window `[x0, y0, x1, y1]` in frame
//!   pixels, whether a face was found, the detected 70 points and the fitted FLAME's 70
//!   landmarks reprojected, both in frame pixels (corner convention).
//!
//! Names: the release's training loader takes the video id as the text before the *first*
//! underscore and the frame as the text after the last, so [`sanitize_name`] keeps names to
//! ASCII letters, digits and `-`.
//!
//! The folder is built under a temporary sibling and moved into place whole, so a failure
//! leaves nothing behind; an existing folder is replaced only if it holds nothing but these
//! four entries (we never delete files we did not write).

use std::collections::BTreeMap;
use std::path::Path;

use gagavatar_data::records::records_to_pickle;
use gagavatar_flame::TrackedFrame;
use gagavatar_formats::atomic::{replace_dir, temp_sibling};
use gagavatar_formats::lmdb::write_lmdb;
use image::RgbImage;
use serde::{Deserialize, Serialize};

use crate::error::{Result, TrackError};
use crate::pipeline::{FrameTrack, TrackedPhoto, TrackedVideo};

pub const IMAGES_DIR: &str = "img_lmdb";
pub const OPTIM_FILE: &str = "optim.pkl";
pub const SMOOTHED_FILE: &str = "smoothed.pkl";
pub const TRACK_JSON: &str = "track.json";
/// The release's JPEG quality for LMDB crops.
pub const JPEG_QUALITY: u8 = 95;
pub const TRACK_JSON_FORMAT: &str = "gagavatar-track";
pub const TRACK_JSON_VERSION: u32 = 1;

/// Keeps ASCII letters, digits and `-` (everything else becomes `-`); empty names become
/// `track`.
pub fn sanitize_name(stem: &str) -> String {
    let s: String = stem
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '-'
            }
        })
        .collect();
    if s.is_empty() {
        "track".into()
    } else {
        s
    }
}

pub fn frame_key(name: &str, i: usize) -> String {
    format!("{name}_{i}")
}

pub fn encode_jpeg(img: &RgbImage) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, JPEG_QUALITY)
        .encode_image(img)
        .map_err(|e| TrackError::Output {
            path: "<jpeg>".into(),
            reason: format!("cannot encode a crop: {e}"),
        })?;
    Ok(out)
}

/// A record in `track.json` (float32 values, as in the pickles).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JsonRecord {
    pub bbox: [f32; 4],
    pub shapecode: Vec<f32>,
    pub expcode: Vec<f32>,
    pub posecode: Vec<f32>,
    pub eyecode: Vec<f32>,
    pub transform_matrix: [[f32; 4]; 3],
}

impl JsonRecord {
    fn from_record(r: &TrackedFrame) -> Result<Self> {
        let f = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        let (Some(b), Some(tm)) = (r.bbox, r.transform_matrix) else {
            return Err(TrackError::Output {
                path: TRACK_JSON.into(),
                reason: "a record lacks its bbox or transform".into(),
            });
        };
        Ok(Self {
            bbox: b.map(|x| x as f32),
            shapecode: f(&r.shapecode),
            expcode: f(&r.expcode),
            posecode: f(&r.posecode),
            eyecode: f(&r.eyecode),
            transform_matrix: tm.map(|row| row.map(|x| x as f32)),
        })
    }

    pub fn to_record(&self) -> TrackedFrame {
        let f = |v: &[f32]| v.iter().map(|&x| x as f64).collect::<Vec<f64>>();
        TrackedFrame {
            shapecode: f(&self.shapecode),
            expcode: f(&self.expcode),
            posecode: f(&self.posecode),
            eyecode: f(&self.eyecode),
            transform_matrix: Some(self.transform_matrix.map(|r| r.map(|x| x as f64))),
            bbox: Some(self.bbox.map(|x| x as f64)),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JsonFrame {
    pub key: String,
    pub index: usize,
    pub face_found: bool,
    /// Frame width and height.
    pub image_size: [u32; 2],
    /// Crop window `[x0, y0, x1, y1]` in frame pixels.
    pub window: [i64; 4],
    /// The 70 detected points (iBUG 68 + pupils), frame pixels; `null` entries were not
    /// detected; `null` when no face was found.
    pub landmarks_detected: Option<Vec<Option<[f64; 2]>>>,
    /// The fitted FLAME's 70 landmarks reprojected, frame pixels.
    pub landmarks_fitted: Vec<Option<[f64; 2]>>,
    /// RMS landmark error of the fit, in 512-crop pixels.
    pub fit_rms_px: Option<f64>,
    pub record: JsonRecord,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackJson {
    pub format: String,
    pub version: u32,
    /// `photo` or `video`.
    pub kind: String,
    pub name: String,
    /// What the 2D coordinates mean.
    pub coordinates: String,
    /// Frames the video's shape was solved on.
    pub keyframes: Vec<usize>,
    /// The source video's frame rate (absent for a photo, and in folders written before it was
    /// kept).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
    pub frames: Vec<JsonFrame>,
}

const COORDINATES: &str =
    "pixels of the original frame; top-left image corner at (0, 0), pixel (row i, column j) \
     centred at (j + 0.5, i + 0.5)";

fn json_frame(name: &str, i: usize, f: &FrameTrack) -> Result<JsonFrame> {
    Ok(JsonFrame {
        key: frame_key(name, i),
        index: i,
        face_found: f.face_found,
        image_size: f.image_size,
        window: f.window.as_array(),
        landmarks_detected: f.detected.clone(),
        landmarks_fitted: f.reprojected.clone(),
        fit_rms_px: f.fit_rms_px,
        record: JsonRecord::from_record(&f.record)?,
    })
}

/// Reads a `track.json`.
pub fn read_track_json(path: &Path) -> Result<TrackJson> {
    let text = std::fs::read_to_string(path).map_err(|e| TrackError::Output {
        path: path.to_owned(),
        reason: format!("cannot read: {e}"),
    })?;
    let t: TrackJson = serde_json::from_str(&text).map_err(|e| TrackError::Output {
        path: path.to_owned(),
        reason: format!("not a track.json: {e}"),
    })?;
    if t.format != TRACK_JSON_FORMAT || t.version != TRACK_JSON_VERSION {
        return Err(TrackError::Output {
            path: path.to_owned(),
            reason: format!(
                "format {} version {}, expected {TRACK_JSON_FORMAT} {TRACK_JSON_VERSION}",
                t.format, t.version
            ),
        });
    }
    Ok(t)
}

/// Refuses to replace an existing path that holds anything we did not write.
fn check_replaceable(dir: &Path) -> Result<()> {
    if !dir.exists() {
        return Ok(());
    }
    let err = |reason: String| TrackError::Output {
        path: dir.to_owned(),
        reason,
    };
    if !dir.is_dir() {
        return Err(err("exists and is not a directory".into()));
    }
    let entries = std::fs::read_dir(dir).map_err(|e| err(format!("cannot list: {e}")))?;
    for e in entries {
        let e = e.map_err(|e| err(format!("cannot list: {e}")))?;
        let name = e.file_name().to_string_lossy().into_owned();
        if ![IMAGES_DIR, OPTIM_FILE, SMOOTHED_FILE, TRACK_JSON].contains(&name.as_str()) {
            return Err(err(format!(
                "refusing to replace it: it holds `{name}`, which a tracking run does not write"
            )));
        }
    }
    Ok(())
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).map_err(|e| TrackError::Output {
        path: path.to_owned(),
        reason: format!("cannot write: {e}"),
    })
}

/// Builds the folder in a temporary sibling with `fill`, then moves it into place.
fn write_dir(dir: &Path, fill: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    check_replaceable(dir)?;
    if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|e| TrackError::Output {
            path: parent.to_owned(),
            reason: format!("cannot create: {e}"),
        })?;
    }
    let tmp = temp_sibling(dir);
    std::fs::create_dir_all(&tmp).map_err(|e| TrackError::Output {
        path: tmp.clone(),
        reason: format!("cannot create: {e}"),
    })?;
    let result = fill(&tmp).and_then(|()| {
        replace_dir(&tmp, dir).map_err(|e| TrackError::Output {
            path: dir.to_owned(),
            reason: format!("cannot move the new folder into place: {e}"),
        })
    });
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&tmp);
    }
    result
}

fn pickle(path: &Path, records: &BTreeMap<String, TrackedFrame>) -> Result<()> {
    let bytes = records_to_pickle(path, records)?;
    write_file(path, &bytes)
}

fn json(path: &Path, t: &TrackJson) -> Result<()> {
    let text = serde_json::to_string(t).map_err(|e| TrackError::Output {
        path: path.to_owned(),
        reason: e.to_string(),
    })?;
    write_file(path, text.as_bytes())
}

/// Writes a tracked photo: `img_lmdb/` (one crop, key `<name>_0`), `optim.pkl`, `track.json`.
/// `crop` is the (matted) 512 crop through the photo's window.
pub fn write_photo(dir: &Path, name: &str, photo: &TrackedPhoto, crop: &RgbImage) -> Result<()> {
    check_crop(crop, 0)?;
    write_photo_jpeg(dir, name, photo, encode_jpeg(crop)?)
}

/// [`write_photo`] with the crop already encoded ([`encode_jpeg`] of the 512 crop), so a caller
/// that keeps the crop holds exactly the pixels the folder stores.
pub fn write_photo_jpeg(dir: &Path, name: &str, photo: &TrackedPhoto, jpeg: Vec<u8>) -> Result<()> {
    let name = sanitize_name(name);
    let key = frame_key(&name, 0);
    let records = BTreeMap::from([(key.clone(), photo.frame.record.clone())]);
    let track = TrackJson {
        format: TRACK_JSON_FORMAT.into(),
        version: TRACK_JSON_VERSION,
        kind: "photo".into(),
        name: name.clone(),
        coordinates: COORDINATES.into(),
        keyframes: vec![0],
        fps: None,
        frames: vec![json_frame(&name, 0, &photo.frame)?],
    };
    write_dir(dir, |tmp| {
        write_lmdb(&tmp.join(IMAGES_DIR), [(key.into_bytes(), jpeg)])?;
        pickle(&tmp.join(OPTIM_FILE), &records)?;
        json(&tmp.join(TRACK_JSON), &track)
    })
}

fn check_crop(img: &RgbImage, i: usize) -> Result<()> {
    if img.dimensions() != (512, 512) {
        return Err(TrackError::Output {
            path: IMAGES_DIR.into(),
            reason: format!(
                "crop {i} is {}x{}, expected 512x512",
                img.width(),
                img.height()
            ),
        });
    }
    Ok(())
}

/// Writes a tracked video: `img_lmdb/` (one crop per frame, streamed from `crops` in frame
/// order), `optim.pkl` (raw), `smoothed.pkl`, `track.json`. `crops` must yield exactly one
/// 512x512 crop per frame; its first error stops the write.
pub fn write_video(
    dir: &Path,
    name: &str,
    video: &TrackedVideo,
    crops: impl IntoIterator<Item = Result<RgbImage>>,
) -> Result<()> {
    let jpegs = crops.into_iter().enumerate().map(|(i, item)| {
        item.and_then(|img| {
            check_crop(&img, i)?;
            encode_jpeg(&img)
        })
    });
    write_video_jpegs(dir, name, video, jpegs)
}

/// [`write_video`] with the crops already encoded (e.g. by [`encode_jpeg`] on other threads):
/// one JPEG of a 512x512 crop per frame, in frame order.
pub fn write_video_jpegs(
    dir: &Path,
    name: &str,
    video: &TrackedVideo,
    jpegs: impl IntoIterator<Item = Result<Vec<u8>>>,
) -> Result<()> {
    write_video_dir(dir, name, video.frames.len(), jpegs, || Ok(video)).map(|_| ())
}

/// Writes a tracked video whose records are finished while its crops are written (the fit can
/// run beside the cropping, and no frame or crop is held longer than it takes to write it):
/// the `n` JPEGs are streamed into `img_lmdb/` first, then `finish` gives the tracked video
/// (its `n` frames), whose records, `optim.pkl`, `smoothed.pkl` and `track.json` complete the
/// folder. The first error, of either, leaves nothing behind. Returns the tracked video.
pub fn write_video_streaming(
    dir: &Path,
    name: &str,
    n: usize,
    jpegs: impl IntoIterator<Item = Result<Vec<u8>>>,
    finish: impl FnOnce() -> Result<TrackedVideo>,
) -> Result<TrackedVideo> {
    write_video_dir(dir, name, n, jpegs, finish)
}

fn write_video_dir<V: std::borrow::Borrow<TrackedVideo>>(
    dir: &Path,
    name: &str,
    n: usize,
    jpegs: impl IntoIterator<Item = Result<Vec<u8>>>,
    finish: impl FnOnce() -> Result<V>,
) -> Result<V> {
    let name = sanitize_name(name);
    let keys: Vec<String> = (0..n).map(|i| frame_key(&name, i)).collect();
    let mut done = None;
    write_dir(dir, |tmp| {
        let mut failure: Option<TrackError> = None;
        let mut count = 0usize;
        let mut crops = jpegs.into_iter();
        let entries = std::iter::from_fn(|| {
            if failure.is_some() || count >= n {
                return None;
            }
            match crops.next()? {
                Ok(jpeg) => {
                    let key = keys[count].clone().into_bytes();
                    count += 1;
                    Some((key, jpeg))
                }
                Err(e) => {
                    failure = Some(e);
                    None
                }
            }
        });
        let written = write_lmdb(&tmp.join(IMAGES_DIR), entries);
        if let Some(e) = failure {
            return Err(e);
        }
        written?;
        if count != n || crops.next().is_some() {
            return Err(TrackError::Output {
                path: IMAGES_DIR.into(),
                reason: format!("{n} frames tracked but a different number of crops given"),
            });
        }
        let owned = finish()?;
        let video: &TrackedVideo = owned.borrow();
        write_records(tmp, &name, &keys, video)?;
        done = Some(owned);
        Ok(())
    })?;
    done.ok_or_else(|| TrackError::Output {
        path: dir.to_owned(),
        reason: "internal: the folder was written without its records".into(),
    })
}

/// `optim.pkl`, `smoothed.pkl` and `track.json` of a tracked video, into `tmp`.
fn write_records(tmp: &Path, name: &str, keys: &[String], video: &TrackedVideo) -> Result<()> {
    let n = keys.len();
    if video.frames.len() != n || video.raw_records.len() != n {
        return Err(TrackError::Output {
            path: tmp.to_owned(),
            reason: format!(
                "{n} crops but {} frames and {} raw records",
                video.frames.len(),
                video.raw_records.len()
            ),
        });
    }
    let optim: BTreeMap<String, TrackedFrame> = keys
        .iter()
        .cloned()
        .zip(video.raw_records.iter().cloned())
        .collect();
    pickle(&tmp.join(OPTIM_FILE), &optim)?;
    drop(optim);
    let smoothed: BTreeMap<String, TrackedFrame> = keys
        .iter()
        .cloned()
        .zip(video.frames.iter().map(|f| f.record.clone()))
        .collect();
    pickle(&tmp.join(SMOOTHED_FILE), &smoothed)?;
    drop(smoothed);
    let path = tmp.join(TRACK_JSON);
    let file = std::fs::File::create(&path).map_err(|e| TrackError::Output {
        path: path.clone(),
        reason: format!("cannot write: {e}"),
    })?;
    let mut out = std::io::BufWriter::new(file);
    let err = |reason: String| TrackError::Output {
        path: path.clone(),
        reason,
    };
    serde_json::to_writer(&mut out, &VideoJson { name, video }).map_err(|e| err(e.to_string()))?;
    std::io::Write::flush(&mut out).map_err(|e| err(format!("cannot write: {e}")))
}

/// A video's `track.json` as a value (what [`write_video`] writes frame by frame without holding
/// it; a test compares the two byte for byte).
pub fn video_track_json(name: &str, video: &TrackedVideo) -> Result<TrackJson> {
    let name = sanitize_name(name);
    Ok(TrackJson {
        format: TRACK_JSON_FORMAT.into(),
        version: TRACK_JSON_VERSION,
        kind: "video".into(),
        name: name.clone(),
        coordinates: COORDINATES.into(),
        keyframes: video.keyframes.clone(),
        fps: video.fps,
        frames: video
            .frames
            .iter()
            .enumerate()
            .map(|(i, f)| json_frame(&name, i, f))
            .collect::<Result<_>>()?,
    })
}

/// A video's `track.json`, serialized frame by frame straight to the file, so a long clip's
/// JSON is never held whole: the same fields in the same order as [`TrackJson`].
struct VideoJson<'a> {
    name: &'a str,
    video: &'a TrackedVideo,
}

impl Serialize for VideoJson<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        use serde::ser::{Error, SerializeSeq, SerializeStruct};
        struct Frames<'a>(&'a VideoJson<'a>);
        impl Serialize for Frames<'_> {
            fn serialize<S: serde::Serializer>(
                &self,
                s: S,
            ) -> std::result::Result<S::Ok, S::Error> {
                let frames = &self.0.video.frames;
                let mut seq = s.serialize_seq(Some(frames.len()))?;
                for (i, f) in frames.iter().enumerate() {
                    let jf = json_frame(self.0.name, i, f).map_err(S::Error::custom)?;
                    seq.serialize_element(&jf)?;
                }
                seq.end()
            }
        }
        let mut m = s.serialize_struct("TrackJson", 8)?;
        m.serialize_field("format", TRACK_JSON_FORMAT)?;
        m.serialize_field("version", &TRACK_JSON_VERSION)?;
        m.serialize_field("kind", "video")?;
        m.serialize_field("name", self.name)?;
        m.serialize_field("coordinates", COORDINATES)?;
        m.serialize_field("keyframes", &self.video.keyframes)?;
        match self.video.fps {
            Some(fps) => m.serialize_field("fps", &fps)?,
            None => m.skip_field("fps")?,
        }
        m.serialize_field("frames", &Frames(self))?;
        m.end()
    }
}
