//! Tracking an input file into a tracked folder, either where the caller says or in the
//! content-addressed cache (so `reenact`, `orbit`, the Python package and the server take raw
//! photos and videos, and track each only once), and reading a tracked folder's frames back.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use gagavatar_flame::TrackedFrame;
use gagavatar_formats::atomic::write_atomic;
use gagavatar_track::output::{frame_key, sanitize_name, IMAGES_DIR, OPTIM_FILE, SMOOTHED_FILE};
use gagavatar_track::TrackOptions;
use image::RgbImage;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::error::{input_err, io_err, Result};
use crate::flame_source::FlameSource;
use crate::monitor::{check, Finish, Monitor};
use crate::tracking::{input_kind, input_name, InputKind, Tracker, VideoSummary};

/// Bump when the tracker's results change for the same input (a new fit, crop or matte, or a new
/// field in its output: 5 writes the video's frame rate into track.json), so cached tracks made by
/// older builds are not reused. The cache key also holds the crate version and the tracking options.
pub const TRACKER_REVISION: u32 = 5;

const CACHE_FORMAT: &str = "gagavatar-track-cache 1";

/// Where a tracking goes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TrackTo {
    /// The content-addressed cache ([`cache_root`]): a folder a previous run made for the same
    /// bytes, FLAME asset and tracker is reused.
    Cache,
    /// This folder (replaced if it holds a previous tracking and nothing else); always tracks.
    Folder(PathBuf),
}

/// What [`track_input`] made or found: the folder and what it holds, in frame order, with the
/// values as the folder stores them (float32), so a run that finds it in the cache computes
/// from exactly the same numbers as the run that made it.
#[derive(Debug, Clone)]
pub struct Tracked {
    pub dir: PathBuf,
    pub kind: InputKind,
    /// The frames' keys (`<name>_<i>`), in frame order.
    pub names: Vec<String>,
    /// The records (a video's smoothed ones, as a driver reads them), in frame order.
    pub records: Vec<TrackedFrame>,
    /// A photo's 512 crop, as stored (matted, through its JPEG).
    pub crop: Option<RgbImage>,
    /// The video's frame rate (`gagavatar_data::driver::DEFAULT_FPS` for a photo).
    pub fps: f64,
    /// Found in the cache: nothing was tracked.
    pub cached: bool,
    /// Wall seconds of the call.
    pub seconds: f64,
    /// What a video run did (`None` for a photo and for a cache hit).
    pub video: Option<VideoSummary>,
}

/// What the cache keeps beside a tracked folder; written after the folder, so its presence
/// means the folder is complete.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CacheMeta {
    pub format: String,
    pub kind: InputKind,
    pub input: String,
    pub frames: usize,
    pub fps: f64,
}

/// The cache folder: `$GAGAVATAR_CACHE`, else `$XDG_CACHE_HOME/gagavatar`, else
/// `~/.cache/gagavatar`.
pub fn cache_root() -> Result<PathBuf> {
    let env = |k: &str| std::env::var_os(k).filter(|v| !v.is_empty());
    if let Some(p) = env("GAGAVATAR_CACHE") {
        return Ok(PathBuf::from(p));
    }
    if let Some(p) = env("XDG_CACHE_HOME") {
        return Ok(PathBuf::from(p).join("gagavatar"));
    }
    if let Some(h) = env("HOME") {
        return Ok(PathBuf::from(h).join(".cache").join("gagavatar"));
    }
    Err(input_err(
        "the tracking cache",
        "no cache folder: set GAGAVATAR_CACHE (or XDG_CACHE_HOME or HOME)",
    ))
}

fn hash_file(h: &mut Sha256, path: &Path) -> Result<()> {
    let mut f = std::fs::File::open(path).map_err(io_err("cannot read", path))?;
    let mut buf = vec![0u8; 1 << 20];
    let mut total = 0u64;
    loop {
        let k = f.read(&mut buf).map_err(io_err("cannot read", path))?;
        if k == 0 {
            break;
        }
        h.update(&buf[..k]);
        total += k as u64;
    }
    h.update(total.to_le_bytes());
    Ok(())
}

/// Hashes a file's bytes, or a folder's files (names and bytes, in name order).
fn hash_input(h: &mut Sha256, path: &Path) -> Result<()> {
    if !path.is_dir() {
        return hash_file(h, path);
    }
    let mut entries: Vec<PathBuf> = std::fs::read_dir(path)
        .map_err(io_err("cannot list", path))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file())
        .collect();
    entries.sort();
    for p in entries {
        let name = p.file_name().unwrap_or_default().to_string_lossy();
        h.update((name.len() as u64).to_le_bytes());
        h.update(name.as_bytes());
        hash_file(h, &p)?;
    }
    Ok(())
}

/// The cache key of tracking `input` with the FLAME `flame`: SHA-256 of the tracker's identity
/// (revision, crate version, options), the FLAME asset's bytes (or `synthetic`), and the
/// input's bytes.
pub fn cache_key(input: &Path, flame: &FlameSource, opts: &TrackOptions) -> Result<String> {
    let mut h = Sha256::new();
    h.update(
        format!(
            "gagavatar-track-cache r{TRACKER_REVISION} v{} {opts:?}\0",
            env!("CARGO_PKG_VERSION")
        )
        .as_bytes(),
    );
    match flame {
        FlameSource::File(p) => {
            h.update(b"flame:file\0");
            hash_file(&mut h, p)?;
        }
        _ => h.update(b"flame:synthetic(0)\0"),
    }
    h.update(b"input\0");
    hash_input(&mut h, input)?;
    Ok(h.finalize().iter().map(|b| format!("{b:02x}")).collect())
}

fn read_meta(path: &Path) -> Option<CacheMeta> {
    let text = std::fs::read_to_string(path).ok()?;
    let meta: CacheMeta = serde_json::from_str(&text).ok()?;
    (meta.format == CACHE_FORMAT).then_some(meta)
}

/// A tracked folder: `optim.pkl` or `smoothed.pkl` inside.
pub fn is_tracked_folder(path: &Path) -> bool {
    path.is_dir() && (path.join(OPTIM_FILE).is_file() || path.join(SMOOTHED_FILE).is_file())
}

fn cached_folder_complete(dir: &Path) -> bool {
    dir.join(IMAGES_DIR).exists() && is_tracked_folder(dir)
}

/// A record as a tracked folder stores it (float32 values), so a record kept in memory equals
/// the one read back.
pub fn as_stored(r: &TrackedFrame) -> TrackedFrame {
    let f = |v: &[f64]| v.iter().map(|&x| x as f32 as f64).collect::<Vec<f64>>();
    TrackedFrame {
        shapecode: f(&r.shapecode),
        expcode: f(&r.expcode),
        posecode: f(&r.posecode),
        eyecode: f(&r.eyecode),
        transform_matrix: r
            .transform_matrix
            .map(|m| m.map(|row| row.map(|x| x as f32 as f64))),
        bbox: r.bbox.map(|b| b.map(|x| x as f32 as f64)),
    }
}

/// Tracks `input` (a photo, a video or a folder of images) with `tracker`, into `to`. `what`
/// names the input in messages (`source`, `driver`); with `photo_only`, anything but a photo is
/// refused. `tracker` is only called when something has to be tracked (a cache hit loads no
/// model).
pub fn track_input(
    input: &Path,
    flame: &FlameSource,
    to: &TrackTo,
    what: &str,
    photo_only: bool,
    tracker: impl FnOnce() -> Result<std::sync::Arc<Tracker>>,
    monitor: &dyn Monitor,
) -> Result<Tracked> {
    let _finish = Finish(monitor);
    let t0 = Instant::now();
    if !input.exists() {
        return Err(input_err(
            format!("{what} {}", input.display()),
            "does not exist",
        ));
    }
    let kind = input_kind(input)?;
    if photo_only && kind != InputKind::Photo {
        return Err(input_err(
            format!("{what} {}", input.display()),
            "is not a photo (PNG, JPEG, WebP or BMP), a tracked folder or a record",
        ));
    }
    let (dir, meta_path) = match to {
        TrackTo::Folder(d) => (d.clone(), None),
        TrackTo::Cache => {
            let key = cache_key(input, flame, &TrackOptions::default())?;
            let root = cache_root()?.join("track");
            (root.join(&key), Some(root.join(format!("{key}.json"))))
        }
    };
    if let Some(mp) = &meta_path {
        if let Some(meta) = read_meta(mp).filter(|_| cached_folder_complete(&dir)) {
            let mut t = read_folder(&dir, meta.kind, Some(meta.fps))?;
            t.seconds = t0.elapsed().as_secs_f64();
            return Ok(t);
        }
    }
    check(monitor)?;
    let tracker = tracker()?;
    let mut tracked = match kind {
        InputKind::Photo => {
            monitor.stage("photo", Some(1));
            let p = tracker.track_photo_file(input, &dir, None)?;
            monitor.advance(1);
            let name = sanitize_name(&input_name(input));
            Tracked {
                dir: dir.clone(),
                kind,
                names: vec![frame_key(&name, 0)],
                records: vec![as_stored(p.record())],
                crop: Some(p.crop),
                fps: gagavatar_data::driver::DEFAULT_FPS,
                cached: false,
                seconds: 0.0,
                video: None,
            }
        }
        InputKind::Video => {
            let s = tracker.track_video_unfinished(input, &dir, None, monitor)?;
            let name = sanitize_name(&input_name(input));
            Tracked {
                dir: dir.clone(),
                kind,
                names: (0..s.frames).map(|i| frame_key(&name, i)).collect(),
                records: s
                    .video
                    .frames
                    .iter()
                    .map(|f| as_stored(&f.record))
                    .collect(),
                crop: None,
                fps: s.fps,
                cached: false,
                seconds: 0.0,
                video: Some(s),
            }
        }
    };
    if let Some(mp) = &meta_path {
        let meta = CacheMeta {
            format: CACHE_FORMAT.into(),
            kind,
            input: input.display().to_string(),
            frames: tracked.records.len(),
            fps: tracked.fps,
        };
        let text = serde_json::to_string_pretty(&meta)
            .map_err(|e| input_err("the cache's record", e.to_string()))?;
        write_atomic(mp, text.as_bytes())?;
    }
    tracked.seconds = t0.elapsed().as_secs_f64();
    Ok(tracked)
}

/// Reads a tracked folder back: its records in frame order (a video's smoothed ones), and for
/// a photo its crop.
pub fn read_tracked(dir: &Path, kind: InputKind) -> Result<Tracked> {
    read_folder(dir, kind, None)
}

/// [`read_tracked`]; `fps` when the caller knows it (a long video's `track.json` is large and
/// read only for its rate otherwise).
fn read_folder(dir: &Path, kind: InputKind, fps: Option<f64>) -> Result<Tracked> {
    let prefer = match kind {
        InputKind::Photo => [OPTIM_FILE, SMOOTHED_FILE],
        InputKind::Video => [SMOOTHED_FILE, OPTIM_FILE],
    };
    let pkl = prefer
        .iter()
        .map(|f| dir.join(f))
        .find(|p| p.is_file())
        .ok_or_else(|| input_err(dir.display().to_string(), "not a tracked folder"))?;
    let records = gagavatar_data::read_records(&pkl)?;
    let mut names: Vec<String> = records.keys().cloned().collect();
    gagavatar_data::sort_frame_names(&mut names);
    let mut records = records;
    let ordered: Vec<TrackedFrame> = names.iter().filter_map(|k| records.remove(k)).collect();
    let crop = match kind {
        InputKind::Photo => Some(read_crop(dir, names.first().map_or("", String::as_str))?),
        InputKind::Video => None,
    };
    let fps = fps.unwrap_or_else(|| {
        gagavatar_track::output::read_track_json(&dir.join(gagavatar_track::output::TRACK_JSON))
            .ok()
            .and_then(|t| t.fps)
            .unwrap_or(gagavatar_data::driver::DEFAULT_FPS)
    });
    Ok(Tracked {
        dir: dir.to_owned(),
        kind,
        names,
        records: ordered,
        crop,
        fps,
        cached: true,
        seconds: 0.0,
        video: None,
    })
}

/// The stored 512 crop of frame `key` of a tracked folder.
pub fn read_crop(dir: &Path, key: &str) -> Result<RgbImage> {
    let lmdb_path = dir.join(IMAGES_DIR);
    let lmdb = gagavatar_data::LmdbReader::open(&lmdb_path)?;
    let bytes = lmdb
        .get(key.as_bytes())?
        .ok_or_else(|| input_err(lmdb_path.display().to_string(), format!("no image `{key}`")))?;
    Ok(gagavatar_data::decode_image(&bytes, &lmdb_path, key)?)
}

/// Frame `key` of a tracked folder (its only frame when `key` is `None`): the crop from
/// `img_lmdb/` and the record from `optim.pkl` (else `smoothed.pkl`), and a label for messages.
pub fn read_tracked_frame(
    dir: &Path,
    key: Option<&str>,
) -> Result<(RgbImage, TrackedFrame, String)> {
    let pkl = [OPTIM_FILE, SMOOTHED_FILE]
        .iter()
        .map(|f| dir.join(f))
        .find(|p| p.is_file())
        .ok_or_else(|| {
            input_err(
                dir.display().to_string(),
                "is not a tracked folder (no optim.pkl)",
            )
        })?;
    let mut records = gagavatar_data::read_records(&pkl)?;
    let key = match key {
        Some(k) => k.to_owned(),
        None if records.len() == 1 => records.keys().next().cloned().unwrap_or_default(),
        None => {
            return Err(input_err(
                pkl.display().to_string(),
                format!(
                    "holds {} frames: name one with --source-key (e.g. {})",
                    records.len(),
                    records.keys().next().cloned().unwrap_or_default()
                ),
            ))
        }
    };
    let record = records
        .remove(&key)
        .ok_or_else(|| input_err(pkl.display().to_string(), format!("has no frame `{key}`")))?;
    let image = read_crop(dir, &key)?;
    Ok((image, record, format!("`{key}` of {}", pkl.display())))
}
