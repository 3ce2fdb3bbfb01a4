//! Random identities and frames: shape codes, expressions, jaw and eye poses, and release-style
//! cameras, each drawn from its own seeded stream so any frame can be produced alone, in any
//! order and on any thread, with the same result.
//!
//! Every value is rounded to float32 when drawn: the records store float32 arrays, so the
//! images are rendered from exactly the numbers a reader gets back.
//!
//! Cameras: PyTorch3D's frontal look-at camera (`look_at_view_transform(d, 0, 0)`: camera on
//! the +Z axis, `R = diag(-1, 1, -1)`, `T = (0, 0, d)`; the release's multi-view helper uses
//! the same), which looks at the FLAME face (the face looks along +z). In
//! `Camera::look_at_origin_matrix` terms that is a yaw of pi: its yaw 0 puts the camera on -Z,
//! behind the head. The head rotation lives in the camera (`posecode[0:3] = 0`), as in tracked
//! data.

use gagavatar_splat::Camera;

use crate::error::{config_err, Result};

pub use gagavatar_splat::rng::Rng;

/// Stream tags, so identity, appearance and frame streams never overlap.
pub(crate) const TAG_SHAPE: u64 = 1;
pub(crate) const TAG_APPEARANCE: u64 = 2;
pub(crate) const TAG_FRAME: u64 = 3;

/// The distributions the generator draws from. The defaults suit the synthetic asset, whose
/// blendshapes are smooth random fields rather than PCA modes: larger codes melt the face (for
/// the licensed FLAME, codes of about N(0, 1) are typical of tracked data).
#[derive(Debug, Clone, PartialEq)]
pub struct SampleConfig {
    /// Shape components drawn (the rest are 0).
    pub shape_components: usize,
    pub shape_sigma: f64,
    /// Expression components drawn (the rest are 0).
    pub exp_components: usize,
    pub exp_sigma: f64,
    /// Jaw opening `posecode[3]` is drawn in `[0, jaw_max]` radians (skewed toward closed).
    pub jaw_max: f64,
    /// Gaze: standard deviation of the eye yaw and pitch (radians), shared by both eyes.
    pub eye_sigma: f64,
    /// Camera yaw is uniform in `±yaw_max_deg` and pitch in `±pitch_max_deg` about the front.
    pub yaw_max_deg: f64,
    pub pitch_max_deg: f64,
    /// Camera distance is uniform in this range.
    pub distance: (f64, f64),
    /// Standard deviation of the camera-space x/y offset of the head (framing jitter).
    pub shift_sigma: f64,
    /// Frame 0 of each identity (the source frame of val/test pairs) uses this fraction of the
    /// pose and expression ranges, like a near-frontal reference photo.
    pub first_frame_scale: f64,
}

impl Default for SampleConfig {
    fn default() -> Self {
        Self {
            shape_components: 50,
            shape_sigma: 0.5,
            exp_components: 50,
            exp_sigma: 0.4,
            jaw_max: 0.3,
            eye_sigma: 0.12,
            yaw_max_deg: 35.0,
            pitch_max_deg: 20.0,
            distance: (8.6, 9.6),
            shift_sigma: 0.03,
            first_frame_scale: 0.4,
        }
    }
}

impl SampleConfig {
    /// Checks ranges against a FLAME with `n_shape` / `n_exp` components.
    pub fn validate(&self, n_shape: usize, n_exp: usize) -> Result<()> {
        if self.shape_components > n_shape {
            return Err(config_err(
                "shape_components",
                format!("{} > the model's {n_shape}", self.shape_components),
            ));
        }
        if self.exp_components > n_exp {
            return Err(config_err(
                "exp_components",
                format!("{} > the model's {n_exp}", self.exp_components),
            ));
        }
        let checks: [(&'static str, f64, f64, f64); 9] = [
            ("shape_sigma", self.shape_sigma, 0.0, 10.0),
            ("exp_sigma", self.exp_sigma, 0.0, 10.0),
            ("jaw_max", self.jaw_max, 0.0, 1.0),
            ("eye_sigma", self.eye_sigma, 0.0, 1.0),
            ("yaw_max_deg", self.yaw_max_deg, 0.0, 90.0),
            ("pitch_max_deg", self.pitch_max_deg, 0.0, 80.0),
            ("shift_sigma", self.shift_sigma, 0.0, 1.0),
            ("first_frame_scale", self.first_frame_scale, 0.0, 1.0),
            ("distance", self.distance.0, 2.0, 100.0),
        ];
        for (field, v, lo, hi) in checks {
            if !(v.is_finite() && v >= lo && v <= hi) {
                return Err(config_err(field, format!("{v} is outside [{lo}, {hi}]")));
            }
        }
        let (d0, d1) = self.distance;
        if !(d1.is_finite() && d1 >= d0 && d1 <= 100.0) {
            return Err(config_err(
                "distance",
                format!("({d0}, {d1}) is not a range within [2, 100]"),
            ));
        }
        Ok(())
    }
}

/// Rounds to the nearest float32 (records are float32; rendering uses the rounded value).
pub fn f32_exact(x: f64) -> f64 {
    x as f32 as f64
}

/// One frame's drawn parameters (all float32-exact).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameSample {
    /// `[n_exp]`
    pub expression: Vec<f64>,
    /// `[6]`: global rotation (zero) then jaw.
    pub pose: [f64; 6],
    /// `[6]`: eye joint 3 then eye joint 4, axis-angle.
    pub eye: [f64; 6],
    /// The release's `transform_matrix`.
    pub transform: [[f64; 4]; 3],
}

/// The shape code of identity `idx` (`[n_shape]`, float32-exact).
pub fn sample_shape(cfg: &SampleConfig, seed: u64, idx: usize, n_shape: usize) -> Vec<f64> {
    let mut rng = Rng::stream(seed, &[TAG_SHAPE, idx as u64]);
    (0..n_shape)
        .map(|k| {
            if k < cfg.shape_components {
                f32_exact(cfg.shape_sigma * rng.normal())
            } else {
                0.0
            }
        })
        .collect()
}

/// Frame `frame` of identity `idx`.
pub fn sample_frame(
    cfg: &SampleConfig,
    seed: u64,
    idx: usize,
    frame: usize,
    n_exp: usize,
) -> FrameSample {
    let mut rng = Rng::stream(seed, &[TAG_FRAME, idx as u64, frame as u64]);
    let s = if frame == 0 {
        cfg.first_frame_scale
    } else {
        1.0
    };
    let expression = (0..n_exp)
        .map(|k| {
            if k < cfg.exp_components {
                f32_exact(s * cfg.exp_sigma * rng.normal())
            } else {
                0.0
            }
        })
        .collect();
    // Mouths are closed more often than wide open.
    let jaw = s * cfg.jaw_max * rng.uniform().powf(1.5);
    let pose = [0.0, 0.0, 0.0, f32_exact(jaw), 0.0, 0.0];
    let clamp = |x: f64, m: f64| x.clamp(-m, m);
    let gaze_pitch = f32_exact(clamp(s * cfg.eye_sigma * rng.normal(), 3.0 * cfg.eye_sigma));
    let gaze_yaw = f32_exact(clamp(s * cfg.eye_sigma * rng.normal(), 3.0 * cfg.eye_sigma));
    let eye = [gaze_pitch, gaze_yaw, 0.0, gaze_pitch, gaze_yaw, 0.0];
    let yaw = s * rng.range(-cfg.yaw_max_deg, cfg.yaw_max_deg).to_radians();
    let pitch = s * rng
        .range(-cfg.pitch_max_deg, cfg.pitch_max_deg)
        .to_radians();
    let distance = rng.range(cfg.distance.0, cfg.distance.1);
    let mut tm = Camera::look_at_origin_matrix(distance, std::f64::consts::PI + yaw, pitch);
    tm[0][3] += cfg.shift_sigma * rng.normal();
    tm[1][3] += cfg.shift_sigma * rng.normal();
    let transform = tm.map(|row| row.map(f32_exact));
    FrameSample {
        expression,
        pose,
        eye,
        transform,
    }
}

/// The appearance stream of identity `idx`.
pub fn appearance_rng(seed: u64, idx: usize) -> Rng {
    Rng::stream(seed, &[TAG_APPEARANCE, idx as u64])
}
