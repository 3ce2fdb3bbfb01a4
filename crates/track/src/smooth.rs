//! Temporal smoothing of a video's per-frame fits, and filling frames without a face.
//!
//! * [`Smoothing::ReleaseEma`]: the release's `smoothed.pkl` (TRACKING.md section 5): a causal
//!   EMA `s_0 = x_0, s_i = a x_i + (1 - a) s_{i-1}` on the camera rotation as PyTorch3D 6D (its
//!   first two rows; Gram-Schmidt afterwards) and the translation with `a = 0.6`, and on the eye
//!   codes with `a = 0.7`; expression and jaw untouched. Its lag is `(1 - a) / a` frames.
//! * [`Smoothing::Offline`] (the default): a zero-lag two-sided smoother, the Whittaker
//!   penalised least squares `min sum w_i (x_i - y_i)^2 + lambda sum (x_{i-1} - 2 x_i +
//!   x_{i+1})^2` per channel (a pentadiagonal solve), on the camera rotation (as a rotation
//!   vector about a reference rotation), translation, eyes, and optionally expression and jaw.
//!   Its gain at frequency `w` (radians per frame) is `1 / (1 + 16 lambda sin^4(w / 2))`:
//!   `lambda = 2` halves the power at a period of 7.3 frames and passes slower motion almost
//!   untouched, with a steeper roll-off than the EMA's and no lag.
//!
//! Frames without a face never disappear: [`interpolate_states`] fills them (linear between
//! the nearest fitted frames, rotations along the geodesic, held before the first and after the
//! last), and the offline smoother gives them a tiny weight on that fill, so the curve through
//! a gap follows the neighbours' motion.

use crate::camera::{exp_so3, log_so3, matmul, rotation_from_6d, rotation_to_6d, transpose, Mat3};
use crate::error::{input, Result};
use crate::fit::FrameState;

/// The release's EMA coefficients.
pub const RELEASE_ALPHA_CAMERA: f64 = 0.6;
pub const RELEASE_ALPHA_EYES: f64 = 0.7;
/// Weight of a filled (faceless) frame's value in the offline smoother: enough to hold the
/// ends of a video still, small enough that observed neighbours decide the curve.
pub const MISSING_WEIGHT: f64 = 1e-3;

/// Whittaker smoothing strengths (0 leaves a group untouched).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OfflineSmoothing {
    pub camera: f64,
    pub eyes: f64,
    /// Expression and jaw. The release never smooths them; a light touch removes landmark
    /// jitter without flattening speech (lambda 0.5: half power at 5 frames, 5 Hz at 25 fps).
    pub expression: f64,
}

impl Default for OfflineSmoothing {
    fn default() -> Self {
        Self {
            camera: 2.0,
            eyes: 2.0,
            expression: 0.5,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Smoothing {
    /// No smoothing (`smoothed.pkl` equals `optim.pkl`, gaps filled).
    None,
    /// The release's causal EMA.
    ReleaseEma,
    /// Two-sided Whittaker smoothing (the default).
    Offline(OfflineSmoothing),
}

impl Default for Smoothing {
    fn default() -> Self {
        Smoothing::Offline(OfflineSmoothing::default())
    }
}

/// Whittaker smoother of one series with per-sample weights (`w_i >= 0`; at least two positive,
/// or the problem is not determined and the input comes back unchanged).
pub fn whittaker(y: &[f64], w: &[f64], lambda: f64) -> Result<Vec<f64>> {
    let n = y.len();
    if w.len() != n {
        return Err(input(
            "smoothing",
            format!("{n} values and {} weights", w.len()),
        ));
    }
    if !(lambda.is_finite() && lambda >= 0.0) {
        return Err(input(
            "smoothing",
            format!("lambda = {lambda}: must be finite and >= 0"),
        ));
    }
    if let Some(i) = (0..n).find(|&i| !(y[i].is_finite() && w[i].is_finite() && w[i] >= 0.0)) {
        return Err(input(
            "smoothing",
            format!(
                "sample {i}: value {} weight {} (finite, weight >= 0)",
                y[i], w[i]
            ),
        ));
    }
    if n < 3 || lambda == 0.0 || w.iter().filter(|&&x| x > 0.0).count() < 2 {
        return Ok(y.to_vec());
    }
    // Banded symmetric matrix A = W + lambda D^T D, bands 0..=2 (a[b][i] = A[i][i + b]).
    let mut a = [w.to_vec(), vec![0.0; n], vec![0.0; n]];
    let c = [1.0, -2.0, 1.0];
    for r in 0..n - 2 {
        for p in 0..3 {
            for q in p..3 {
                a[q - p][r + p] += lambda * c[p] * c[q];
            }
        }
    }
    // LDL^T of the pentadiagonal matrix, then two substitutions.
    let mut d = vec![0.0; n];
    let mut l1 = vec![0.0; n]; // L[i + 1][i]
    let mut l2 = vec![0.0; n]; // L[i + 2][i]
    for i in 0..n {
        let mut di = a[0][i];
        if i >= 1 {
            di -= l1[i - 1] * l1[i - 1] * d[i - 1];
        }
        if i >= 2 {
            di -= l2[i - 2] * l2[i - 2] * d[i - 2];
        }
        d[i] = di;
        if i + 1 < n {
            let mut v = a[1][i];
            if i >= 1 {
                v -= l1[i - 1] * l2[i - 1] * d[i - 1];
            }
            l1[i] = v / di;
        }
        if i + 2 < n {
            l2[i] = a[2][i] / di;
        }
    }
    let mut x: Vec<f64> = (0..n).map(|i| w[i] * y[i]).collect();
    for i in 0..n {
        if i >= 1 {
            x[i] -= l1[i - 1] * x[i - 1];
        }
        if i >= 2 {
            x[i] -= l2[i - 2] * x[i - 2];
        }
    }
    for i in 0..n {
        x[i] /= d[i];
    }
    for i in (0..n).rev() {
        if i + 1 < n {
            x[i] -= l1[i] * x[i + 1];
        }
        if i + 2 < n {
            x[i] -= l2[i] * x[i + 2];
        }
    }
    Ok(x)
}

/// The release's causal EMA of a series of vectors.
pub fn ema(series: &[Vec<f64>], alpha: f64) -> Vec<Vec<f64>> {
    let mut out: Vec<Vec<f64>> = Vec::with_capacity(series.len());
    for x in series {
        let s = match out.last() {
            None => x.clone(),
            Some(prev) => x
                .iter()
                .zip(prev)
                .map(|(a, b)| alpha * a + (1.0 - alpha) * b)
                .collect(),
        };
        out.push(s);
    }
    out
}

/// Fills frames without a fit: linear between the nearest fitted frames (rotation along the
/// geodesic), held before the first and after the last. `None` everywhere is an error.
pub fn interpolate_states(states: &[Option<FrameState>]) -> Result<Vec<FrameState>> {
    let known: Vec<usize> = (0..states.len()).filter(|&i| states[i].is_some()).collect();
    let (Some(&first), Some(&last)) = (known.first(), known.last()) else {
        return Err(input("interpolation", "no frame has a fit"));
    };
    let get = |i: usize| states[i].as_ref().expect("index from `known`");
    let mut out = Vec::with_capacity(states.len());
    let mut next_known = 0;
    for i in 0..states.len() {
        if let Some(s) = &states[i] {
            out.push(s.clone());
            continue;
        }
        if i < first {
            out.push(get(first).clone());
            continue;
        }
        if i > last {
            out.push(get(last).clone());
            continue;
        }
        while known[next_known] < i {
            next_known += 1;
        }
        let (b, a) = (known[next_known], known[next_known - 1]);
        let t = (i - a) as f64 / (b - a) as f64;
        out.push(lerp_state(get(a), get(b), t));
    }
    Ok(out)
}

fn lerp(a: f64, b: f64, t: f64) -> f64 {
    a + t * (b - a)
}

fn lerp_state(a: &FrameState, b: &FrameState, t: f64) -> FrameState {
    let rel = log_so3(&matmul(&transpose(&a.camera.rotation), &b.camera.rotation));
    let mut s = a.clone();
    s.camera.rotation = matmul(&a.camera.rotation, &exp_so3(&rel.map(|x| t * x)));
    for i in 0..3 {
        s.camera.translation[i] = lerp(a.camera.translation[i], b.camera.translation[i], t);
        s.jaw[i] = lerp(a.jaw[i], b.jaw[i], t);
    }
    for i in 0..6 {
        s.eyes[i] = lerp(a.eyes[i], b.eyes[i], t);
    }
    for (e, (x, y)) in s
        .expression
        .iter_mut()
        .zip(a.expression.iter().zip(&b.expression))
    {
        *e = lerp(*x, *y, t);
    }
    s
}

/// Smooths a filled sequence. `observed[i]` says whether frame i had a face (filled frames get
/// [`MISSING_WEIGHT`] in the offline smoother; the EMA runs over them like the rest).
pub fn smooth_states(
    states: &[FrameState],
    observed: &[bool],
    smoothing: &Smoothing,
) -> Result<Vec<FrameState>> {
    if states.len() != observed.len() {
        return Err(input(
            "smoothing",
            format!("{} frames and {} flags", states.len(), observed.len()),
        ));
    }
    match smoothing {
        Smoothing::None => Ok(states.to_vec()),
        Smoothing::ReleaseEma => Ok(release_ema(states)),
        Smoothing::Offline(o) => offline(states, observed, o),
    }
}

/// The release's `run_smoothing`: camera (6D rotation, translation) and eyes.
pub fn release_ema(states: &[FrameState]) -> Vec<FrameState> {
    let rot6: Vec<Vec<f64>> = states
        .iter()
        .map(|s| rotation_to_6d(&s.camera.rotation).to_vec())
        .collect();
    let trans: Vec<Vec<f64>> = states
        .iter()
        .map(|s| s.camera.translation.to_vec())
        .collect();
    let eyes: Vec<Vec<f64>> = states.iter().map(|s| s.eyes.to_vec()).collect();
    let rot6 = ema(&rot6, RELEASE_ALPHA_CAMERA);
    let trans = ema(&trans, RELEASE_ALPHA_CAMERA);
    let eyes = ema(&eyes, RELEASE_ALPHA_EYES);
    states
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let mut s = s.clone();
            let d: [f64; 6] = std::array::from_fn(|k| rot6[i][k]);
            // Averages of nearby rotations' rows never collapse; keep the raw one if they did.
            if let Some(r) = rotation_from_6d(&d) {
                s.camera.rotation = r;
            }
            s.camera.translation = [trans[i][0], trans[i][1], trans[i][2]];
            s.eyes = std::array::from_fn(|k| eyes[i][k]);
            s
        })
        .collect()
}

fn offline(
    states: &[FrameState],
    observed: &[bool],
    o: &OfflineSmoothing,
) -> Result<Vec<FrameState>> {
    let n = states.len();
    let w: Vec<f64> = observed
        .iter()
        .map(|&b| if b { 1.0 } else { MISSING_WEIGHT })
        .collect();
    let mut out = states.to_vec();
    let channel = |get: &dyn Fn(&FrameState) -> f64, lambda: f64| -> Result<Vec<f64>> {
        let y: Vec<f64> = states.iter().map(get).collect();
        whittaker(&y, &w, lambda)
    };
    if o.camera > 0.0 && n > 0 {
        // Rotation vectors about the middle frame's rotation: heads turn well under 180 degrees
        // from it, where the logarithm is smooth and unambiguous.
        let reference: Mat3 = states[n / 2].camera.rotation;
        let rt = transpose(&reference);
        let logs: Vec<[f64; 3]> = states
            .iter()
            .map(|s| log_so3(&matmul(&rt, &s.camera.rotation)))
            .collect();
        let mut sm = [vec![], vec![], vec![]];
        for (a, out_a) in sm.iter_mut().enumerate() {
            let y: Vec<f64> = logs.iter().map(|l| l[a]).collect();
            *out_a = whittaker(&y, &w, o.camera)?;
        }
        for a in 0..3 {
            let t = channel(&|s| s.camera.translation[a], o.camera)?;
            for i in 0..n {
                out[i].camera.translation[a] = t[i];
            }
        }
        for i in 0..n {
            let v = [sm[0][i], sm[1][i], sm[2][i]];
            out[i].camera.rotation = matmul(&reference, &exp_so3(&v));
        }
    }
    if o.eyes > 0.0 {
        for k in 0..6 {
            let e = channel(&|s| s.eyes[k], o.eyes)?;
            for i in 0..n {
                out[i].eyes[k] = e[i];
            }
        }
    }
    if o.expression > 0.0 {
        for k in 0..3 {
            let j = channel(&|s| s.jaw[k], o.expression)?;
            for i in 0..n {
                out[i].jaw[k] = j[i];
            }
        }
        let ne = states.first().map_or(0, |s| s.expression.len());
        for k in 0..ne {
            let e = channel(&|s| s.expression[k], o.expression)?;
            for i in 0..n {
                out[i].expression[k] = e[i];
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The banded solve against a dense solve of the same normal equations.
    #[test]
    fn whittaker_matches_the_dense_solution() {
        let n = 9;
        let y: Vec<f64> = (0..n).map(|i| ((i * i) as f64 * 0.37).sin()).collect();
        let w: Vec<f64> = (0..n)
            .map(|i| if i == 4 { 0.0 } else { 1.0 + 0.1 * i as f64 })
            .collect();
        let lambda = 3.0;
        let got = whittaker(&y, &w, lambda).unwrap();
        let mut a = vec![vec![0.0; n]; n];
        for i in 0..n {
            a[i][i] = w[i];
        }
        for r in 0..n - 2 {
            let c = [1.0, -2.0, 1.0];
            for p in 0..3 {
                for q in 0..3 {
                    a[r + p][r + q] += lambda * c[p] * c[q];
                }
            }
        }
        let mut b: Vec<f64> = (0..n).map(|i| w[i] * y[i]).collect();
        // Gaussian elimination (the matrix is SPD).
        for i in 0..n {
            for j in i + 1..n {
                let f = a[j][i] / a[i][i];
                for k in i..n {
                    a[j][k] -= f * a[i][k];
                }
                b[j] -= f * b[i];
            }
        }
        let mut x = vec![0.0; n];
        for i in (0..n).rev() {
            let s: f64 = (i + 1..n).map(|k| a[i][k] * x[k]).sum();
            x[i] = (b[i] - s) / a[i][i];
        }
        for i in 0..n {
            assert!(
                (x[i] - got[i]).abs() < 1e-12,
                "{i}: dense {}, banded {}",
                x[i],
                got[i]
            );
        }
    }

    #[test]
    fn whittaker_keeps_lines_and_rejects_bad_input() {
        // Second differences of a line are zero: it passes unchanged at any strength.
        let y: Vec<f64> = (0..20).map(|i| 0.5 * i as f64 - 3.0).collect();
        let got = whittaker(&y, &[1.0; 20], 1e4).unwrap();
        for (a, b) in y.iter().zip(&got) {
            assert!((a - b).abs() < 1e-8);
        }
        assert!(whittaker(&[1.0, f64::NAN, 2.0], &[1.0; 3], 1.0).is_err());
        assert!(whittaker(&[1.0, 2.0], &[1.0], 1.0).is_err());
        assert!(whittaker(&[1.0, 2.0, 3.0], &[1.0; 3], -1.0).is_err());
        assert!(whittaker(&[], &[], 1.0).unwrap().is_empty());
    }

    #[test]
    fn ema_is_the_release_recursion() {
        let s = ema(&[vec![1.0], vec![2.0], vec![4.0]], 0.6);
        assert_eq!(s[0], vec![1.0]);
        assert!((s[1][0] - 1.6).abs() < 1e-15);
        assert!((s[2][0] - (0.6 * 4.0 + 0.4 * 1.6)).abs() < 1e-15);
    }
}
