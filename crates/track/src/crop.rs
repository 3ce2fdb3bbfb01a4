//! The release's 512 crop (TRACKING.md section 2) and its matte composite (section 3).
//!
//! * Crop rule: a square window of side `S = 1.65 sqrt(w h)` centred on a head box, corners
//!   `c +- S/2` cast to integers by truncation toward zero, any part outside the frame black,
//!   resized to 512 x 512 with antialiased bilinear (PyTorch's weights, `gagavatar_ops`).
//! * Head box: the release detects it with VGGHead (head with hair, larger than a face box); we
//!   estimate it from face landmarks, calibrated so our crops are framed like the release's
//!   training crops. Measured (`tools/reference/framing_measure.py`: MediaPipe 0.10.21 with
//!   irises on the 40 release crops of the VFHQ demo LMDB, medians, 512-crop pixels): iris
//!   midpoint (255.56, 199.03), axis-aligned mesh height 277.2 and inter-iris distance 92.6 (the
//!   spec's table, reproduced), and in the face's own frame (turned with the iris line, so a
//!   tilted head is framed like an upright one, which is how the head box is placed here): iris
//!   midpoint (259.94, 200.04) and mesh height along the up axis 273.64.
//!   [`FramingCalibration::default`] holds those face-frame numbers; the window is centred so
//!   the eyes land there, with a side that makes the mesh that tall.
//!   [`FramingCalibration::measure`] recomputes them from landmarks detected on any set of
//!   release crops (e.g. with the project's own face crate), [`framing_stats`] for one crop.
//! * Video: the head boxes are smoothed two-sided over the whole clip (Whittaker on the centre
//!   and the log side; the release uses a causal EMA with 0.03, which lags a moving head), so the
//!   crop window is nearly static but follows the head without delay.

use gagavatar_ops::resample::{ResizeMode, Taps};
use image::RgbImage;
use rayon::prelude::*;

use crate::error::{input, Result};
use crate::observation::FaceLandmarks;
use crate::smooth::{whittaker, MISSING_WEIGHT};

/// The release's window side over the head box's geometric-mean side.
pub const CROP_SCALE: f64 = 1.65;
/// Output side of the crop.
pub const CROP_PX: u32 = 512;

/// MediaPipe eye corners (image-left eye 33 / 133, other eye 362 / 263), for faces without
/// iris points.
const EYE_CORNERS: [usize; 4] = [33, 133, 362, 263];

/// A head box in frame pixels (corner convention), `x0 < x1`, `y0 < y1`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeadBox {
    pub x0: f64,
    pub y0: f64,
    pub x1: f64,
    pub y1: f64,
}

impl HeadBox {
    pub fn new(x0: f64, y0: f64, x1: f64, y1: f64) -> Result<Self> {
        if !([x0, y0, x1, y1].iter().all(|v| v.is_finite()) && x1 > x0 && y1 > y0) {
            return Err(input(
                "head box",
                format!("[{x0}, {y0}, {x1}, {y1}] is not a finite box with x0 < x1, y0 < y1"),
            ));
        }
        Ok(Self { x0, y0, x1, y1 })
    }

    /// A square box.
    pub fn square(centre: [f64; 2], side: f64) -> Result<Self> {
        let h = side / 2.0;
        Self::new(centre[0] - h, centre[1] - h, centre[0] + h, centre[1] + h)
    }

    pub fn centre(&self) -> [f64; 2] {
        [(self.x0 + self.x1) / 2.0, (self.y0 + self.y1) / 2.0]
    }

    /// Geometric mean of the sides.
    pub fn mean_side(&self) -> f64 {
        ((self.x1 - self.x0) * (self.y1 - self.y0)).sqrt()
    }
}

/// An integer crop window in frame pixels, `[x0, x1) x [y0, y1)`, possibly reaching outside
/// the frame (that part is black in the crop).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CropWindow {
    pub x0: i64,
    pub y0: i64,
    pub x1: i64,
    pub y1: i64,
}

impl CropWindow {
    /// The release's rule for a head box.
    pub fn from_head_box(b: &HeadBox) -> Result<Self> {
        let c = b.centre();
        let half = CROP_SCALE * b.mean_side() / 2.0;
        // Far beyond any image; keeps the integer corners and their differences exact.
        const LIMIT: f64 = 1e9;
        if !(c[0].abs() + half <= LIMIT && c[1].abs() + half <= LIMIT) {
            return Err(input(
                "crop window",
                format!("head box {b:?} lies too far out (beyond {LIMIT} pixels)"),
            ));
        }
        // Python's `.long()` truncates toward zero; `as` does too (and saturates).
        let w = Self {
            x0: (c[0] - half) as i64,
            y0: (c[1] - half) as i64,
            x1: (c[0] + half) as i64,
            y1: (c[1] + half) as i64,
        };
        if w.x1 <= w.x0 || w.y1 <= w.y0 {
            return Err(input(
                "crop window",
                format!("head box {b:?} gives an empty window {:?}", w.as_array()),
            ));
        }
        Ok(w)
    }

    pub fn width(&self) -> i64 {
        self.x1.saturating_sub(self.x0)
    }

    pub fn height(&self) -> i64 {
        self.y1.saturating_sub(self.y0)
    }

    pub fn as_array(&self) -> [i64; 4] {
        [self.x0, self.y0, self.x1, self.y1]
    }

    /// Frame pixels to 512-crop pixels (the resize maps the window's edges onto the crop's).
    pub fn frame_to_crop(&self, p: [f64; 2]) -> [f64; 2] {
        let s = CROP_PX as f64;
        [
            (p[0] - self.x0 as f64) * s / self.width() as f64,
            (p[1] - self.y0 as f64) * s / self.height() as f64,
        ]
    }

    pub fn crop_to_frame(&self, p: [f64; 2]) -> [f64; 2] {
        let s = CROP_PX as f64;
        [
            p[0] * self.width() as f64 / s + self.x0 as f64,
            p[1] * self.height() as f64 / s + self.y0 as f64,
        ]
    }

    /// A frame-pixel box as the release's `bbox` field: in the crop, divided by 512, clamped to
    /// [0, 1].
    pub fn normalized_box(&self, b: &HeadBox) -> [f64; 4] {
        let s = CROP_PX as f64;
        let a = self.frame_to_crop([b.x0, b.y0]);
        let c = self.frame_to_crop([b.x1, b.y1]);
        [a[0], a[1], c[0], c[1]].map(|v| (v / s).clamp(0.0, 1.0))
    }
}

/// Framing statistics of a face in a 512 crop (the quantities of the spec's table).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FramingStats {
    /// Eye centre (iris midpoint, or eye-corner midpoint without irises), crop pixels.
    pub eye_centre: [f64; 2],
    /// The eye centre in the face's frame: its offset from the crop centre turned by minus the
    /// eye line's angle, plus the centre (equals `eye_centre` for an upright face).
    pub eye_centre_face: [f64; 2],
    /// Height of the 468-point mesh along the face's up axis, crop pixels.
    pub face_height: f64,
    /// Inter-iris (or inter-eye-centre) distance, crop pixels.
    pub eye_distance: f64,
}

/// Eye centres (image-left eye first), the unit eye-line direction and the face's height along
/// the perpendicular, in the landmarks' pixel frame.
fn face_geometry(lm: &FaceLandmarks) -> ([[f64; 2]; 2], [f64; 2], f64) {
    let p = lm.points();
    let eyes = if lm.has_irises() {
        [p[468], p[473]]
    } else {
        let mid = |a: usize, b: usize| [(p[a][0] + p[b][0]) / 2.0, (p[a][1] + p[b][1]) / 2.0];
        [
            mid(EYE_CORNERS[0], EYE_CORNERS[1]),
            mid(EYE_CORNERS[2], EYE_CORNERS[3]),
        ]
    };
    let d = [eyes[1][0] - eyes[0][0], eyes[1][1] - eyes[0][1]];
    let n = (d[0] * d[0] + d[1] * d[1]).sqrt();
    // A degenerate eye line (both eyes on one point) falls back to upright.
    let dir = if n > 1e-9 {
        [d[0] / n, d[1] / n]
    } else {
        [1.0, 0.0]
    };
    // Image y points down; the face's down axis is the eye line turned +90 degrees.
    let down = [-dir[1], dir[0]];
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for q in lm.mesh() {
        let t = q[0] * down[0] + q[1] * down[1];
        lo = lo.min(t);
        hi = hi.max(t);
    }
    (eyes, dir, hi - lo)
}

/// The framing statistics of landmarks detected on a crop of side `crop_side` pixels.
pub fn framing_stats(lm: &FaceLandmarks, crop_side: f64) -> FramingStats {
    let (eyes, dir, height) = face_geometry(lm);
    let dx = eyes[1][0] - eyes[0][0];
    let dy = eyes[1][1] - eyes[0][1];
    let eye = [
        (eyes[0][0] + eyes[1][0]) / 2.0,
        (eyes[0][1] + eyes[1][1]) / 2.0,
    ];
    let h = crop_side / 2.0;
    let c = [eye[0] - h, eye[1] - h];
    let down = [-dir[1], dir[0]];
    FramingStats {
        eye_centre: eye,
        eye_centre_face: [
            c[0] * dir[0] + c[1] * dir[1] + h,
            c[0] * down[0] + c[1] * down[1] + h,
        ],
        face_height: height,
        eye_distance: (dx * dx + dy * dy).sqrt(),
    }
}

/// Where the face sits in a crop, as fractions of the crop side, in the face's frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FramingCalibration {
    /// Eye centre in the crop, `[x, y]` / crop side (face frame, see [`FramingStats`]).
    pub eye_centre: [f64; 2],
    /// Mesh height along the face's up axis / crop side.
    pub face_height: f64,
}

impl Default for FramingCalibration {
    /// Measured on the release's VFHQ demo crops (see the module notes).
    fn default() -> Self {
        Self {
            eye_centre: [259.94 / 512.0, 200.04 / 512.0],
            face_height: 273.64 / 512.0,
        }
    }
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

impl FramingCalibration {
    /// Medians of [`framing_stats`] over landmarks detected on release crops of side
    /// `crop_side` pixels.
    pub fn measure(crops: &[FaceLandmarks], crop_side: f64) -> Result<Self> {
        if crops.is_empty() || !(crop_side.is_finite() && crop_side > 0.0) {
            return Err(input(
                "framing calibration",
                format!("{} crops of side {crop_side}", crops.len()),
            ));
        }
        let stats: Vec<FramingStats> = crops.iter().map(|c| framing_stats(c, crop_side)).collect();
        let mut xs: Vec<f64> = stats.iter().map(|s| s.eye_centre_face[0]).collect();
        let mut ys: Vec<f64> = stats.iter().map(|s| s.eye_centre_face[1]).collect();
        let mut hs: Vec<f64> = stats.iter().map(|s| s.face_height).collect();
        Ok(Self {
            eye_centre: [median(&mut xs) / crop_side, median(&mut ys) / crop_side],
            face_height: median(&mut hs) / crop_side,
        })
    }

    /// The head box (square) whose release crop frames these landmarks like the calibration.
    pub fn head_box(&self, lm: &FaceLandmarks) -> Result<HeadBox> {
        let usable = self.face_height > 0.0
            && self.face_height.is_finite()
            && self.eye_centre.iter().all(|v| v.is_finite());
        if !usable {
            return Err(input(
                "framing calibration",
                format!("{self:?} is not usable"),
            ));
        }
        let (eyes, dir, height) = face_geometry(lm);
        if !(height > 0.0) {
            return Err(input(
                "face landmarks",
                "the mesh has no extent (all points on one line)",
            ));
        }
        let side = height / self.face_height;
        let down = [-dir[1], dir[0]];
        let eye = [
            (eyes[0][0] + eyes[1][0]) / 2.0,
            (eyes[0][1] + eyes[1][1]) / 2.0,
        ];
        let (ex, ey) = (self.eye_centre[0] - 0.5, self.eye_centre[1] - 0.5);
        let centre = [
            eye[0] - side * (ex * dir[0] + ey * down[0]),
            eye[1] - side * (ex * dir[1] + ey * down[1]),
        ];
        HeadBox::square(centre, side / CROP_SCALE)
    }
}

/// Head boxes of a video, smoothed over time (two-sided), with frames without a box filled.
/// `lambda` is the Whittaker strength on the centre and log side (per frame).
pub fn smooth_head_boxes(boxes: &[Option<HeadBox>], lambda: f64) -> Result<Vec<HeadBox>> {
    let known: Vec<usize> = (0..boxes.len()).filter(|&i| boxes[i].is_some()).collect();
    if known.is_empty() {
        return Err(input("head boxes", "no frame has a box"));
    }
    // Centre x, centre y, log side: filled linearly (held at the ends), then smoothed.
    let feats = |b: &HeadBox| {
        let c = b.centre();
        [c[0], c[1], b.mean_side().ln()]
    };
    let mut series = vec![[0.0; 3]; boxes.len()];
    let mut k = 0;
    for (i, s) in series.iter_mut().enumerate() {
        while k + 1 < known.len() && known[k + 1] <= i {
            k += 1;
        }
        let a = known[k];
        *s = match boxes[i] {
            Some(b) => feats(&b),
            None if i < a || k + 1 == known.len() => feats(&boxes[a].expect("known")),
            None => {
                let b = known[k + 1];
                let (fa, fb) = (
                    feats(&boxes[a].expect("known")),
                    feats(&boxes[b].expect("known")),
                );
                let t = (i - a) as f64 / (b - a) as f64;
                std::array::from_fn(|j| fa[j] + t * (fb[j] - fa[j]))
            }
        };
    }
    let w: Vec<f64> = boxes
        .iter()
        .map(|b| if b.is_some() { 1.0 } else { MISSING_WEIGHT })
        .collect();
    let mut out = [vec![], vec![], vec![]];
    for (j, o) in out.iter_mut().enumerate() {
        let y: Vec<f64> = series.iter().map(|s| s[j]).collect();
        *o = whittaker(&y, &w, lambda)?;
    }
    (0..boxes.len())
        .map(|i| HeadBox::square([out[0][i], out[1][i]], out[2][i].exp()))
        .collect()
}

/// The release's crop of `img` through `window`, `CROP_PX` square, antialiased bilinear with
/// PyTorch's weights, black outside the frame, rounded to 8 bits.
pub fn crop_image(img: &RgbImage, window: &CropWindow) -> Result<RgbImage> {
    let (ww, wh) = (window.width(), window.height());
    const MAX_SIDE: i64 = 1 << 16;
    if ww <= 0 || wh <= 0 || ww > MAX_SIDE || wh > MAX_SIDE {
        return Err(input(
            "crop window",
            format!("{:?}: sides must be 1 to {MAX_SIDE}", window.as_array()),
        ));
    }
    let out = CROP_PX as usize;
    let tx = Taps::new(ww as usize, out, ResizeMode::Antialias);
    let ty = Taps::new(wh as usize, out, ResizeMode::Antialias);
    let (iw, ih) = (img.width() as i64, img.height() as i64);
    let src = img.as_raw();
    let (wx, wy): (Vec<f32>, Vec<f32>) = (
        tx.w.iter().map(|&w| w as f32).collect(),
        ty.w.iter().map(|&w| w as f32).collect(),
    );
    // Vertical pass: for each output row, the window's columns (in f32), zero outside. Rows
    // are independent, so both passes run in parallel over output rows.
    let cols = ww as usize;
    let mut mid = vec![0f32; out * cols * 3];
    let (xa, xb) = (window.x0.max(0), window.x1.min(iw));
    mid.par_chunks_mut(cols * 3)
        .enumerate()
        .for_each(|(o, row)| {
            // Only the part of the window's row that lies inside the frame contributes.
            if xa >= xb {
                return;
            }
            for t in 0..ty.n {
                let wgt = wy[o * ty.n + t];
                if wgt == 0.0 {
                    continue;
                }
                let y = window.y0 + (ty.start[o] + t) as i64;
                if y < 0 || y >= ih {
                    continue;
                }
                let line = &src[(y * iw + xa) as usize * 3..(y * iw + xb) as usize * 3];
                let dst = &mut row[(xa - window.x0) as usize * 3..(xb - window.x0) as usize * 3];
                for (d, &s) in dst.iter_mut().zip(line) {
                    *d += wgt * s as f32;
                }
            }
        });
    // Horizontal pass.
    let mut res = RgbImage::new(CROP_PX, CROP_PX);
    res.as_mut()
        .par_chunks_mut(out * 3)
        .enumerate()
        .for_each(|(o, dst)| {
            let row = &mid[o * cols * 3..(o + 1) * cols * 3];
            for (p, px) in dst.chunks_exact_mut(3).enumerate() {
                let mut acc = [0f32; 3];
                let taps = &wx[p * tx.n..(p + 1) * tx.n];
                let base = tx.start[p] * 3;
                for (t, &w) in taps.iter().enumerate() {
                    let x = base + t * 3;
                    acc[0] += w * row[x];
                    acc[1] += w * row[x + 1];
                    acc[2] += w * row[x + 2];
                }
                for c in 0..3 {
                    px[c] = acc[c].round().clamp(0.0, 255.0) as u8;
                }
            }
        });
    Ok(res)
}

/// The release's matte composite on black: `img / 255 * alpha * 255`, truncated to 8 bits (as
/// its `.to(torch.uint8)`). `alpha` is row-major, one value per pixel, clamped to [0, 1] (a
/// network's soft matte may overshoot by rounding); non-finite values are an error.
pub fn apply_matte(crop: &RgbImage, alpha: &[f32]) -> Result<RgbImage> {
    let n = (crop.width() * crop.height()) as usize;
    if alpha.len() != n {
        return Err(input(
            "matte",
            format!(
                "{} values for a {}x{} image",
                alpha.len(),
                crop.width(),
                crop.height()
            ),
        ));
    }
    if let Some(i) = alpha.iter().position(|a| !a.is_finite()) {
        return Err(input("matte", format!("value {i} is {}", alpha[i])));
    }
    let mut out = crop.clone();
    for (px, &a) in out.as_mut().chunks_exact_mut(3).zip(alpha) {
        let a = a.clamp(0.0, 1.0);
        for c in px {
            *c = ((*c as f32 / 255.0 * a) * 255.0).clamp(0.0, 255.0) as u8;
        }
    }
    Ok(out)
}
