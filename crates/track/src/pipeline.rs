//! Observations in, release records out: the stages tied together.
//!
//! Photo: landmarks -> head box -> crop window -> the 70 targets in crop pixels -> photo fit ->
//! record. Video: head boxes of all frames -> smoothed windows -> targets -> one shape on
//! keyframes, warm-started frame fits -> gaps filled -> smoothing (the default offline smoother
//! also refits each frame to its smoothed landmarks, see `consistent_states`) -> records. The
//! images themselves are cropped separately ([`crate::crop::crop_image`] with each frame's window), so
//! a caller can decode a video twice instead of holding it in memory.

use gagavatar_data::records::{EXPRESSION_COMPONENTS, SHAPE_COMPONENTS};
use gagavatar_flame::TrackedFrame;

use crate::crop::{smooth_head_boxes, CropWindow, FramingCalibration, HeadBox};
use crate::error::{input, Result, TrackError};
use rayon::prelude::*;

use crate::fit::{
    fit_frame, fit_photo, fit_sequence, reproject, FitOptions, FrameState, LandmarkTargets,
};
use crate::mapping::to_70;
use crate::observation::Observation;
use crate::rig::{LandmarkRig, N_LANDMARKS};
use crate::smooth::{interpolate_states, smooth_states, whittaker, Smoothing, MISSING_WEIGHT};

#[derive(Debug, Clone, PartialEq)]
pub struct TrackOptions {
    pub fit: FitOptions,
    pub framing: FramingCalibration,
    pub smoothing: Smoothing,
    /// Whittaker strength on a video's head boxes (centre, log side). 1e4 halves the power at a
    /// period of about 64 frames: a nearly static window that still follows a moving head.
    pub window_smoothing: f64,
}

impl Default for TrackOptions {
    fn default() -> Self {
        Self {
            fit: FitOptions::default(),
            framing: FramingCalibration::default(),
            smoothing: Smoothing::default(),
            window_smoothing: 1e4,
        }
    }
}

/// One tracked frame, with what `track.json` reports about it.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameTrack {
    /// The release record (for a video: the smoothed one, as in `smoothed.pkl`).
    pub record: TrackedFrame,
    /// Width and height of the frame.
    pub image_size: [u32; 2],
    /// The crop window in frame pixels.
    pub window: CropWindow,
    /// The head box the window was made from (frame pixels; for video the smoothed one).
    pub head_box: HeadBox,
    /// The 70 detected target points in frame pixels (`None` entries: not detected, e.g. the
    /// pupils of a 468-point mesh); `None` when no face was found in the frame.
    pub detected: Option<Vec<Option<[f64; 2]>>>,
    /// The fitted FLAME's 70 landmarks reprojected into frame pixels (`None` behind the camera).
    pub reprojected: Vec<Option<[f64; 2]>>,
    /// Whether a face was found; frames without one are filled from their neighbours.
    pub face_found: bool,
    /// RMS landmark error of the raw fit in 512-crop pixels (`None` for filled frames).
    pub fit_rms_px: Option<f64>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct TrackedPhoto {
    pub frame: FrameTrack,
    /// The fitted shape code (the rig's component count).
    pub shape: Vec<f64>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct TrackedVideo {
    /// Per frame, with smoothed records (`smoothed.pkl`).
    pub frames: Vec<FrameTrack>,
    /// Per frame, the unsmoothed records (`optim.pkl`; filled frames interpolated).
    pub raw_records: Vec<TrackedFrame>,
    pub shape: Vec<f64>,
    /// Frames the shape was solved on.
    pub keyframes: Vec<usize>,
    /// The source video's frame rate, when the caller knows it (written to `track.json`, so
    /// driving from the tracked folder keeps the video's timing).
    pub fps: Option<f64>,
}

/// The release record of a fitted state (global pose zero, jaw in `posecode[3..6]`), codes
/// zero-padded to the release's 300 / 100 components.
pub fn record_of(shape: &[f64], s: &FrameState, bbox: [f64; 4]) -> TrackedFrame {
    let pad = |v: &[f64], n: usize| {
        let mut v = v.to_vec();
        if v.len() < n {
            v.resize(n, 0.0);
        }
        v
    };
    TrackedFrame {
        shapecode: pad(shape, SHAPE_COMPONENTS),
        expcode: pad(&s.expression, EXPRESSION_COMPONENTS),
        posecode: vec![0.0, 0.0, 0.0, s.jaw[0], s.jaw[1], s.jaw[2]],
        eyecode: s.eyes.to_vec(),
        transform_matrix: Some(s.camera.matrix()),
        bbox: Some(bbox),
    }
}

/// The 70 points of a frame in frame pixels, `None` where not detected.
type Detected = Vec<Option<[f64; 2]>>;

/// The fit's targets for a frame's landmarks seen through a crop window.
fn targets_in_crop(
    obs: &Observation,
    window: &CropWindow,
    o: &FitOptions,
) -> Result<Option<(LandmarkTargets, Detected)>> {
    let Some(lm) = &obs.landmarks else {
        return Ok(None);
    };
    let (pts, present) = to_70(lm);
    let base = o.landmark_weights.per_landmark();
    let mut crop_pts = [[0.0; 2]; N_LANDMARKS];
    let mut weights = [0.0; N_LANDMARKS];
    let mut detected = Vec::with_capacity(N_LANDMARKS);
    for k in 0..N_LANDMARKS {
        if present[k] {
            crop_pts[k] = window.frame_to_crop(pts[k]);
            weights[k] = base[k];
            detected.push(Some(pts[k]));
        } else {
            detected.push(None);
        }
    }
    Ok(Some((LandmarkTargets::new(crop_pts, weights)?, detected)))
}

fn reprojected_in_frame(
    rig: &LandmarkRig,
    shape: &[f64],
    s: &FrameState,
    window: &CropWindow,
) -> Result<Vec<Option<[f64; 2]>>> {
    Ok(reproject(rig, shape, s)?
        .into_iter()
        .map(|p| p.map(|p| window.crop_to_frame(p)))
        .collect())
}

/// Tracks a photo. `label` names it in the "no face found" error.
pub fn track_photo(
    obs: &Observation,
    rig: &LandmarkRig,
    opts: &TrackOptions,
    label: &str,
) -> Result<TrackedPhoto> {
    opts.fit.validate()?;
    let Some(lm) = &obs.landmarks else {
        return Err(TrackError::NoFace {
            name: label.to_owned(),
        });
    };
    let head = opts.framing.head_box(lm)?;
    let window = CropWindow::from_head_box(&head)?;
    let (targets, detected) =
        targets_in_crop(obs, &window, &opts.fit)?.ok_or_else(|| input("photo", "no landmarks"))?;
    let fit = fit_photo(rig, &targets, &opts.fit)?;
    let bbox = window.normalized_box(&head);
    let frame = FrameTrack {
        record: record_of(&fit.shape, &fit.frame.state, bbox),
        image_size: [obs.width, obs.height],
        window,
        head_box: head,
        detected: Some(detected),
        reprojected: reprojected_in_frame(rig, &fit.shape, &fit.frame.state, &window)?,
        face_found: true,
        fit_rms_px: Some(fit.frame.rms_px),
    };
    Ok(TrackedPhoto {
        frame,
        shape: fit.shape,
    })
}

/// A video's crop windows, which depend on the landmarks only (not on the fit), so a caller
/// can crop while [`track_video`] fits.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoWindows {
    /// Per frame, the head box from its landmarks (`None`: no face).
    pub boxes: Vec<Option<HeadBox>>,
    /// The boxes smoothed over the clip (missing ones filled).
    pub smooth_boxes: Vec<HeadBox>,
    /// The crop window of each frame.
    pub windows: Vec<CropWindow>,
}

/// The crop windows [`track_video`] uses for these observations (no face in any frame: the
/// "no face found in `label`" error).
pub fn video_windows(
    obs: &[Observation],
    opts: &TrackOptions,
    label: &str,
) -> Result<VideoWindows> {
    let boxes: Vec<Option<HeadBox>> = obs
        .iter()
        .map(|o| {
            o.landmarks
                .as_ref()
                .map(|lm| opts.framing.head_box(lm))
                .transpose()
        })
        .collect::<Result<_>>()?;
    if boxes.iter().all(Option::is_none) {
        return Err(TrackError::NoFace {
            name: label.to_owned(),
        });
    }
    let smooth_boxes = smooth_head_boxes(&boxes, opts.window_smoothing)?;
    let windows: Vec<CropWindow> = smooth_boxes
        .iter()
        .map(CropWindow::from_head_box)
        .collect::<Result<_>>()?;
    Ok(VideoWindows {
        boxes,
        smooth_boxes,
        windows,
    })
}

/// Tracks a video's frames (all of them are needed before the first window is final).
/// `progress(done, total)` is called as frames are fitted. `label` names the video in the "no
/// face found" error.
pub fn track_video(
    observations: impl IntoIterator<Item = Observation>,
    rig: &LandmarkRig,
    opts: &TrackOptions,
    label: &str,
    mut progress: impl FnMut(usize, usize),
) -> Result<TrackedVideo> {
    opts.fit.validate()?;
    if !(opts.window_smoothing.is_finite() && opts.window_smoothing >= 0.0) {
        return Err(input(
            "track options",
            format!("window_smoothing = {}", opts.window_smoothing),
        ));
    }
    let obs: Vec<Observation> = observations.into_iter().collect();
    if obs.is_empty() {
        return Err(input("video", "no frames"));
    }
    let (w0, h0) = (obs[0].width, obs[0].height);
    if let Some(i) = obs.iter().position(|o| (o.width, o.height) != (w0, h0)) {
        return Err(input(
            "video",
            format!(
                "frame {i} is {}x{}, frame 0 is {w0}x{h0}",
                obs[i].width, obs[i].height
            ),
        ));
    }
    let VideoWindows {
        boxes,
        smooth_boxes,
        windows,
    } = video_windows(&obs, opts, label)?;
    let mut targets = Vec::with_capacity(obs.len());
    let mut detected = Vec::with_capacity(obs.len());
    for (o, w) in obs.iter().zip(&windows) {
        match targets_in_crop(o, w, &opts.fit)? {
            Some((t, d)) => {
                targets.push(Some(t));
                detected.push(Some(d));
            }
            None => {
                targets.push(None);
                detected.push(None);
            }
        }
    }
    let total = obs.len();
    let seq = fit_sequence(rig, &targets, &opts.fit, |i| progress(i + 1, total))?;
    let observed: Vec<bool> = seq.frames.iter().map(Option::is_some).collect();
    let raw_states: Vec<Option<FrameState>> = seq
        .frames
        .iter()
        .map(|f| f.as_ref().map(|f| f.state.clone()))
        .collect();
    let filled = interpolate_states(&raw_states)?;
    let mut smoothed = smooth_states(&filled, &observed, &opts.smoothing)?;
    if let Smoothing::Offline(s) = &opts.smoothing {
        if s.camera > 0.0 {
            smoothed = consistent_states(
                rig, &seq.shape, &filled, &smoothed, &observed, s.camera, &opts.fit,
            )?;
        }
    }
    let mut frames = Vec::with_capacity(total);
    let mut raw_records = Vec::with_capacity(total);
    for i in 0..total {
        let w = &windows[i];
        // The record's box: the frame's own head box (smoothed one for filled frames).
        let bbox = w.normalized_box(boxes[i].as_ref().unwrap_or(&smooth_boxes[i]));
        raw_records.push(record_of(&seq.shape, &filled[i], bbox));
        frames.push(FrameTrack {
            record: record_of(&seq.shape, &smoothed[i], bbox),
            image_size: [obs[i].width, obs[i].height],
            window: *w,
            head_box: smooth_boxes[i],
            detected: detected[i].clone(),
            reprojected: reprojected_in_frame(rig, &seq.shape, &smoothed[i], w)?,
            face_found: observed[i],
            fit_rms_px: seq.frames[i].as_ref().map(|f| f.rms_px),
        });
    }
    Ok(TrackedVideo {
        frames,
        raw_records,
        shape: seq.shape,
        keyframes: seq.keyframes,
        fps: None,
    })
}

/// How much worse (RMS pixels at 512) a refit from the smoothed state may fit the smoothed
/// landmarks than one from the raw state and still be kept: a fraction of a pixel is invisible,
/// a steadier camera is not.
const PREFER_SMOOTHED_PX: f64 = 0.25;

/// Makes smoothed states agree with smoothed landmarks. Smoothing each parameter on its own
/// breaks their agreement: from 70 landmarks a small turn of the camera and a change of the
/// expression codes look nearly alike, so per-frame fits trade one for the other from frame to
/// frame while their landmarks move smoothly, and averaging the two separately lands off the
/// face (measured on the release's demo video: 0.0029 median normalised landmark error raw,
/// up to 0.5 after smoothing the parameters alone). So the fitted landmarks themselves are
/// smoothed (Whittaker, strength `lambda`, frames without a face nearly free), and each frame
/// is fitted to them, warm-started from its smoothed state.
fn consistent_states(
    rig: &LandmarkRig,
    shape: &[f64],
    filled: &[FrameState],
    smoothed: &[FrameState],
    observed: &[bool],
    lambda: f64,
    o: &FitOptions,
) -> Result<Vec<FrameState>> {
    let n = filled.len();
    let pts: Vec<Vec<Option<[f64; 2]>>> = filled
        .iter()
        .map(|s| reproject(rig, shape, s))
        .collect::<Result<_>>()?;
    // A landmark behind the camera in any frame (not seen in practice): keep the parameter
    // smoothing as it is.
    if pts.iter().flatten().any(Option::is_none) {
        return Ok(smoothed.to_vec());
    }
    let w: Vec<f64> = observed
        .iter()
        .map(|&o| if o { 1.0 } else { MISSING_WEIGHT })
        .collect();
    let mut smooth_pts = vec![[[0.0; 2]; N_LANDMARKS]; n];
    for k in 0..N_LANDMARKS {
        for c in 0..2 {
            let y: Vec<f64> = pts.iter().map(|p| p[k].map_or(0.0, |q| q[c])).collect();
            for (i, v) in whittaker(&y, &w, lambda)?.into_iter().enumerate() {
                smooth_pts[i][k][c] = v;
            }
        }
    }
    // Warm starts only (a restart from the closed form can land in a distant, degenerate
    // minimum): from the smoothed state, which keeps the smoothed camera, unless the frame's
    // own raw state fits the smoothed landmarks clearly better.
    let warm = FitOptions {
        restart_rms_px: f64::MAX,
        ..o.clone()
    };
    (0..n)
        .into_par_iter()
        .map(|i| {
            let t = LandmarkTargets::with_weights(smooth_pts[i], &o.landmark_weights)?;
            let a = fit_frame(rig, shape, &t, Some(&smoothed[i]), &warm)?;
            let b = fit_frame(rig, shape, &t, Some(&filled[i]), &warm)?;
            Ok(if a.rms_px <= b.rms_px + PREFER_SMOOTHED_PX {
                a.state
            } else {
                b.state
            })
        })
        .collect()
}

/// Tracks frames one at a time as they arrive (a webcam), where a video's two-sided smoothing
/// cannot wait for the clip's end: the first frame with a face fixes the shape (a photo fit);
/// each later frame is fitted warm-started from the one before, through a crop window whose
/// head box follows an exponential moving average (so the window does not shake).
#[derive(Debug, Clone, Default)]
pub struct LiveTrack {
    shape: Option<Vec<f64>>,
    prev: Option<FrameState>,
    head: Option<HeadBox>,
}

/// How much of a new frame's head box the live window takes (the rest is the previous one):
/// about an 8-frame memory.
pub const LIVE_HEAD_SMOOTHING: f64 = 0.25;

impl LiveTrack {
    pub fn new() -> Self {
        Self::default()
    }

    /// The record of the next frame, or `None` when it has no face (the caller keeps showing
    /// the last one).
    pub fn frame(
        &mut self,
        obs: &Observation,
        rig: &LandmarkRig,
        opts: &TrackOptions,
    ) -> Result<Option<TrackedFrame>> {
        let Some(lm) = &obs.landmarks else {
            return Ok(None);
        };
        let seen = opts.framing.head_box(lm)?;
        let head = match &self.head {
            None => seen,
            Some(h) => {
                let a = LIVE_HEAD_SMOOTHING;
                let mix = |p: f64, q: f64| (1.0 - a) * p + a * q;
                HeadBox::new(
                    mix(h.x0, seen.x0),
                    mix(h.y0, seen.y0),
                    mix(h.x1, seen.x1),
                    mix(h.y1, seen.y1),
                )?
            }
        };
        let window = CropWindow::from_head_box(&head)?;
        let Some((targets, _)) = targets_in_crop(obs, &window, &opts.fit)? else {
            return Ok(None);
        };
        let (shape, state) = match &self.shape {
            None => {
                let fit = fit_photo(rig, &targets, &opts.fit)?;
                (fit.shape, fit.frame.state)
            }
            Some(shape) => {
                let fit = fit_frame(rig, shape, &targets, self.prev.as_ref(), &opts.fit)?;
                (shape.clone(), fit.state)
            }
        };
        let record = record_of(&shape, &state, window.normalized_box(&seen));
        self.shape = Some(shape);
        self.prev = Some(state);
        self.head = Some(head);
        Ok(Some(record))
    }
}
