//! Fitting FLAME + camera to the 70 landmarks (TRACKING.md section 4's model and camera; our own
//! objective and solver).
//!
//! Unknowns per frame: expression, jaw, both eyes, the camera rotation (a multiplicative
//! 3-vector step, `R <- R Exp(d)`) and translation; FLAME's global pose stays zero (the head's
//! rotation lives in the camera, as in the release) and the focal length is the release's 12.
//! The shape code is shared: one per photo, one per video.
//!
//! Objective (squared pixels at 512): per landmark `w_k rho(|pi(L_k) - target_k|)` with `rho` the
//! square or Huber, plus Tikhonov priors on shape and expression, per-component priors on jaw and
//! eyes, a coupling of the two eyes (their gazes move together), and hinge penalties outside
//! plausible jaw and eye ranges. It is minimised by Levenberg-Marquardt on the normal equations
//! with analytic Jacobians (the rig's and the camera's, checked against central differences in
//! the tests). With several frames sharing one shape the frame blocks are eliminated first (a
//! Schur complement on the shape), so a joint solve over K frames costs K small solves plus one
//! of the shape's size.
//!
//! Start: a scaled-orthographic alignment of the mean face (closed form), a rigid LM, then the
//! full LM. Video: the shape is solved jointly on a few keyframes, then each frame is fitted
//! with that shape, warm-started from the previous frame (the first from its nearest
//! keyframe's joint state; a warm start that ends worse than a threshold is retried from the
//! nearest keyframe's state and from the closed form, keeping the best).

use rayon::prelude::*;

use crate::camera::{
    cross, matvec_t, project_with_grad, skew, CameraPose, Mat3, Vec3, CROP_SIZE, FOCAL_PX,
};
use crate::error::{input, Result, TrackError};
use crate::linalg::{cholesky, cholesky_solve, cholesky_solve_many, matmul_tn, matvec_tn};
use crate::rig::{FaceCodes, LandmarkRig, RigColumns, N_LANDMARKS};

/// Per-group landmark weights (iBUG groups; the pupils are 68 and 69).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LandmarkWeights {
    pub contour: f64,
    pub brows: f64,
    pub nose: f64,
    pub eyes: f64,
    pub mouth: f64,
    pub pupils: f64,
}

impl Default for LandmarkWeights {
    fn default() -> Self {
        Self {
            // FLAME's static contour and a detector's jaw line are different curves (see
            // `mapping`); trust them half as much as the inner face.
            contour: 0.5,
            brows: 1.0,
            nose: 1.0,
            eyes: 1.0,
            mouth: 1.0,
            pupils: 1.0,
        }
    }
}

impl LandmarkWeights {
    pub fn per_landmark(&self) -> [f64; N_LANDMARKS] {
        std::array::from_fn(|k| match k {
            0..=16 => self.contour,
            17..=26 => self.brows,
            27..=35 => self.nose,
            36..=47 => self.eyes,
            48..=67 => self.mouth,
            _ => self.pupils,
        })
    }
}

/// Everything the fit can be told. Prior weights are in squared pixels (at 512) per squared
/// unit of the code: a weight of 4 makes a code of 1 cost as much as a 2 px landmark error.
#[derive(Debug, Clone, PartialEq)]
pub struct FitOptions {
    pub shape_prior: f64,
    pub expression_prior: f64,
    /// Jaw axis-angle components (x opens the mouth; y and z are sideways and twist).
    pub jaw_prior: [f64; 3],
    /// Plausible jaw opening `jaw.x` in radians; outside it a hinge penalty applies.
    pub jaw_opening_range: (f64, f64),
    /// Eye axis-angle components (x pitch, y yaw, z roll; two pupils cannot see the roll).
    /// Pitch and yaw are held loosely: a gaze pulled towards straight ahead leaves the iris
    /// points off, and the fit then turns the head to meet them (with 50 instead of 5, exact
    /// synthetic landmarks gave the camera 0.7 degrees off instead of 0.25).
    pub eye_prior: [f64; 3],
    /// Ties the two eyes' rotations together (both look the same way).
    pub eye_coupling: f64,
    /// Largest plausible |eye rotation| per component (radians).
    pub eye_range: f64,
    /// Plausible camera distance (the translation's z). The 512 crop frames every head alike,
    /// so the release's tracked cameras sit near z = 9 (its start is 9.01); a photo fit free
    /// to move closer trades distance for shape and perspective and lands at z ~ 1 with a
    /// distorted head, though its landmarks match.
    pub distance_range: (f64, f64),
    /// Weight of the hinge penalties.
    pub bound_weight: f64,
    pub landmark_weights: LandmarkWeights,
    /// Huber threshold in pixels (`None`: plain least squares).
    pub huber_px: Option<f64>,
    /// LM iterations of a photo's (or keyframes') joint fit.
    pub photo_iterations: usize,
    /// LM iterations of a video frame (warm-started).
    pub frame_iterations: usize,
    /// Frames of a video used to solve its shape.
    pub keyframes: usize,
    /// A warm-started video frame whose RMS landmark error ends above this (pixels) is fitted
    /// again from the closed-form start, keeping the better.
    pub restart_rms_px: f64,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            shape_prior: 40.0,
            expression_prior: 2.0,
            jaw_prior: [1.0, 400.0, 400.0],
            jaw_opening_range: (-0.05, 0.6),
            eye_prior: [5.0, 5.0, 4000.0],
            eye_coupling: 200.0,
            eye_range: 0.6,
            distance_range: (7.0, 12.0),
            bound_weight: 1e5,
            landmark_weights: LandmarkWeights::default(),
            huber_px: Some(8.0),
            photo_iterations: 40,
            frame_iterations: 12,
            keyframes: 8,
            restart_rms_px: 6.0,
        }
    }
}

impl FitOptions {
    pub fn validate(&self) -> Result<()> {
        let mut vals = vec![
            ("shape_prior", self.shape_prior),
            ("expression_prior", self.expression_prior),
            ("eye_coupling", self.eye_coupling),
            ("eye_range", self.eye_range),
            ("bound_weight", self.bound_weight),
            ("restart_rms_px", self.restart_rms_px),
        ];
        vals.extend(self.jaw_prior.iter().map(|&v| ("jaw_prior", v)));
        vals.extend(self.eye_prior.iter().map(|&v| ("eye_prior", v)));
        let w = self.landmark_weights;
        vals.extend([
            ("landmark_weights", w.contour),
            ("landmark_weights", w.brows),
            ("landmark_weights", w.nose),
            ("landmark_weights", w.eyes),
            ("landmark_weights", w.mouth),
            ("landmark_weights", w.pupils),
        ]);
        for (name, v) in vals {
            if !(v.is_finite() && v >= 0.0) {
                return Err(input(
                    "fit options",
                    format!("{name} = {v}: must be finite and >= 0"),
                ));
            }
        }
        let (lo, hi) = self.jaw_opening_range;
        if !(lo.is_finite() && hi.is_finite() && lo < hi) {
            return Err(input(
                "fit options",
                format!("jaw_opening_range ({lo}, {hi}) is not an interval"),
            ));
        }
        let (zlo, zhi) = self.distance_range;
        if !(zlo.is_finite() && zhi.is_finite() && 0.0 < zlo && zlo < zhi) {
            return Err(input(
                "fit options",
                format!("distance_range ({zlo}, {zhi}) is not a positive interval"),
            ));
        }
        if let Some(h) = self.huber_px {
            if !(h.is_finite() && h > 0.0) {
                return Err(input("fit options", format!("huber_px = {h}: must be > 0")));
            }
        }
        if self.photo_iterations == 0 || self.frame_iterations == 0 || self.keyframes == 0 {
            return Err(input(
                "fit options",
                "iteration and keyframe counts must be at least 1",
            ));
        }
        Ok(())
    }
}

/// The 70 targets of one frame in 512-crop pixels, with a weight each (0: absent).
#[derive(Debug, Clone, PartialEq)]
pub struct LandmarkTargets {
    pub points: [[f64; 2]; N_LANDMARKS],
    pub weights: [f64; N_LANDMARKS],
}

/// At least this many weighted landmarks, or a frame says too little to fit a camera.
pub const MIN_LANDMARKS: usize = 6;

impl LandmarkTargets {
    pub fn new(points: [[f64; 2]; N_LANDMARKS], weights: [f64; N_LANDMARKS]) -> Result<Self> {
        for k in 0..N_LANDMARKS {
            let w = weights[k];
            if !(w.is_finite() && w >= 0.0) {
                return Err(input(
                    "landmark targets",
                    format!("weight {k} is {w}: must be finite and >= 0"),
                ));
            }
            if w > 0.0 && !(points[k][0].is_finite() && points[k][1].is_finite()) {
                return Err(input(
                    "landmark targets",
                    format!("point {k} is not finite ({:?})", points[k]),
                ));
            }
        }
        let used = weights.iter().filter(|&&w| w > 0.0).count();
        if used < MIN_LANDMARKS {
            return Err(input(
                "landmark targets",
                format!("{used} weighted points; at least {MIN_LANDMARKS} are needed"),
            ));
        }
        Ok(Self { points, weights })
    }

    /// All 70 with the options' group weights.
    pub fn with_weights(points: [[f64; 2]; N_LANDMARKS], w: &LandmarkWeights) -> Result<Self> {
        Self::new(points, w.per_landmark())
    }
}

/// The per-frame unknowns.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameState {
    pub expression: Vec<f64>,
    pub jaw: Vec3,
    pub eyes: [f64; 6],
    pub camera: CameraPose,
}

impl FrameState {
    pub fn neutral(rig: &LandmarkRig, camera: CameraPose) -> Self {
        Self {
            expression: vec![0.0; rig.n_exp],
            jaw: [0.0; 3],
            eyes: [0.0; 6],
            camera,
        }
    }

    pub fn codes(&self, shape: &[f64]) -> FaceCodes {
        FaceCodes {
            shape: shape.to_vec(),
            expression: self.expression.clone(),
            jaw: self.jaw,
            eyes: self.eyes,
        }
    }
}

/// A fitted frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameFit {
    pub state: FrameState,
    /// RMS landmark error (pixels at 512) over the weighted landmarks, unweighted.
    pub rms_px: f64,
    pub iterations: usize,
}

/// A fitted photo: its shape and its frame.
#[derive(Debug, Clone, PartialEq)]
pub struct PhotoFit {
    pub shape: Vec<f64>,
    pub frame: FrameFit,
}

/// Which columns a frame's Jacobian has: `[shape?][expression, jaw, eyes]?[rotation, translation]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Layout {
    pub n_shape: usize,
    pub nonrigid: bool,
    pub n_exp: usize,
}

impl Layout {
    pub fn new(rig: &LandmarkRig, shape: bool, nonrigid: bool) -> Self {
        Self {
            n_shape: if shape { rig.n_shape } else { 0 },
            nonrigid,
            n_exp: rig.n_exp,
        }
    }
    pub fn exp(&self) -> usize {
        self.n_shape
    }
    pub fn jaw(&self) -> usize {
        self.n_shape + self.n_exp
    }
    pub fn eyes(&self) -> usize {
        self.jaw() + 3
    }
    pub fn rot(&self) -> usize {
        if self.nonrigid {
            self.eyes() + 6
        } else {
            self.n_shape
        }
    }
    pub fn trans(&self) -> usize {
        self.rot() + 3
    }
    pub fn n(&self) -> usize {
        self.trans() + 3
    }
    /// Columns owned by the frame (everything but the shape).
    pub fn n_frame(&self) -> usize {
        self.n() - self.n_shape
    }
}

/// Residuals of one frame (data rows then prior rows) and optionally their Jacobian: dense for
/// the data rows, sparse for the prior rows (one or two entries each).
#[derive(Debug, Clone, Default)]
pub(crate) struct Residuals {
    pub r: Vec<f64>,
    /// `[n_data][n]` row-major, or empty.
    pub j: Vec<f64>,
    pub n_data: usize,
    /// `(column, value)` entries of each prior row (`r[n_data + i]`), when asked.
    pub sparse: Vec<Vec<(usize, f64)>>,
    /// Robust cost (equals `|r|^2` without Huber).
    pub cost: f64,
    /// Sum of squared pixel errors and the number of landmarks, for the RMS.
    pub sq_px: f64,
    pub n_px: usize,
}

impl Residuals {
    /// The whole Jacobian as one dense `[r.len()][n]` matrix (tests).
    #[cfg(test)]
    fn dense_jacobian(&self, n: usize) -> Vec<f64> {
        let mut out = self.j.clone();
        for entries in &self.sparse {
            let mut row = vec![0.0; n];
            for &(c, v) in entries {
                row[c] += v;
            }
            out.extend(row);
        }
        out
    }
}

fn hinge(x: f64, lo: f64, hi: f64) -> f64 {
    if x < lo {
        x - lo
    } else if x > hi {
        x - hi
    } else {
        0.0
    }
}

/// The residuals of one frame at `shape` / `state`; with `layout`, the Jacobian too (the
/// rotation column is the derivative along `R Exp(d)` at d = 0).
pub(crate) fn frame_residuals(
    rig: &LandmarkRig,
    t: &LandmarkTargets,
    o: &FitOptions,
    shape: &[f64],
    state: &FrameState,
    layout: Option<Layout>,
) -> Result<Residuals> {
    let codes = state.codes(shape);
    let rig_cols = layout.and_then(|l| {
        l.nonrigid.then_some(RigColumns {
            shape: l.n_shape > 0,
        })
    });
    let out = rig.evaluate(&codes, rig_cols)?;
    let n = layout.map_or(0, |l| l.n());
    let cam = &state.camera;
    let rot: &Mat3 = &cam.rotation;
    let mut res = Residuals::default();
    let mut row_u = vec![0.0; n];
    let mut row_v = vec![0.0; n];
    for k in 0..N_LANDMARKS {
        let w = t.weights[k];
        if w <= 0.0 {
            continue;
        }
        let p = out.points[k];
        let q = matvec_t(rot, &p);
        let x = [
            q[0] + cam.translation[0],
            q[1] + cam.translation[1],
            q[2] + cam.translation[2],
        ];
        if !(x[2] > 1e-6) {
            return Err(TrackError::Numerical {
                stage: "landmark projection",
                reason: format!("landmark {k} is behind the camera (depth {})", x[2]),
            });
        }
        let (uv, g) = project_with_grad(&x);
        let e = [uv[0] - t.points[k][0], uv[1] - t.points[k][1]];
        let en = (e[0] * e[0] + e[1] * e[1]).sqrt();
        res.sq_px += en * en;
        res.n_px += 1;
        // Huber as iteratively reweighted least squares: the weight makes the gradient exact.
        let (hw, cost) = match o.huber_px {
            Some(h) if en > h => (h / en, 2.0 * h * en - h * h),
            _ => (1.0, en * en),
        };
        res.cost += w * cost;
        let sw = (w * hw).sqrt();
        res.r.push(sw * e[0]);
        res.r.push(sw * e[1]);
        let Some(l) = layout else { continue };
        for (row, gi) in [(&mut row_u, &g[0]), (&mut row_v, &g[1])] {
            row.fill(0.0);
            // d pixel / d FLAME point = g R^T (column form X = R^T p + T).
            let c: Vec3 = std::array::from_fn(|y| (0..3).map(|xx| gi[xx] * rot[y][xx]).sum());
            if l.nonrigid {
                let nc = out.n_cols;
                let jk = &out.jacobian[k * 3 * nc..(k + 1) * 3 * nc];
                for (y, &cy) in c.iter().enumerate() {
                    if cy == 0.0 {
                        continue;
                    }
                    for (dst, &src) in row[..nc].iter_mut().zip(&jk[y * nc..(y + 1) * nc]) {
                        *dst += cy * src;
                    }
                }
            }
            // d X / d rotation step = [q]x, d X / d T = I.
            let sq = skew(&q);
            for a in 0..3 {
                row[l.rot() + a] = (0..3).map(|xx| gi[xx] * sq[xx][a]).sum();
                row[l.trans() + a] = gi[a];
            }
            res.j.extend(row.iter().map(|v| v * sw));
        }
    }
    res.n_data = res.r.len();
    // Priors and bounds (the shape's prior is added by the caller, once per shape).
    let prior = |value: f64, weight: f64, col: Option<usize>, res: &mut Residuals| {
        let s = weight.sqrt();
        res.r.push(s * value);
        res.cost += weight * value * value;
        if layout.is_some() {
            res.sparse.push(col.map(|c| (c, s)).into_iter().collect());
        }
    };
    let (zlo, zhi) = o.distance_range;
    let hz = hinge(state.camera.translation[2], zlo, zhi);
    prior(
        hz,
        o.bound_weight,
        layout.filter(|_| hz != 0.0).map(|l| l.trans() + 2),
        &mut res,
    );
    let nonrigid = layout.is_none_or(|l| l.nonrigid);
    if nonrigid {
        let l = layout;
        for (i, &e) in state.expression.iter().enumerate() {
            prior(e, o.expression_prior, l.map(|l| l.exp() + i), &mut res);
        }
        for a in 0..3 {
            prior(
                state.jaw[a],
                o.jaw_prior[a],
                l.map(|l| l.jaw() + a),
                &mut res,
            );
        }
        let (lo, hi) = o.jaw_opening_range;
        let hj = hinge(state.jaw[0], lo, hi);
        prior(
            hj,
            o.bound_weight,
            l.filter(|_| hj != 0.0).map(|l| l.jaw()),
            &mut res,
        );
        for i in 0..6 {
            prior(
                state.eyes[i],
                o.eye_prior[i % 3],
                l.map(|l| l.eyes() + i),
                &mut res,
            );
            let he = hinge(state.eyes[i], -o.eye_range, o.eye_range);
            prior(
                he,
                o.bound_weight,
                l.filter(|_| he != 0.0).map(|l| l.eyes() + i),
                &mut res,
            );
        }
        for a in 0..3 {
            let d = state.eyes[a] - state.eyes[3 + a];
            let s = o.eye_coupling.sqrt();
            res.r.push(s * d);
            res.cost += o.eye_coupling * d * d;
            if let Some(l) = layout {
                res.sparse
                    .push(vec![(l.eyes() + a, s), (l.eyes() + 3 + a, -s)]);
            }
        }
    }
    Ok(res)
}

fn rms(sq: f64, n: usize) -> f64 {
    if n == 0 {
        0.0
    } else {
        (sq / n as f64).sqrt()
    }
}

/// Applies a frame's step (frame columns only, in [`Layout`] order without the shape).
fn apply_frame_step(state: &mut FrameState, l: &Layout, step: &[f64]) {
    let off = l.n_shape;
    let at = |c: usize| step[c - off];
    if l.nonrigid {
        for (i, e) in state.expression.iter_mut().enumerate() {
            *e += at(l.exp() + i);
        }
        for a in 0..3 {
            state.jaw[a] += at(l.jaw() + a);
        }
        for i in 0..6 {
            state.eyes[i] += at(l.eyes() + i);
        }
    }
    let d = [at(l.rot()), at(l.rot() + 1), at(l.rot() + 2)];
    let t = [at(l.trans()), at(l.trans() + 1), at(l.trans() + 2)];
    state.camera.retract(&d, &t);
}

/// One frame's linearisation split into frame (`a`, `g`) and shape (`b`, `c`, `gs`) blocks.
struct FrameSystem {
    a: Vec<f64>,
    g: Vec<f64>,
    /// `[n_frame][n_shape]`
    b: Vec<f64>,
    c: Vec<f64>,
    gs: Vec<f64>,
}

fn frame_system(
    rig: &LandmarkRig,
    t: &LandmarkTargets,
    o: &FitOptions,
    shape: &[f64],
    state: &FrameState,
    l: &Layout,
) -> Result<FrameSystem> {
    let res = frame_residuals(rig, t, o, shape, state, Some(*l))?;
    let n = l.n();
    let rows = res.n_data;
    let mut full = vec![0.0; n * n];
    matmul_tn(&res.j, &res.j, rows, n, n, &mut full, false);
    let mut gfull = matvec_tn(&res.j, &res.r[..rows], n);
    for (entries, &r) in res.sparse.iter().zip(&res.r[rows..]) {
        for &(a, va) in entries {
            gfull[a] += va * r;
            for &(b, vb) in entries {
                full[a * n + b] += va * vb;
            }
        }
    }
    let (ns, nf) = (l.n_shape, l.n_frame());
    let mut a = vec![0.0; nf * nf];
    let mut b = vec![0.0; nf * ns];
    let mut c = vec![0.0; ns * ns];
    for i in 0..nf {
        a[i * nf..(i + 1) * nf].copy_from_slice(&full[(ns + i) * n + ns..(ns + i + 1) * n]);
        b[i * ns..(i + 1) * ns].copy_from_slice(&full[(ns + i) * n..(ns + i) * n + ns]);
    }
    for i in 0..ns {
        c[i * ns..(i + 1) * ns].copy_from_slice(&full[i * n..i * n + ns]);
    }
    Ok(FrameSystem {
        a,
        g: gfull[ns..].to_vec(),
        b,
        c,
        gs: gfull[..ns].to_vec(),
    })
}

/// LM stops when an accepted step lowers the cost by less than this fraction (the cost is in
/// squared pixels; 1e-7 of it is far below a visible change).
const REL_TOL: f64 = 1e-7;

/// Levenberg-Marquardt over K frames sharing a shape (free or fixed). Returns the iterations
/// run. `nonrigid = false` fits the cameras only.
#[allow(clippy::too_many_arguments)] // the problem (rig, targets, options), its state, its mode
fn lm(
    rig: &LandmarkRig,
    targets: &[&LandmarkTargets],
    o: &FitOptions,
    shape: &mut [f64],
    states: &mut [FrameState],
    shape_free: bool,
    nonrigid: bool,
    max_iters: usize,
) -> Result<usize> {
    let l = Layout::new(rig, shape_free, nonrigid);
    let (ns, nf) = (l.n_shape, l.n_frame());
    let cost_of = |shape: &[f64], states: &[FrameState]| -> Result<f64> {
        let mut c = 0.0;
        for (t, s) in targets.iter().zip(states) {
            c += frame_residuals(rig, t, o, shape, s, None)?.cost;
        }
        if shape_free {
            c += o.shape_prior * shape.iter().map(|x| x * x).sum::<f64>();
        }
        Ok(c)
    };
    let mut cost = cost_of(shape, states)?;
    let mut mu = 1e-4;
    let mut iters = 0;
    for _ in 0..max_iters {
        iters += 1;
        let systems: Vec<FrameSystem> = targets
            .par_iter()
            .zip(states.par_iter())
            .map(|(t, s)| frame_system(rig, t, o, shape, s, &l))
            .collect::<Result<_>>()?;
        let mut improved = false;
        for _attempt in 0..12 {
            let step = damped_step(&systems, ns, nf, shape, o.shape_prior, mu);
            let Some((ds, dfs)) = step else {
                mu *= 10.0;
                continue;
            };
            let mut new_shape = shape.to_vec();
            for (x, d) in new_shape.iter_mut().zip(&ds) {
                *x += d;
            }
            let mut new_states = states.to_vec();
            for (s, d) in new_states.iter_mut().zip(&dfs) {
                apply_frame_step(s, &l, d);
            }
            let new_cost = match cost_of(&new_shape, &new_states) {
                Ok(c) if c.is_finite() => c,
                // A step behind the camera or to NaN: shorten it.
                _ => f64::INFINITY,
            };
            if new_cost < cost {
                let rel = (cost - new_cost) / cost.max(1e-300);
                shape.copy_from_slice(&new_shape);
                states.clone_from_slice(&new_states);
                cost = new_cost;
                mu = (mu / 3.0).max(1e-12);
                improved = true;
                if rel < REL_TOL {
                    return Ok(iters);
                }
                break;
            }
            mu *= 4.0;
        }
        if !improved {
            break;
        }
    }
    Ok(iters)
}

/// Solves the damped normal equations with the frames eliminated first. `None` when a block is
/// not positive definite at this damping.
fn damped_step(
    systems: &[FrameSystem],
    ns: usize,
    nf: usize,
    shape: &[f64],
    shape_prior: f64,
    mu: f64,
) -> Option<(Vec<f64>, Vec<Vec<f64>>)> {
    let damp = |m: &mut [f64], n: usize| {
        for i in 0..n {
            let d = m[i * n + i];
            m[i * n + i] = d + mu * d.max(1e-9) + 1e-12;
        }
    };
    // Per frame: L_i, A_i^-1 B_i, A_i^-1 g_i.
    let mut factors = Vec::with_capacity(systems.len());
    for s in systems {
        let mut a = s.a.clone();
        damp(&mut a, nf);
        if !cholesky(&mut a, nf) {
            return None;
        }
        let mut ainv_b = s.b.clone();
        if ns > 0 {
            cholesky_solve_many(&a, nf, &mut ainv_b, ns);
        }
        let mut ainv_g = s.g.clone();
        cholesky_solve(&a, nf, &mut ainv_g);
        factors.push((a, ainv_b, ainv_g));
    }
    let mut ds = vec![0.0; ns];
    if ns > 0 {
        let mut sc = vec![0.0; ns * ns];
        let mut rhs: Vec<f64> = shape.iter().map(|x| shape_prior * x).collect();
        for i in 0..ns {
            sc[i * ns + i] += shape_prior;
        }
        for s in systems {
            for (x, y) in sc.iter_mut().zip(&s.c) {
                *x += y;
            }
            for (x, y) in rhs.iter_mut().zip(&s.gs) {
                *x += y;
            }
        }
        // Damp the shape block of the full system (as the frame blocks were), then eliminate.
        damp(&mut sc, ns);
        let mut btab = vec![0.0; ns * ns];
        for (s, (_, ainv_b, ainv_g)) in systems.iter().zip(&factors) {
            // S -= B^T A^-1 B, rhs -= B^T A^-1 g.
            matmul_tn(&s.b, ainv_b, nf, ns, ns, &mut btab, false);
            for (d, x) in sc.iter_mut().zip(&btab) {
                *d -= x;
            }
            for (x, y) in rhs.iter_mut().zip(matvec_tn(&s.b, ainv_g, ns)) {
                *x -= y;
            }
        }
        if !cholesky(&mut sc, ns) {
            return None;
        }
        cholesky_solve(&sc, ns, &mut rhs);
        ds = rhs.iter().map(|x| -x).collect();
    }
    let dfs = factors
        .iter()
        .map(|(_, ainv_b, ainv_g)| {
            (0..nf)
                .map(|r| {
                    let coupled: f64 = (0..ns).map(|i| ainv_b[r * ns + i] * ds[i]).sum();
                    -(ainv_g[r] + coupled)
                })
                .collect()
        })
        .collect();
    Some((ds, dfs))
}

/// Closed-form camera for a face with these landmarks: scaled orthographic alignment of the
/// rig's landmarks (at `codes`) to the targets, then depth from the scale. Needs 4 or more
/// weighted, non-coplanar points.
pub fn initial_camera(
    rig: &LandmarkRig,
    codes: &FaceCodes,
    t: &LandmarkTargets,
) -> Result<CameraPose> {
    let pts = rig.landmarks(codes)?;
    // Normalised image coordinates: x_n = X / Z = (256 - u) / focal_px.
    let c = CROP_SIZE / 2.0;
    let mut obs = Vec::new();
    for k in 0..N_LANDMARKS {
        if t.weights[k] > 0.0 {
            let [u, v] = t.points[k];
            obs.push((
                pts[k],
                [(c - u) / FOCAL_PX, (c - v) / FOCAL_PX],
                t.weights[k],
            ));
        }
    }
    let wsum: f64 = obs.iter().map(|o| o.2).sum();
    let pm: Vec3 = std::array::from_fn(|i| obs.iter().map(|o| o.2 * o.0[i]).sum::<f64>() / wsum);
    let xm: [f64; 2] =
        std::array::from_fn(|i| obs.iter().map(|o| o.2 * o.1[i]).sum::<f64>() / wsum);
    // Affine fit x - xm = A (p - pm): A = (X^T W P)(P^T W P)^-1.
    let mut ptp = [[0.0; 3]; 3];
    let mut xtp = [[0.0; 3]; 2];
    for (p, x, w) in &obs {
        let dp = [p[0] - pm[0], p[1] - pm[1], p[2] - pm[2]];
        let dx = [x[0] - xm[0], x[1] - xm[1]];
        for i in 0..3 {
            for j in 0..3 {
                ptp[i][j] += w * dp[i] * dp[j];
            }
            for r in 0..2 {
                xtp[r][i] += w * dx[r] * dp[i];
            }
        }
    }
    let inv = invert3(&ptp).ok_or_else(|| TrackError::Numerical {
        stage: "initial camera",
        reason: "the model landmarks are coplanar".into(),
    })?;
    let a: [[f64; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|j| (0..3).map(|i| xtp[r][i] * inv[i][j]).sum())
    });
    // Nearest scaled matrix with orthonormal rows: M = (A A^T)^-1/2 A, s = mean singular value.
    let aat = [
        [dot3(&a[0], &a[0]), dot3(&a[0], &a[1])],
        [dot3(&a[1], &a[0]), dot3(&a[1], &a[1])],
    ];
    let det = aat[0][0] * aat[1][1] - aat[0][1] * aat[1][0];
    let tr = aat[0][0] + aat[1][1];
    if !(det > 0.0) {
        return Err(TrackError::Numerical {
            stage: "initial camera",
            reason: "degenerate landmark configuration".into(),
        });
    }
    let sd = det.sqrt();
    let st = (tr + 2.0 * sd).sqrt();
    // sqrt(AA^T) = (AA^T + sqrt(det) I) / sqrt(tr + 2 sqrt(det)); its inverse in closed form.
    let sq = [
        [(aat[0][0] + sd) / st, aat[0][1] / st],
        [aat[1][0] / st, (aat[1][1] + sd) / st],
    ];
    let scale = (sq[0][0] + sq[1][1]) / 2.0;
    let dsq = sq[0][0] * sq[1][1] - sq[0][1] * sq[1][0];
    let isq = [
        [sq[1][1] / dsq, -sq[0][1] / dsq],
        [-sq[1][0] / dsq, sq[0][0] / dsq],
    ];
    let m: [[f64; 3]; 2] =
        std::array::from_fn(|r| std::array::from_fn(|j| isq[r][0] * a[0][j] + isq[r][1] * a[1][j]));
    // Columns of R (row convention: X = p . R[:, 0]) are the rows of M; the third completes a
    // right-handed frame.
    let c0 = m[0];
    let c1 = m[1];
    let c2 = cross(&c0, &c1);
    let rotation: Mat3 = std::array::from_fn(|i| [c0[i], c1[i], c2[i]]);
    let z0 = 1.0 / scale;
    let translation = [
        xm[0] * z0 - dot3(&c0, &pm),
        xm[1] * z0 - dot3(&c1, &pm),
        z0 - dot3(&c2, &pm),
    ];
    let cam = CameraPose {
        rotation,
        translation,
    };
    if !(z0.is_finite() && z0 > 0.0) {
        return Err(TrackError::Numerical {
            stage: "initial camera",
            reason: format!("depth {z0}"),
        });
    }
    Ok(cam)
}

fn dot3(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn invert3(m: &Mat3) -> Option<Mat3> {
    let c = |r: usize, s: usize| {
        let (r1, r2) = ((r + 1) % 3, (r + 2) % 3);
        let (s1, s2) = ((s + 1) % 3, (s + 2) % 3);
        m[r1][s1] * m[r2][s2] - m[r1][s2] * m[r2][s1]
    };
    let det = m[0][0] * c(0, 0) + m[0][1] * c(0, 1) + m[0][2] * c(0, 2);
    let scale = m.iter().flatten().map(|x| x.abs()).fold(0.0, f64::max);
    if !(det.abs() > 1e-12 * scale.powi(3)) {
        return None;
    }
    Some(std::array::from_fn(|i| {
        std::array::from_fn(|j| c(j, i) / det)
    }))
}

fn finish(
    rig: &LandmarkRig,
    t: &LandmarkTargets,
    o: &FitOptions,
    shape: &[f64],
    state: FrameState,
    iterations: usize,
) -> Result<FrameFit> {
    let r = frame_residuals(rig, t, o, shape, &state, None)?;
    Ok(FrameFit {
        state,
        rms_px: rms(r.sq_px, r.n_px),
        iterations,
    })
}

/// A frame started from the closed form (shape fixed): rigid LM, then everything.
fn fit_frame_from_scratch(
    rig: &LandmarkRig,
    shape: &[f64],
    t: &LandmarkTargets,
    o: &FitOptions,
    iterations: usize,
) -> Result<FrameFit> {
    let neutral = FaceCodes {
        shape: shape.to_vec(),
        ..FaceCodes::zeros(rig)
    };
    let cam = initial_camera(rig, &neutral, t)?;
    let mut states = [FrameState::neutral(rig, cam)];
    let mut sh = shape.to_vec();
    let n0 = lm(rig, &[t], o, &mut sh, &mut states, false, false, 8)?;
    let n1 = lm(rig, &[t], o, &mut sh, &mut states, false, true, iterations)?;
    let [state] = states;
    finish(rig, t, o, shape, state, n0 + n1)
}

/// Fits one frame with a fixed shape. With `init` (the previous frame's state) the fit is
/// warm-started, and redone from the closed form if it ends above `restart_rms_px`.
pub fn fit_frame(
    rig: &LandmarkRig,
    shape: &[f64],
    t: &LandmarkTargets,
    init: Option<&FrameState>,
    o: &FitOptions,
) -> Result<FrameFit> {
    o.validate()?;
    check_shape(rig, shape)?;
    let Some(init) = init else {
        return fit_frame_from_scratch(rig, shape, t, o, o.photo_iterations);
    };
    check_state(rig, init)?;
    let mut states = [init.clone()];
    let mut sh = shape.to_vec();
    let warm = match lm(
        rig,
        &[t],
        o,
        &mut sh,
        &mut states,
        false,
        true,
        o.frame_iterations,
    ) {
        Ok(n) => {
            let [state] = states;
            Some(finish(rig, t, o, shape, state, n)?)
        }
        // A warm start the new landmarks put behind the camera: start over.
        Err(TrackError::Numerical { .. }) => None,
        Err(e) => return Err(e),
    };
    match warm {
        Some(w) if w.rms_px <= o.restart_rms_px => Ok(w),
        other => {
            let fresh = fit_frame_from_scratch(rig, shape, t, o, o.photo_iterations)?;
            Ok(match other {
                Some(w) if w.rms_px <= fresh.rms_px => w,
                _ => fresh,
            })
        }
    }
}

fn check_state(rig: &LandmarkRig, s: &FrameState) -> Result<()> {
    let finite = s.expression.iter().all(|x| x.is_finite())
        && s.jaw.iter().chain(&s.eyes).all(|x| x.is_finite())
        && s.camera.rotation.iter().flatten().all(|x| x.is_finite())
        && s.camera.translation.iter().all(|x| x.is_finite());
    if s.expression.len() != rig.n_exp || !finite {
        return Err(input(
            "start state",
            format!(
                "{} expression values (the rig takes {}), finite: {finite}",
                s.expression.len(),
                rig.n_exp
            ),
        ));
    }
    Ok(())
}

fn check_shape(rig: &LandmarkRig, shape: &[f64]) -> Result<()> {
    if shape.len() != rig.n_shape {
        return Err(input(
            "shape code",
            format!("{} values, the rig takes {}", shape.len(), rig.n_shape),
        ));
    }
    if let Some(i) = shape.iter().position(|x| !x.is_finite()) {
        return Err(input("shape code", format!("value {i} is not finite")));
    }
    Ok(())
}

/// Fits a shape shared by several frames jointly with their per-frame unknowns, starting from
/// `states` (e.g. fits with a fixed shape). Returns the shape and the refined states.
pub fn fit_shared_shape(
    rig: &LandmarkRig,
    targets: &[&LandmarkTargets],
    shape: &[f64],
    states: &[FrameState],
    o: &FitOptions,
) -> Result<(Vec<f64>, Vec<FrameState>)> {
    o.validate()?;
    check_shape(rig, shape)?;
    if targets.is_empty() || targets.len() != states.len() {
        return Err(input(
            "shared shape fit",
            format!(
                "{} target frames and {} start states (need as many, at least 1)",
                targets.len(),
                states.len()
            ),
        ));
    }
    for s in states {
        check_state(rig, s)?;
    }
    let mut sh = shape.to_vec();
    let mut st = states.to_vec();
    lm(
        rig,
        targets,
        o,
        &mut sh,
        &mut st,
        true,
        true,
        o.photo_iterations,
    )?;
    Ok((sh, st))
}

/// Fits a photo: shape, expression, jaw, eyes and camera from the closed-form start.
pub fn fit_photo(rig: &LandmarkRig, t: &LandmarkTargets, o: &FitOptions) -> Result<PhotoFit> {
    o.validate()?;
    let zero = vec![0.0; rig.n_shape];
    let start = fit_frame_from_scratch(rig, &zero, t, o, o.frame_iterations)?;
    let mut shape = zero;
    let mut states = [start.state];
    let n = lm(
        rig,
        &[t],
        o,
        &mut shape,
        &mut states,
        true,
        true,
        o.photo_iterations,
    )?;
    let [state] = states;
    let frame = finish(rig, t, o, &shape, state, start.iterations + n)?;
    Ok(PhotoFit { shape, frame })
}

/// A video's fit: one shape, per-frame states (`None` where the frame had no targets).
#[derive(Debug, Clone, PartialEq)]
pub struct SequenceFit {
    pub shape: Vec<f64>,
    pub frames: Vec<Option<FrameFit>>,
    /// Indices of the frames the shape was solved on.
    pub keyframes: Vec<usize>,
}

/// Evenly spread picks among the frames that have targets.
fn pick_keyframes(present: &[usize], k: usize) -> Vec<usize> {
    if present.len() <= k {
        return present.to_vec();
    }
    let mut out: Vec<usize> = (0..k)
        .map(|i| present[((i as f64 + 0.5) * present.len() as f64 / k as f64) as usize])
        .collect();
    out.dedup();
    out
}

/// Fits a video: the shape on keyframes, then every frame in order with warm starts.
/// `on_frame(i)` is called after each frame (for progress).
pub fn fit_sequence(
    rig: &LandmarkRig,
    targets: &[Option<LandmarkTargets>],
    o: &FitOptions,
    mut on_frame: impl FnMut(usize),
) -> Result<SequenceFit> {
    o.validate()?;
    if targets.is_empty() {
        return Err(input("video", "no frames"));
    }
    let present: Vec<usize> = (0..targets.len())
        .filter(|&i| targets[i].is_some())
        .collect();
    if present.is_empty() {
        return Err(TrackError::NoFace {
            name: "any frame of the video".into(),
        });
    }
    let keyframes = pick_keyframes(&present, o.keyframes);
    let zero = vec![0.0; rig.n_shape];
    let key_targets: Vec<&LandmarkTargets> = keyframes
        .iter()
        .filter_map(|&i| targets[i].as_ref())
        .collect();
    let starts: Vec<FrameState> = key_targets
        .par_iter()
        .map(|t| fit_frame_from_scratch(rig, &zero, t, o, o.frame_iterations).map(|f| f.state))
        .collect::<Result<_>>()?;
    let (shape, key_states) = fit_shared_shape(rig, &key_targets, &zero, &starts, o)?;
    // The keyframes' joint states fit the solved shape; a frame started from scratch with that
    // shape can settle in a poor minimum (a shape fitted to several views of a real face is far
    // from the mean face the closed-form start assumes). So the first frame starts from its
    // nearest keyframe's state, and a frame whose warm start ends poorly is retried from there.
    let nearest_key = |i: usize| -> &FrameState {
        let j = (0..keyframes.len())
            .min_by_key(|&j| keyframes[j].abs_diff(i))
            .unwrap_or(0);
        &key_states[j]
    };
    let mut frames = Vec::with_capacity(targets.len());
    let mut prev: Option<FrameState> = None;
    for (i, t) in targets.iter().enumerate() {
        let fit = match t {
            Some(t) => {
                let key = nearest_key(i);
                let mut f = fit_frame(rig, &shape, t, Some(prev.as_ref().unwrap_or(key)), o)?;
                if f.rms_px > o.restart_rms_px && prev.is_some() {
                    let g = fit_frame(rig, &shape, t, Some(key), o)?;
                    if g.rms_px < f.rms_px {
                        f = g;
                    }
                }
                prev = Some(f.state.clone());
                Some(f)
            }
            None => None,
        };
        frames.push(fit);
        on_frame(i);
    }
    Ok(SequenceFit {
        shape,
        frames,
        keyframes,
    })
}

/// The rig's 70 landmarks projected to 512-crop pixels (`None` behind the camera).
pub fn reproject(
    rig: &LandmarkRig,
    shape: &[f64],
    state: &FrameState,
) -> Result<Vec<Option<[f64; 2]>>> {
    let pts = rig.landmarks(&state.codes(shape))?;
    Ok(pts.iter().map(|p| state.camera.project(p)).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use gagavatar_flame::synthesize;

    fn rig() -> LandmarkRig {
        LandmarkRig::new(&synthesize(0), 20, 10).unwrap()
    }

    fn state(rig: &LandmarkRig) -> FrameState {
        let mut cam = CameraPose::frontal(9.2);
        cam.retract(&[0.1, -0.3, 0.05], &[0.1, -0.05, 0.2]);
        FrameState {
            expression: (0..rig.n_exp)
                .map(|i| 0.3 * ((i as f64) * 1.3).sin())
                .collect(),
            jaw: [0.2, 0.03, -0.02],
            eyes: [0.1, -0.2, 0.01, 0.12, -0.18, -0.02],
            camera: cam,
        }
    }

    fn targets(rig: &LandmarkRig, shape: &[f64], s: &FrameState) -> LandmarkTargets {
        let px = reproject(rig, shape, s).unwrap();
        let mut pts = [[0.0; 2]; N_LANDMARKS];
        for k in 0..N_LANDMARKS {
            let p = px[k].unwrap();
            // Offsets so no residual is exactly zero (and the Huber kinks are away).
            pts[k] = [
                p[0] + 0.7 * ((k as f64) * 0.9).sin(),
                p[1] - 0.5 * ((k as f64) * 0.4).cos(),
            ];
        }
        LandmarkTargets::new(pts, LandmarkWeights::default().per_landmark()).unwrap()
    }

    /// Every column of the frame Jacobian (shape, expression, jaw, eyes, rotation step,
    /// translation; data and prior rows) against f64 central differences of the residuals.
    #[test]
    fn frame_jacobian_matches_finite_differences() {
        // Step 1e-6 on unknowns of size ~1 gives truncation ~1e-12 and rounding ~1e-10 on
        // residuals of size ~100.
        const TOL: f64 = 2e-6;
        let rig = rig();
        let shape: Vec<f64> = (0..rig.n_shape)
            .map(|i| 0.2 * ((i as f64) * 0.7).cos())
            .collect();
        let s0 = state(&rig);
        let t = targets(&rig, &shape, &s0);
        let mut o = FitOptions {
            huber_px: None,
            ..FitOptions::default()
        };
        // Put the jaw and one eye component beyond their ranges so the hinge rows are active.
        o.jaw_opening_range = (-0.05, 0.15);
        o.eye_range = 0.15;
        let l = Layout::new(&rig, true, true);
        let base = frame_residuals(&rig, &t, &o, &shape, &s0, Some(l)).unwrap();
        let m = base.r.len();
        let n = l.n();
        let dense = base.dense_jacobian(n);
        assert_eq!(dense.len(), m * n);
        let h = 1e-6;
        for col in 0..n {
            let eval = |sign: f64| {
                let mut sh = shape.clone();
                let mut st = s0.clone();
                if col < l.n_shape {
                    sh[col] += sign * h;
                } else {
                    let mut step = vec![0.0; l.n_frame()];
                    step[col - l.n_shape] = sign * h;
                    apply_frame_step(&mut st, &l, &step);
                }
                frame_residuals(&rig, &t, &o, &sh, &st, None).unwrap().r
            };
            let (rp, rm) = (eval(1.0), eval(-1.0));
            for row in 0..m {
                let fd = (rp[row] - rm[row]) / (2.0 * h);
                let an = dense[row * n + col];
                assert!(
                    (fd - an).abs() <= TOL * (1.0 + an.abs()),
                    "row {row} col {col}: finite difference {fd}, analytic {an}"
                );
            }
        }
    }

    /// The Huber reweighting keeps the gradient J^T r equal to half the robust cost's gradient.
    #[test]
    fn huber_gradient_matches_finite_differences() {
        const TOL: f64 = 1e-5;
        let rig = rig();
        let shape = vec![0.0; rig.n_shape];
        let s0 = state(&rig);
        let mut t = targets(&rig, &shape, &s0);
        // Three far outliers (beyond the 8 px threshold).
        t.points[30][0] += 40.0;
        t.points[5][1] -= 25.0;
        t.points[60][0] += 15.0;
        let o = FitOptions::default();
        let l = Layout::new(&rig, false, true);
        let base = frame_residuals(&rig, &t, &o, &shape, &s0, Some(l)).unwrap();
        let n = l.n();
        let h = 1e-6;
        let dense = base.dense_jacobian(n);
        for col in 0..n {
            let grad: f64 = (0..base.r.len())
                .map(|r| dense[r * n + col] * base.r[r])
                .sum();
            let cost = |sign: f64| {
                let mut st = s0.clone();
                let mut step = vec![0.0; n];
                step[col] = sign * h;
                apply_frame_step(&mut st, &l, &step);
                frame_residuals(&rig, &t, &o, &shape, &st, None)
                    .unwrap()
                    .cost
            };
            let fd = (cost(1.0) - cost(-1.0)) / (2.0 * h) / 2.0;
            assert!(
                (fd - grad).abs() <= TOL * (1.0 + grad.abs()),
                "col {col}: finite difference {fd}, J^T r {grad}"
            );
        }
    }

    /// The Schur-complement step equals the dense solve of the full damped system.
    #[test]
    fn schur_step_equals_the_dense_solve() {
        let rig = rig();
        let shape: Vec<f64> = (0..rig.n_shape).map(|i| 0.1 * (i as f64).sin()).collect();
        let s0 = state(&rig);
        let mut s1 = s0.clone();
        s1.camera.retract(&[0.0, 0.4, 0.0], &[0.05, 0.0, 0.1]);
        let ts = [targets(&rig, &shape, &s0), targets(&rig, &shape, &s1)];
        let o = FitOptions::default();
        let l = Layout::new(&rig, true, true);
        let (ns, nf) = (l.n_shape, l.n_frame());
        let sys: Vec<FrameSystem> = ts
            .iter()
            .zip([&s0, &s1])
            .map(|(t, s)| frame_system(&rig, t, &o, &shape, s, &l).unwrap())
            .collect();
        let mu = 1e-3;
        let (ds, dfs) = damped_step(&sys, ns, nf, &shape, o.shape_prior, mu).unwrap();
        // Dense: unknowns [shape, frame 0, frame 1].
        let n = ns + 2 * nf;
        let mut a = vec![0.0; n * n];
        let mut g = vec![0.0; n];
        for i in 0..ns {
            a[i * n + i] += o.shape_prior;
            g[i] += o.shape_prior * shape[i];
        }
        for (f, s) in sys.iter().enumerate() {
            let off = ns + f * nf;
            for i in 0..ns {
                for j in 0..ns {
                    a[i * n + j] += s.c[i * ns + j];
                }
                g[i] += s.gs[i];
            }
            for i in 0..nf {
                for j in 0..nf {
                    a[(off + i) * n + off + j] += s.a[i * nf + j];
                }
                for j in 0..ns {
                    a[(off + i) * n + j] += s.b[i * ns + j];
                    a[j * n + off + i] += s.b[i * ns + j];
                }
                g[off + i] += s.g[i];
            }
        }
        // The same damping, block by block (it only touches diagonals).
        for i in 0..n {
            let d = a[i * n + i];
            a[i * n + i] = d + mu * d.max(1e-9) + 1e-12;
        }
        assert!(cholesky(&mut a, n));
        let mut x: Vec<f64> = g.iter().map(|v| -v).collect();
        cholesky_solve(&a, n, &mut x);
        let want: Vec<f64> = ds.iter().chain(&dfs[0]).chain(&dfs[1]).copied().collect();
        for i in 0..n {
            assert!(
                (x[i] - want[i]).abs() <= 1e-7 * (1.0 + x[i].abs()),
                "unknown {i}: dense {}, Schur {}",
                x[i],
                want[i]
            );
        }
    }
}
