//! Tracking as the commands use it: a photo, a video or a folder of images in, a tracked folder
//! (the release layout plus `track.json`, `gagavatar_track::output`) out, optionally a picture
//! of the fit; and the content-addressed cache that lets `reenact`, `orbit` and `export-ply`
//! take raw photos and videos.
//!
//! Per frame: MediaPipe's 478 landmarks on the original frame (video: the face tracker, which
//! carries the landmark ROI from frame to frame), the FLAME fit (`gagavatar_track`), then the
//! release's 512 crop through the frame's window, the person matte on that crop composited onto
//! black, and a JPEG in `img_lmdb/`.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use candle_core::{DType, Device};
use gagavatar_face::{FaceMesh, FaceTracker, SelfieSegmenter};
use gagavatar_flame::{FlameAsset, FlameModel, LoadOptions, TrackedFrame};
use gagavatar_formats::atomic::write_atomic;
use gagavatar_formats::image::{read_image, sniff, DecodeOptions};
use gagavatar_track::camera::CameraPose;
use gagavatar_track::crop::{apply_matte, crop_image};
use gagavatar_track::output::{
    encode_jpeg, write_photo, write_video_jpegs, IMAGES_DIR, OPTIM_FILE, SMOOTHED_FILE,
};
use gagavatar_track::overlay::{draw_fit, mesh_edges, MeshEdges, ProjectedMesh};
use gagavatar_track::pipeline::video_windows;
use gagavatar_track::{
    track_photo, track_video, CropWindow, FaceLandmarks, FrameTrack, LandmarkRig, Observation,
    TrackError, TrackOptions, TrackedPhoto, TrackedVideo,
};
use gagavatar_video::read::{ReadOptions, VideoReader};
use gagavatar_video::{VideoOptions, VideoWriter};
use image::RgbImage;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::progress::{progress, spinner};
use gagavatar_avatar::FlameSource;

/// Bump when the tracker's results change for the same input (a new fit, crop or matte, or a new
/// field in its output: 5 writes the video's frame rate into track.json), so cached tracks made by
/// older builds are not reused. The cache key also holds the crate version and the tracking options.
pub const TRACKER_REVISION: u32 = 5;
/// Photos larger than this (long side) are tracked downscaled; the networks see at most 256 px.
const WORK_SIDE: u32 = 4096;
/// Smaller images are refused: no face fits in them.
const MIN_SIDE: u32 = 16;
/// A video's decoded frames are kept for the crop pass up to this many bytes (about 1300
/// frames at 512x512); longer videos are decoded a second time instead.
const KEEP_FRAMES_BYTES: usize = 1 << 30;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum InputKind {
    Photo,
    Video,
}

/// A photo when the file's content is an image (PNG, JPEG, WebP, BMP); a folder or anything
/// else is read as a video.
pub fn input_kind(path: &Path) -> Result<InputKind> {
    if path.is_dir() {
        return Ok(InputKind::Video);
    }
    let mut head = Vec::with_capacity(64);
    std::fs::File::open(path)
        .and_then(|f| f.take(64).read_to_end(&mut head))
        .with_context(|| format!("cannot read {}", path.display()))?;
    Ok(if sniff(&head).is_some() {
        InputKind::Photo
    } else {
        InputKind::Video
    })
}

/// The FLAME asset at `path`, or the built-in synthetic one for `synthetic`.
pub fn load_flame_asset(path: &Path) -> Result<FlameAsset> {
    match FlameSource::from_arg(path) {
        FlameSource::File(p) => FlameAsset::load(&p, &LoadOptions::default())
            .with_context(|| format!("loading FLAME {}", p.display())),
        _ => Ok(gagavatar_flame::synthesize(0)),
    }
}

/// The name the tracked folder's keys use: the input's file stem.
pub fn input_name(path: &Path) -> String {
    path.file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "track".into())
}

fn landmarks_of(face: &gagavatar_face::Face, w: u32, h: u32) -> Result<FaceLandmarks> {
    let pts: Vec<[f64; 2]> = face
        .landmarks
        .iter()
        .map(|p| [p[0] as f64, p[1] as f64])
        .collect();
    Ok(FaceLandmarks::from_normalized(&pts, w, h)?)
}

/// What a video run did.
pub struct VideoSummary {
    pub frames: usize,
    pub fps: f64,
    /// Frames without a face (filled from their neighbours).
    pub no_face: usize,
    pub video: TrackedVideo,
    /// Wall seconds of the three passes: decode + landmarks, fit, crop + matte + JPEG + write.
    pub seconds: [f64; 3],
    /// CPU seconds of the thread that ran the fit (the fit is sequential over frames).
    pub fit_cpu_seconds: f64,
}

/// CPU seconds (user + system) of the calling thread; 0 where unavailable.
pub fn thread_cpu_seconds() -> f64 {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: getrusage only writes the struct it is given.
        let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
        if unsafe { libc::getrusage(libc::RUSAGE_THREAD, &mut ru) } == 0 {
            let t = |tv: libc::timeval| tv.tv_sec as f64 + tv.tv_usec as f64 * 1e-6;
            return t(ru.ru_utime) + t(ru.ru_stime);
        }
    }
    0.0
}

/// The models a tracking run needs, loaded once.
pub struct Tracker {
    mesh: FaceMesh,
    segmenter: SelfieSegmenter,
    rig: LandmarkRig,
    flame: FlameModel,
    faces: Vec<[u32; 3]>,
    edges: MeshEdges,
    pub opts: TrackOptions,
}

impl Tracker {
    pub fn new(flame: &Path) -> Result<Self> {
        let asset = load_flame_asset(flame)?;
        let rig = LandmarkRig::for_tracking(&asset)
            .with_context(|| format!("FLAME {} cannot be tracked with", flame.display()))?;
        let model = FlameModel::from_asset(&asset, &Device::Cpu, DType::F32)?;
        Ok(Self {
            mesh: FaceMesh::new().context("loading the face models")?,
            segmenter: SelfieSegmenter::new().context("loading the matting model")?,
            rig,
            edges: mesh_edges(&asset.faces),
            faces: asset.faces.clone(),
            flame: model,
            opts: TrackOptions::default(),
        })
    }

    /// The release's crop through `window`, matted onto black.
    pub fn matted_crop(&self, img: &RgbImage, window: &CropWindow) -> Result<RgbImage> {
        let crop = crop_image(img, window)?;
        let matte = self.segmenter.matte(&crop)?;
        Ok(apply_matte(&crop, &matte.data)?)
    }

    /// The fitted FLAME's vertices in frame pixels (`None` behind the camera).
    fn projected_vertices(
        &self,
        record: &TrackedFrame,
        window: &CropWindow,
    ) -> Result<Vec<Option<[f64; 2]>>> {
        let tm = record
            .transform_matrix
            .context("a tracked record has no camera")?;
        let out = self.flame.forward(&record.params(&self.flame)?)?;
        let v: Vec<f32> = out.vertices.flatten_all()?.to_vec1()?;
        let cam = CameraPose::from_matrix(&tm);
        Ok(v.chunks_exact(3)
            .map(|p| {
                cam.project(&[p[0] as f64, p[1] as f64, p[2] as f64])
                    .map(|q| window.crop_to_frame(q))
            })
            .collect())
    }

    /// `frame` with the fit drawn over it: mesh, detected and fitted landmarks, crop window.
    pub fn draw(&self, frame: &RgbImage, track: &FrameTrack) -> Result<RgbImage> {
        let points = self.projected_vertices(&track.record, &track.window)?;
        let mesh = ProjectedMesh {
            points: &points,
            faces: &self.faces,
        };
        Ok(draw_fit(frame, track, Some((&mesh, &self.edges))))
    }

    /// The landmarks of a photo (best face), as the tracker's observation.
    pub fn observe_photo(&self, img: &RgbImage) -> Result<Observation> {
        let (w, h) = img.dimensions();
        let faces = self.mesh.process(img, 1)?;
        let lm = faces.first().map(|f| landmarks_of(f, w, h)).transpose()?;
        Ok(Observation::new(w, h, lm)?)
    }

    /// Tracks a photo into `dir`; with `overlay`, also writes the fit drawn over the photo
    /// (PNG). No face: the error "no face found in PATH" and nothing written.
    pub fn track_photo_file(
        &self,
        path: &Path,
        dir: &Path,
        overlay: Option<&Path>,
    ) -> Result<TrackedPhoto> {
        let label = path.display().to_string();
        let opts = DecodeOptions {
            min_side: MIN_SIDE,
            fit_within: Some(WORK_SIDE),
        };
        let img = read_image(path, &opts)?.rgb;
        let obs = self.observe_photo(&img)?;
        let photo = track_photo(&obs, &self.rig, &self.opts, &label)?;
        let crop = self.matted_crop(&img, &photo.frame.window)?;
        let picture = overlay.map(|_| self.draw(&img, &photo.frame)).transpose()?;
        write_photo(dir, &input_name(path), &photo, &crop)?;
        if let (Some(p), Some(pic)) = (overlay, picture) {
            write_png(p, &pic)?;
        }
        Ok(photo)
    }

    /// The JPEG of a frame's matted crop, as `img_lmdb/` stores it.
    fn crop_jpeg(&self, frame: &RgbImage, window: &CropWindow) -> Result<Vec<u8>> {
        Ok(encode_jpeg(&self.matted_crop(frame, window)?)?)
    }

    /// Tracks a video (any video file, or a folder of images) into `dir`: landmarks frame by
    /// frame, then the fit over the whole clip while the crops are made on another thread (the
    /// crop windows depend on the landmarks only); with `overlay`, a video of the fit drawn over
    /// the original frames. Progress bars on stderr.
    pub fn track_video_file(
        &self,
        path: &Path,
        dir: &Path,
        overlay: Option<&Path>,
    ) -> Result<VideoSummary> {
        let label = path.display().to_string();
        let t0 = Instant::now();
        let reader = VideoReader::open(path, &ReadOptions::default())?;
        let fps = reader.output_fps();
        let bar = match reader.expected_frames() {
            Some(n) => progress(n as usize, "1/2 landmarks"),
            None => spinner("1/2 landmarks"),
        };
        let mut tracker = FaceTracker::with_models(self.mesh.clone());
        let mut obs = Vec::new();
        let mut kept: Option<Vec<RgbImage>> = Some(Vec::new());
        let mut kept_bytes = 0usize;
        for frame in reader {
            crate::check_interrupt()?;
            let img = frame?.rgb;
            let (w, h) = img.dimensions();
            let lm = tracker
                .process(&img)?
                .map(|f| landmarks_of(&f, w, h))
                .transpose()?;
            obs.push(Observation::new(w, h, lm)?);
            kept_bytes += img.as_raw().len();
            if kept_bytes > KEEP_FRAMES_BYTES {
                kept = None;
            } else if let Some(k) = &mut kept {
                k.push(img);
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        let n = obs.len();
        if n == 0 {
            bail!("{label} has no frames");
        }
        let no_face = obs.iter().filter(|o| o.landmarks.is_none()).count();
        let (w, h) = (obs[0].width, obs[0].height);
        let windows = video_windows(&obs, &self.opts, &label)?.windows;
        let t1 = Instant::now();

        let bar = progress(2 * n, "2/2 fit | crop, matte, JPEG");
        let (video, jpegs, fit_cpu) = match &kept {
            // The fit on a second thread, the crops here; both pass over every frame once.
            Some(frames) => std::thread::scope(|s| {
                let fit = s.spawn(|| {
                    let c0 = thread_cpu_seconds();
                    let v = track_video(obs, &self.rig, &self.opts, &label, |_, _| bar.inc(1));
                    (v, thread_cpu_seconds() - c0)
                });
                let jpegs: Result<Vec<Vec<u8>>> = frames
                    .iter()
                    .zip(&windows)
                    .map(|(f, win)| {
                        crate::check_interrupt()?;
                        let j = self.crop_jpeg(f, win);
                        bar.inc(1);
                        j
                    })
                    .collect();
                let (video, cpu) = fit
                    .join()
                    .map_err(|_| anyhow::anyhow!("the fit thread panicked"))?;
                anyhow::Ok((video?, Some(jpegs?), cpu))
            })?,
            None => {
                let c0 = thread_cpu_seconds();
                let v = track_video(obs, &self.rig, &self.opts, &label, |_, _| bar.inc(1))?;
                (v, None, thread_cpu_seconds() - c0)
            }
        };
        // The video's exact rate goes into track.json, so driving from the folder keeps it.
        let mut video = video;
        video.fps = Some(fps);
        if let Some(i) = (0..n).find(|&i| video.frames[i].window != windows[i]) {
            bail!("internal: frame {i}'s crop window differs between the crop and the fit");
        }
        let t2 = Instant::now();
        let name = input_name(path);
        match jpegs {
            Some(j) => write_video_jpegs(dir, &name, &video, j.into_iter().map(Ok))?,
            None => {
                // A long video: decoded again, cropped while written.
                let mut failure: Option<anyhow::Error> = None;
                let frames = VideoReader::open(path, &ReadOptions::default())?;
                let jpegs = frames.zip(&windows).map(|(f, win)| {
                    let j = crate::check_interrupt()
                        .and_then(|()| Ok(f?.rgb))
                        .and_then(|f| self.crop_jpeg(&f, win));
                    bar.inc(1);
                    j.map_err(|e| {
                        failure = Some(e);
                        // Stops the writer; the real error is `failure`.
                        TrackError::Output {
                            path: dir.to_owned(),
                            reason: "stopped".into(),
                        }
                    })
                });
                let written = write_video_jpegs(dir, &name, &video, jpegs);
                if let Some(e) = failure {
                    return Err(e);
                }
                written?;
            }
        }
        bar.finish_and_clear();
        let t3 = Instant::now();
        if let Some(p) = overlay {
            self.write_video_overlay(path, p, kept.as_deref(), &video, w, h, fps)?;
        }
        Ok(VideoSummary {
            frames: n,
            fps,
            no_face,
            video,
            seconds: [
                (t1 - t0).as_secs_f64(),
                (t2 - t1).as_secs_f64(),
                (t3 - t2).as_secs_f64(),
            ],
            fit_cpu_seconds: fit_cpu,
        })
    }

    /// The fit drawn over every frame, as a video at `out` (format by extension).
    #[allow(clippy::too_many_arguments)]
    fn write_video_overlay(
        &self,
        input: &Path,
        out: &Path,
        kept: Option<&[RgbImage]>,
        video: &TrackedVideo,
        w: u32,
        h: u32,
        fps: f64,
    ) -> Result<()> {
        let opts = VideoOptions {
            fps,
            watermark: false,
        };
        let mut writer = VideoWriter::create(out, w as usize, h as usize, opts)
            .with_context(|| format!("creating {}", out.display()))?;
        let frames: Box<dyn Iterator<Item = Result<std::borrow::Cow<RgbImage>>>> = match kept {
            Some(k) => Box::new(k.iter().map(|f| Ok(std::borrow::Cow::Borrowed(f)))),
            None => Box::new(
                VideoReader::open(input, &ReadOptions::default())?
                    .map(|f| Ok(std::borrow::Cow::Owned(f?.rgb))),
            ),
        };
        let bar = progress(video.frames.len(), "overlay");
        for (frame, track) in frames.zip(&video.frames) {
            crate::check_interrupt()?;
            let frame = frame?;
            if frame.dimensions() != (w, h) {
                bail!(
                    "{}: a frame is {}x{}, the first was {w}x{h}",
                    input.display(),
                    frame.width(),
                    frame.height()
                );
            }
            writer.push_rgb(self.draw(&frame, track)?.as_raw())?;
            bar.inc(1);
        }
        bar.finish_and_clear();
        writer.finish()?;
        Ok(())
    }
}

pub fn write_png(path: &Path, img: &RgbImage) -> Result<()> {
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )
    .with_context(|| format!("encoding {}", path.display()))?;
    write_atomic(path, &bytes)?;
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// The cache.

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
    bail!("no cache folder: set GAGAVATAR_CACHE (or XDG_CACHE_HOME or HOME)")
}

fn hash_file(h: &mut Sha256, path: &Path) -> Result<()> {
    let mut f =
        std::fs::File::open(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut buf = vec![0u8; 1 << 20];
    let mut total = 0u64;
    loop {
        let k = f
            .read(&mut buf)
            .with_context(|| format!("cannot read {}", path.display()))?;
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
        .with_context(|| format!("cannot list {}", path.display()))?
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

/// The cache key of tracking `input` with the FLAME at `flame`: SHA-256 of the tracker's
/// identity (revision, crate version, options), the FLAME asset's bytes (or `synthetic`), and
/// the input's bytes.
pub fn cache_key(input: &Path, flame: &Path, opts: &TrackOptions) -> Result<String> {
    let mut h = Sha256::new();
    h.update(
        format!(
            "gagavatar-track-cache r{TRACKER_REVISION} v{} {opts:?}\0",
            env!("CARGO_PKG_VERSION")
        )
        .as_bytes(),
    );
    match FlameSource::from_arg(flame) {
        FlameSource::File(p) => {
            h.update(b"flame:file\0");
            hash_file(&mut h, &p)?;
        }
        _ => h.update(b"flame:synthetic(0)\0"),
    }
    h.update(b"input\0");
    hash_input(&mut h, input)?;
    Ok(h.finalize().iter().map(|b| format!("{b:02x}")).collect())
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

const CACHE_FORMAT: &str = "gagavatar-track-cache 1";

/// A tracked folder for a raw input, from the cache or made now.
pub struct Tracked {
    pub dir: PathBuf,
    pub meta: CacheMeta,
}

/// Tracks `input` (a photo, a video or a folder of images) with the FLAME at `flame`, or finds
/// the folder a previous run made for the same bytes. `what` names the input in messages
/// (`source`, `driver`). With `photo_only`, anything but a photo is refused.
pub fn tracked_inline(input: &Path, flame: &Path, what: &str, photo_only: bool) -> Result<Tracked> {
    if !input.exists() {
        bail!("{what} {} does not exist", input.display());
    }
    let kind = input_kind(input)?;
    if photo_only && kind != InputKind::Photo {
        bail!(
            "{what} {} is not a photo (PNG, JPEG, WebP or BMP), a tracked folder or a record",
            input.display()
        );
    }
    let t0 = Instant::now();
    let key = cache_key(input, flame, &TrackOptions::default())?;
    let root = cache_root()?.join("track");
    let dir = root.join(&key);
    let meta_path = root.join(format!("{key}.json"));
    if let Some(meta) = read_meta(&meta_path).filter(|_| cached_folder_complete(&dir)) {
        eprintln!(
            "{what}: using the cached tracking of {} ({}, {} frame{})",
            input.display(),
            dir.display(),
            meta.frames,
            if meta.frames == 1 { "" } else { "s" }
        );
        return Ok(Tracked { dir, meta });
    }
    let tracker = Tracker::new(flame)?;
    let meta = match kind {
        InputKind::Photo => {
            tracker.track_photo_file(input, &dir, None)?;
            CacheMeta {
                format: CACHE_FORMAT.into(),
                kind,
                input: input.display().to_string(),
                frames: 1,
                fps: 25.0,
            }
        }
        InputKind::Video => {
            let s = tracker.track_video_file(input, &dir, None)?;
            report_video(input, &s);
            CacheMeta {
                format: CACHE_FORMAT.into(),
                kind,
                input: input.display().to_string(),
                frames: s.frames,
                fps: s.fps,
            }
        }
    };
    let text = serde_json::to_string_pretty(&meta)?;
    write_atomic(&meta_path, text.as_bytes())?;
    eprintln!(
        "{what}: tracked {} in {:.1} s (cached in {})",
        input.display(),
        t0.elapsed().as_secs_f64(),
        dir.display()
    );
    Ok(Tracked { dir, meta })
}

fn read_meta(path: &Path) -> Option<CacheMeta> {
    let text = std::fs::read_to_string(path).ok()?;
    let meta: CacheMeta = serde_json::from_str(&text).ok()?;
    (meta.format == CACHE_FORMAT).then_some(meta)
}

fn cached_folder_complete(dir: &Path) -> bool {
    dir.join(IMAGES_DIR).exists()
        && (dir.join(OPTIM_FILE).is_file() || dir.join(SMOOTHED_FILE).is_file())
}

/// A tracked folder: `optim.pkl` or `smoothed.pkl` inside.
pub fn is_tracked_folder(path: &Path) -> bool {
    path.is_dir() && (path.join(OPTIM_FILE).is_file() || path.join(SMOOTHED_FILE).is_file())
}

pub fn report_video(input: &Path, s: &VideoSummary) {
    let rms: Vec<f64> = s.video.frames.iter().filter_map(|f| f.fit_rms_px).collect();
    let median = median(&rms);
    eprintln!(
        "{}: {} frames at {} fps, {} without a face (filled from their neighbours), shape from \
         keyframes {:?}, median landmark RMS {:.2} px at 512",
        input.display(),
        s.frames,
        s.fps,
        s.no_face,
        s.video.keyframes,
        median
    );
}

pub fn median(v: &[f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}
