//! Tracking as the pipeline uses it: a photo, a video or a folder of images in, the release's
//! records and 512 crops out, written as a tracked folder (the release layout plus `track.json`,
//! `gagavatar_track::output`) and returned, so nothing the tracker just made is read back.
//!
//! Per frame: MediaPipe's 478 landmarks on the original frame (video: the face tracker, which
//! carries the landmark ROI from frame to frame), the FLAME fit (`gagavatar_track`), then the
//! release's 512 crop through the frame's window, the person matte on that crop composited onto
//! black, and a JPEG in `img_lmdb/`.
//!
//! A video streams: the first pass keeps only each frame's landmarks; the crop windows need the
//! whole clip's landmarks (they are smoothed over it), so the second pass decodes the video
//! again and crops, mattes and writes each frame while the fit runs on another thread. Memory
//! therefore holds a frame or two and the small per-frame records, whatever the clip's length.

use std::io::Read;
use std::path::Path;
use std::time::Instant;

use candle_core::{DType, Device};
use gagavatar_face::{FaceMesh, FaceTracker, SelfieSegmenter};
use gagavatar_flame::{FlameAsset, FlameModel, LoadOptions, TrackedFrame};
use gagavatar_formats::atomic::write_atomic;
use gagavatar_formats::image::{read_image, sniff, DecodeOptions};
use gagavatar_track::camera::CameraPose;
use gagavatar_track::crop::{apply_matte, crop_image};
use gagavatar_track::output::{encode_jpeg, write_photo_jpeg, write_video_streaming};
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

use crate::error::{input_err, io_err, AvatarError, Result};
use crate::flame_source::FlameSource;
use crate::monitor::{check, Finish, Monitor};

/// Photos larger than this (long side) are tracked downscaled; the networks see at most 256 px.
pub const WORK_SIDE: u32 = 4096;
/// Smaller images are refused: no face fits in them.
pub const MIN_SIDE: u32 = 16;

/// What an input file holds.
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
        .map_err(io_err("cannot read", path))?;
    Ok(if sniff(&head).is_some() {
        InputKind::Photo
    } else {
        InputKind::Video
    })
}

/// The name the tracked folder's keys use: the input's file stem.
pub fn input_name(path: &Path) -> String {
    path.file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "track".into())
}

/// The FLAME asset of `source` (the built-in synthetic one for anything but a file).
pub fn load_flame_asset(source: &FlameSource) -> Result<FlameAsset> {
    match source {
        FlameSource::File(p) => {
            FlameAsset::load(p, &LoadOptions::default()).map_err(|source| AvatarError::FlameFile {
                path: p.clone(),
                source: Box::new(source),
            })
        }
        _ => Ok(gagavatar_flame::synthesize(0)),
    }
}

fn landmarks_of(face: &gagavatar_face::Face, w: u32, h: u32) -> Result<FaceLandmarks> {
    let pts: Vec<[f64; 2]> = face
        .landmarks
        .iter()
        .map(|p| [p[0] as f64, p[1] as f64])
        .collect();
    Ok(FaceLandmarks::from_normalized(&pts, w, h)?)
}

/// A tracked photo, as written: the fit, its record, and the 512 crop as the folder stores it
/// (matted, and through the JPEG the folder holds, so a run that finds the folder in the cache
/// reconstructs from the same pixels).
#[derive(Debug, Clone)]
pub struct PhotoTrack {
    pub photo: TrackedPhoto,
    pub crop: RgbImage,
    /// The crop's JPEG, as `img_lmdb/` stores it.
    pub jpeg: Vec<u8>,
}

impl PhotoTrack {
    /// The release record (shape, expression, jaw, eyes, camera, box).
    pub fn record(&self) -> &TrackedFrame {
        &self.photo.frame.record
    }
}

/// What a video run did.
#[derive(Debug, Clone)]
pub struct VideoSummary {
    pub frames: usize,
    /// The video's exact frame rate (also in `track.json`).
    pub fps: f64,
    /// Frames without a face (filled from their neighbours).
    pub no_face: usize,
    pub video: TrackedVideo,
    /// Wall seconds of the two passes: decode + landmarks; fit beside decode + crop + matte +
    /// JPEG + write.
    pub seconds: [f64; 2],
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

/// The models a tracking run needs, loaded once: the face mesh and its tracker, the person
/// matte, and the FLAME landmark rig the fit solves with.
pub struct Tracker {
    mesh: FaceMesh,
    segmenter: SelfieSegmenter,
    rig: LandmarkRig,
    flame: FlameModel,
    faces: Vec<[u32; 3]>,
    edges: MeshEdges,
    source: FlameSource,
    pub opts: TrackOptions,
}

impl Tracker {
    /// Loads the face models and the FLAME asset (a file, or the synthetic one; an engine
    /// resolves [`FlameSource::FromWeights`] before it asks for a tracker).
    pub fn new(flame: &FlameSource) -> Result<Self> {
        if *flame == FlameSource::FromWeights {
            return Err(AvatarError::FlameNeeded(
                "tracking needs a FLAME asset: a file, or the synthetic one".into(),
            ));
        }
        let asset = load_flame_asset(flame)?;
        let rig = LandmarkRig::for_tracking(&asset)?;
        let model = FlameModel::from_asset(&asset, &Device::Cpu, DType::F32)?;
        let source = match flame {
            FlameSource::File(p) => FlameSource::File(p.clone()),
            _ => FlameSource::Synthetic,
        };
        Ok(Self {
            mesh: FaceMesh::new()?,
            segmenter: SelfieSegmenter::new()?,
            rig,
            edges: mesh_edges(&asset.faces),
            faces: asset.faces.clone(),
            flame: model,
            source,
            opts: TrackOptions::default(),
        })
    }

    /// The FLAME asset the records are fitted with.
    pub fn flame_source(&self) -> &FlameSource {
        &self.source
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
            .ok_or_else(|| input_err("a tracked record", "it has no camera"))?;
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

    /// Tracks a photo in memory. `label` names it in the "no face found in LABEL" error.
    pub fn track_photo(&self, img: &RgbImage, label: &str) -> Result<PhotoTrack> {
        let (w, h) = img.dimensions();
        if w.min(h) < MIN_SIDE {
            return Err(input_err(
                label,
                format!("the image is {w}x{h}; a face needs at least {MIN_SIDE} pixels a side"),
            ));
        }
        let obs = self.observe_photo(img)?;
        let photo = track_photo(&obs, &self.rig, &self.opts, label)?;
        let matted = self.matted_crop(img, &photo.frame.window)?;
        let jpeg = encode_jpeg(&matted)?;
        let crop = image::load_from_memory_with_format(&jpeg, image::ImageFormat::Jpeg)
            .map_err(|e| input_err("the crop's JPEG", e.to_string()))?
            .to_rgb8();
        Ok(PhotoTrack { photo, crop, jpeg })
    }

    /// Tracks the photo at `path` into the folder `dir`; with `overlay`, also writes the fit
    /// drawn over the photo (PNG). No face: the error "no face found in PATH" and nothing
    /// written.
    pub fn track_photo_file(
        &self,
        path: &Path,
        dir: &Path,
        overlay: Option<&Path>,
    ) -> Result<PhotoTrack> {
        let opts = DecodeOptions {
            min_side: MIN_SIDE,
            fit_within: Some(WORK_SIDE),
        };
        let img = read_image(path, &opts)?.rgb;
        let track = self.track_photo(&img, &path.display().to_string())?;
        let picture = overlay
            .map(|_| self.draw(&img, &track.photo.frame))
            .transpose()?;
        write_photo_jpeg(dir, &input_name(path), &track.photo, track.jpeg.clone())?;
        if let (Some(p), Some(pic)) = (overlay, picture) {
            write_png(p, &pic)?;
        }
        Ok(track)
    }

    /// The JPEG of a frame's matted crop, as `img_lmdb/` stores it.
    fn crop_jpeg(&self, frame: &RgbImage, window: &CropWindow) -> Result<Vec<u8>> {
        Ok(encode_jpeg(&self.matted_crop(frame, window)?)?)
    }

    /// Tracks a video (any video file, or a folder of images) into `dir`, streaming (see the
    /// module's notes); with `overlay`, a video of the fit drawn over the original frames.
    /// Stages: `landmarks` (one step a frame), `fit | crop, matte, JPEG` (two steps a frame),
    /// and `overlay`.
    pub fn track_video_file(
        &self,
        path: &Path,
        dir: &Path,
        overlay: Option<&Path>,
        monitor: &dyn Monitor,
    ) -> Result<VideoSummary> {
        let _finish = Finish(monitor);
        self.track_video_unfinished(path, dir, overlay, monitor)
    }

    /// [`Tracker::track_video_file`] without [`Monitor::finish`], for callers that go on.
    pub(crate) fn track_video_unfinished(
        &self,
        path: &Path,
        dir: &Path,
        overlay: Option<&Path>,
        monitor: &dyn Monitor,
    ) -> Result<VideoSummary> {
        let label = path.display().to_string();
        let t0 = Instant::now();
        let reader = VideoReader::open(path, &ReadOptions::default())?;
        let fps = reader.output_fps();
        monitor.stage("landmarks", reader.expected_frames());
        let mut tracker = FaceTracker::with_models(self.mesh.clone());
        let mut obs = Vec::new();
        for frame in reader {
            check(monitor)?;
            let img = frame?.rgb;
            let (w, h) = img.dimensions();
            let lm = tracker
                .process(&img)?
                .map(|f| landmarks_of(&f, w, h))
                .transpose()?;
            obs.push(Observation::new(w, h, lm)?);
            monitor.advance(1);
        }
        let n = obs.len();
        if n == 0 {
            return Err(input_err(label, "the video has no frames"));
        }
        let no_face = obs.iter().filter(|o| o.landmarks.is_none()).count();
        let (w, h) = (obs[0].width, obs[0].height);
        let windows = video_windows(&obs, &self.opts, &label)?.windows;
        let t1 = Instant::now();

        monitor.stage("fit | crop, matte, JPEG", Some(2 * n as u64));
        let name = input_name(path);
        // The fit on a second thread, the crops of a second decoding here.
        let (video, fit_cpu) = std::thread::scope(|s| -> Result<(TrackedVideo, f64)> {
            let fit = s.spawn(|| {
                let c0 = thread_cpu_seconds();
                let v = track_video(obs, &self.rig, &self.opts, &label, |_, _| {
                    monitor.advance(1)
                });
                (v, thread_cpu_seconds() - c0)
            });
            let mut fit = Some(fit);
            // Stops the writer; the real error is kept beside it and returned instead.
            let stopped = || TrackError::Output {
                path: dir.to_owned(),
                reason: "stopped".into(),
            };
            let mut fit_cpu = 0.0;
            let mut failure: Option<AvatarError> = None;
            let frames = VideoReader::open(path, &ReadOptions::default())?;
            let jpegs = frames.zip(&windows).map(|(frame, win)| {
                let jpeg = check(monitor).and_then(|()| Ok(frame?.rgb)).and_then(|f| {
                    if f.dimensions() != (w, h) {
                        return Err(input_err(
                            &label,
                            format!(
                                "a frame is {}x{} on the second reading, {w}x{h} on the first",
                                f.width(),
                                f.height()
                            ),
                        ));
                    }
                    self.crop_jpeg(&f, win)
                });
                monitor.advance(1);
                jpeg.map_err(|e| {
                    failure = Some(e);
                    stopped()
                })
            });
            let mut fit_failure: Option<AvatarError> = None;
            let written = write_video_streaming(dir, &name, n, jpegs, || {
                let (v, cpu) = fit
                    .take()
                    .ok_or_else(|| TrackError::Output {
                        path: dir.to_owned(),
                        reason: "internal: the fit was joined twice".into(),
                    })?
                    .join()
                    .map_err(|_| TrackError::Output {
                        path: dir.to_owned(),
                        reason: "internal: the fit thread panicked".into(),
                    })?;
                fit_cpu = cpu;
                let mut v = v?;
                // The video's exact rate goes into track.json, so driving from the folder
                // keeps it.
                v.fps = Some(fps);
                if let Some(i) = (0..n).find(|&i| v.frames[i].window != windows[i]) {
                    fit_failure = Some(input_err(
                        "internal",
                        format!("frame {i}'s crop window differs between the crop and the fit"),
                    ));
                    return Err(stopped());
                }
                Ok(v)
            });
            if let Some(e) = failure.or(fit_failure) {
                return Err(e);
            }
            // The scope joins a fit thread the writer did not (it stopped before the records).
            Ok((written?, fit_cpu))
        })?;
        let t2 = Instant::now();
        if let Some(p) = overlay {
            self.write_video_overlay(path, p, &video, w, h, fps, monitor)?;
        }
        Ok(VideoSummary {
            frames: n,
            fps,
            no_face,
            video,
            seconds: [(t1 - t0).as_secs_f64(), (t2 - t1).as_secs_f64()],
            fit_cpu_seconds: fit_cpu,
        })
    }

    /// The fit drawn over every frame, as a video at `out` (format by extension).
    #[allow(clippy::too_many_arguments)]
    fn write_video_overlay(
        &self,
        input: &Path,
        out: &Path,
        video: &TrackedVideo,
        w: u32,
        h: u32,
        fps: f64,
        monitor: &dyn Monitor,
    ) -> Result<()> {
        let opts = VideoOptions {
            fps,
            watermark: false,
        };
        let mut writer = VideoWriter::create(out, w as usize, h as usize, opts)?;
        monitor.stage("overlay", Some(video.frames.len() as u64));
        let frames = VideoReader::open(input, &ReadOptions::default())?;
        for (frame, track) in frames.zip(&video.frames) {
            check(monitor)?;
            let frame = frame?.rgb;
            if frame.dimensions() != (w, h) {
                return Err(input_err(
                    input.display().to_string(),
                    format!(
                        "a frame is {}x{}, the first was {w}x{h}",
                        frame.width(),
                        frame.height()
                    ),
                ));
            }
            writer.push_rgb(self.draw(&frame, track)?.as_raw())?;
            monitor.advance(1);
        }
        writer.finish()?;
        Ok(())
    }
}

/// Tracks a live stream (a webcam) frame by frame: MediaPipe's face tracker carries its region
/// of interest from frame to frame, and the fit keeps the first frame's shape
/// ([`gagavatar_track::LiveTrack`]).
pub struct LiveTracker {
    tracker: std::sync::Arc<Tracker>,
    face: FaceTracker,
    live: gagavatar_track::LiveTrack,
}

impl LiveTracker {
    pub fn new(tracker: std::sync::Arc<Tracker>) -> Self {
        LiveTracker {
            face: FaceTracker::with_models(tracker.mesh.clone()),
            tracker,
            live: gagavatar_track::LiveTrack::new(),
        }
    }

    /// The record of the next frame; `None` when it shows no face.
    pub fn frame(&mut self, img: &RgbImage) -> Result<Option<TrackedFrame>> {
        let (w, h) = img.dimensions();
        if w.min(h) < MIN_SIDE {
            return Err(input_err(
                "a live frame",
                format!("it is {w}x{h}; a face needs at least {MIN_SIDE} pixels a side"),
            ));
        }
        let lm = self
            .face
            .process(img)?
            .map(|f| landmarks_of(&f, w, h))
            .transpose()?;
        let obs = Observation::new(w, h, lm)?;
        Ok(self
            .live
            .frame(&obs, &self.tracker.rig, &self.tracker.opts)?)
    }
}

/// Writes `img` as a PNG at `path`, atomically.
pub fn write_png(path: &Path, img: &RgbImage) -> Result<()> {
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )
    .map_err(|e| input_err(path.display().to_string(), format!("cannot encode: {e}")))?;
    write_atomic(path, &bytes)?;
    Ok(())
}

/// The median of `v` (NaN when empty).
pub fn median(v: &[f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}
