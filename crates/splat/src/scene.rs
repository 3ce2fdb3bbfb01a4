//! Gaussian scenes on disk: a safetensors file with `means` [N,3], `features` [N,C],
//! `opacities` [N,1], `scales` [N,3], `rotations` [N,4], or a 3DGS `.ply`.
//!
//! A standard 3DGS `.ply` stores activated-before-use values: opacity as a logit, log scales, SH
//! DC colour and quaternions that 3DGS normalises. Files written by gagavatar carry
//! `comment gagavatar` and the raw feature channels `feat_0..`; their quaternions are the
//! release's unnormalised ones and are kept as they are.

use crate::error::{Result, SplatError};
use candle_core::{Device, Tensor};
use gagavatar_formats::tensor::RawData;
use gagavatar_formats::FormatError;
use std::path::Path;

/// Zeroth-order spherical-harmonic constant used by 3DGS to store colours.
const SH_C0: f64 = 0.282_094_791_773_878_14;
const PLY_MARKER: &str = "comment gagavatar";

/// Gaussians in host memory, row-major, activated (what [`crate::splat`] takes).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct GaussianScene {
    pub means: Vec<f32>,
    pub features: Vec<f32>,
    pub channels: usize,
    pub opacities: Vec<f32>,
    pub scales: Vec<f32>,
    pub rotations: Vec<f32>,
}

/// A file-level error (unreadable, not PLY / safetensors); its message already names the file.
fn file_err(path: &Path, e: FormatError) -> SplatError {
    match e {
        FormatError::Io { err, .. } => SplatError::Io {
            path: path.display().to_string(),
            err,
        },
        other => SplatError::Scene {
            path: path.display().to_string(),
            msg: other.detail(),
        },
    }
}

fn scene_err(path: &Path, msg: impl Into<String>) -> SplatError {
    SplatError::Scene {
        path: path.display().to_string(),
        msg: msg.into(),
    }
}

impl GaussianScene {
    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacities.is_empty()
    }

    /// Checks that every array agrees with `N` and `C`.
    pub fn validate(&self) -> std::result::Result<(), String> {
        let n = self.len();
        let checks = [
            ("means", self.means.len(), n * 3),
            ("features", self.features.len(), n * self.channels),
            ("scales", self.scales.len(), n * 3),
            ("rotations", self.rotations.len(), n * 4),
        ];
        for (name, got, want) in checks {
            if got != want {
                return Err(format!("{name} has {got} values, expected {want}"));
            }
        }
        if self.channels == 0 {
            return Err("features need at least one channel".into());
        }
        Ok(())
    }

    /// Reads a `.safetensors` or `.ply` scene, chosen by extension.
    pub fn load(path: &Path) -> Result<Self> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        let scene = match ext.as_str() {
            "ply" => Self::load_ply(path)?,
            "safetensors" => Self::load_safetensors(path)?,
            _ => {
                return Err(scene_err(
                    path,
                    "unknown extension: expected .safetensors or .ply",
                ))
            }
        };
        scene.validate().map_err(|m| scene_err(path, m))?;
        Ok(scene)
    }

    pub fn load_safetensors(path: &Path) -> Result<Self> {
        let tensors = gagavatar_formats::safetensors::read_safetensors(path)
            .map_err(|e| file_err(path, e))?
            .tensors;
        let get = |name: &str, k: Option<usize>| -> Result<(Vec<f32>, usize, usize)> {
            let t = tensors
                .get(name)
                .ok_or_else(|| scene_err(path, format!("missing tensor `{name}`")))?;
            let dims = &t.shape;
            let ok = dims.len() == 2 && k.is_none_or(|k| dims[1] == k);
            if !ok {
                let want = k.map_or("[N, C]".to_string(), |k| format!("[N, {k}]"));
                return Err(scene_err(
                    path,
                    format!("tensor `{name}` has shape {dims:?}, expected {want}"),
                ));
            }
            let RawData::Float(v) = &t.data else {
                return Err(scene_err(
                    path,
                    format!("tensor `{name}` is {}, expected floats", t.file_dtype),
                ));
            };
            Ok((v.clone(), dims[0], dims[1]))
        };
        let (means, n, _) = get("means", Some(3))?;
        let (features, nf, channels) = get("features", None)?;
        let (opacities, no, _) = get("opacities", Some(1))?;
        let (scales, ns, _) = get("scales", Some(3))?;
        let (rotations, nr, _) = get("rotations", Some(4))?;
        if [nf, no, ns, nr].iter().any(|&m| m != n) {
            return Err(scene_err(
                path,
                format!("tensors disagree on N: means {n}, features {nf}, opacities {no}, scales {ns}, rotations {nr}"),
            ));
        }
        Ok(Self {
            means,
            features,
            channels,
            opacities,
            scales,
            rotations,
        })
    }

    /// Tensors `[N,3]`, `[N,C]`, `[N,1]`, `[N,3]`, `[N,4]` on `device`.
    pub fn to_tensors(&self, device: &Device) -> Result<[Tensor; 5]> {
        let n = self.len();
        Ok([
            Tensor::from_slice(&self.means, (n, 3), device)?,
            Tensor::from_slice(&self.features, (n, self.channels), device)?,
            Tensor::from_slice(&self.opacities, (n, 1), device)?,
            Tensor::from_slice(&self.scales, (n, 3), device)?,
            Tensor::from_slice(&self.rotations, (n, 4), device)?,
        ])
    }

    pub fn load_ply(path: &Path) -> Result<Self> {
        let ply = gagavatar_formats::ply::read_ply(path).map_err(|e| file_err(path, e))?;
        let col = |name: &str| ply.column(name);
        let need = |name: &str| {
            col(name).ok_or_else(|| scene_err(path, format!("missing vertex property `{name}`")))
        };
        let n = ply.rows;
        let ours = ply.comments.iter().any(|c| c == PLY_MARKER);
        let xyz = [need("x")?, need("y")?, need("z")?];
        let op = need("opacity")?;
        let sc = [need("scale_0")?, need("scale_1")?, need("scale_2")?];
        let rot = [
            need("rot_0")?,
            need("rot_1")?,
            need("rot_2")?,
            need("rot_3")?,
        ];
        let mut feat_cols = Vec::new();
        while let Some(c) = col(&format!("feat_{}", feat_cols.len())) {
            feat_cols.push(c);
        }
        let dc_cols = if feat_cols.is_empty() {
            vec![need("f_dc_0")?, need("f_dc_1")?, need("f_dc_2")?]
        } else {
            Vec::new()
        };
        let channels = if feat_cols.is_empty() {
            3
        } else {
            feat_cols.len()
        };
        let mut s = Self {
            channels,
            ..Default::default()
        };
        for r in 0..n {
            let v = |c: usize| ply.values[r * ply.names.len() + c];
            s.means.extend(xyz.iter().map(|&c| v(c) as f32));
            s.opacities.push((1.0 / (1.0 + (-v(op)).exp())) as f32);
            s.scales.extend(sc.iter().map(|&c| v(c).exp() as f32));
            let q: Vec<f64> = rot.iter().map(|&c| v(c)).collect();
            let norm = if ours {
                1.0
            } else {
                q.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-12)
            };
            s.rotations.extend(q.iter().map(|x| (x / norm) as f32));
            if feat_cols.is_empty() {
                s.features
                    .extend(dc_cols.iter().map(|&c| (0.5 + SH_C0 * v(c)) as f32));
            } else {
                s.features.extend(feat_cols.iter().map(|&c| v(c) as f32));
            }
        }
        for (i, x) in s
            .means
            .iter()
            .chain(&s.features)
            .chain(&s.opacities)
            .chain(&s.scales)
            .chain(&s.rotations)
            .enumerate()
        {
            if !x.is_finite() {
                return Err(scene_err(
                    path,
                    format!("non-finite value at flat index {i}"),
                ));
            }
        }
        Ok(s)
    }

    /// Writes a binary little-endian 3DGS `.ply` (readable by common 3DGS viewers) with the raw
    /// feature channels as extra `feat_i` properties; atomic (temp file + rename).
    pub fn save_ply(&self, path: &Path) -> Result<()> {
        self.validate().map_err(|m| scene_err(path, m))?;
        let n = self.len();
        let mut props: Vec<String> = [
            "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        props.push("opacity".into());
        props.extend((0..3).map(|i| format!("scale_{i}")));
        props.extend((0..4).map(|i| format!("rot_{i}")));
        props.extend((0..self.channels).map(|i| format!("feat_{i}")));
        let mut values: Vec<f32> = Vec::with_capacity(n * props.len());
        let c = self.channels;
        for i in 0..n {
            values.extend_from_slice(&self.means[i * 3..i * 3 + 3]);
            values.extend_from_slice(&[0.0, 0.0, 0.0]);
            for k in 0..3 {
                let colour = if k < c { self.features[i * c + k] } else { 0.0 };
                values.push(((colour as f64 - 0.5) / SH_C0) as f32);
            }
            let o = (self.opacities[i] as f64).clamp(1e-7, 1.0 - 1e-7);
            values.push((o / (1.0 - o)).ln() as f32);
            values.extend(
                self.scales[i * 3..i * 3 + 3]
                    .iter()
                    .map(|s| s.max(1e-30).ln()),
            );
            values.extend_from_slice(&self.rotations[i * 4..i * 4 + 4]);
            values.extend_from_slice(&self.features[i * c..(i + 1) * c]);
        }
        let names: Vec<&str> = props.iter().map(String::as_str).collect();
        let marker = PLY_MARKER.trim_start_matches("comment ");
        gagavatar_formats::ply::write_ply(path, &[marker], &names, &values)
            .map_err(|e| file_err(path, e))
    }
}

impl GaussianScene {
    /// The same Gaussians with unit quaternions and matching scales: each covariance
    /// `M M^T` (`M = R(q) diag(s)`, the release's unnormalised-quaternion matrix of spec §7) is
    /// eigendecomposed into a proper rotation and its axis lengths. Viewers that normalise
    /// quaternions (every 3DGS viewer) then draw exactly the covariances this crate splats.
    pub fn with_unit_quaternions(&self) -> Self {
        let mut out = self.clone();
        for i in 0..self.len() {
            let q: [f64; 4] = std::array::from_fn(|k| self.rotations[4 * i + k] as f64);
            let s: [f64; 3] = std::array::from_fn(|k| self.scales[3 * i + k] as f64);
            let (q, s) = unit_quaternion_form(q, s);
            for k in 0..4 {
                out.rotations[4 * i + k] = q[k] as f32;
            }
            for k in 0..3 {
                out.scales[3 * i + k] = s[k] as f32;
            }
        }
        out
    }
}

/// Covariance `M M^T` with `M = R(q) diag(s)` and the unnormalised quaternion matrix.
pub fn covariance(q: [f64; 4], s: [f64; 3]) -> [[f64; 3]; 3] {
    let r = crate::project::quat_to_mat(q);
    let m: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|k| r[i][k] * s[k]));
    std::array::from_fn(|i| std::array::from_fn(|k| (0..3).map(|j| m[i][j] * m[k][j]).sum()))
}

/// `(unit quaternion, scales)` with the same covariance as the unnormalised `(q, s)`.
pub fn unit_quaternion_form(q: [f64; 4], s: [f64; 3]) -> ([f64; 4], [f64; 3]) {
    let (vals, mut vecs) = symmetric_eigen(covariance(q, s));
    // Columns of `vecs` are the axes; a reflection is not a rotation, so flip one axis.
    let det = vecs[0][0] * (vecs[1][1] * vecs[2][2] - vecs[1][2] * vecs[2][1])
        - vecs[0][1] * (vecs[1][0] * vecs[2][2] - vecs[1][2] * vecs[2][0])
        + vecs[0][2] * (vecs[1][0] * vecs[2][1] - vecs[1][1] * vecs[2][0]);
    if det < 0.0 {
        for row in vecs.iter_mut() {
            row[2] = -row[2];
        }
    }
    let scales = vals.map(|l| l.max(0.0).sqrt());
    (matrix_to_quaternion(&vecs), scales)
}

/// Cyclic Jacobi on a symmetric 3x3: eigenvalues and eigenvectors (as columns).
fn symmetric_eigen(mut a: [[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _sweep in 0..32 {
        let off = a[0][1].abs() + a[0][2].abs() + a[1][2].abs();
        let scale = a[0][0].abs() + a[1][1].abs() + a[2][2].abs();
        if off <= 1e-18 * scale || off == 0.0 {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let sn = t * c;
            // A <- J^T A J with the rotation J in the (p, q) plane.
            for k in 0..3 {
                let (akp, akq) = (a[k][p], a[k][q]);
                a[k][p] = c * akp - sn * akq;
                a[k][q] = sn * akp + c * akq;
            }
            for k in 0..3 {
                let (apk, aqk) = (a[p][k], a[q][k]);
                a[p][k] = c * apk - sn * aqk;
                a[q][k] = sn * apk + c * aqk;
            }
            for row in v.iter_mut() {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - sn * vq;
                row[q] = sn * vp + c * vq;
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2]], v)
}

/// Unit quaternion (r, x, y, z) of a rotation matrix, in the convention of `quat_to_mat`.
fn matrix_to_quaternion(m: &[[f64; 3]; 3]) -> [f64; 4] {
    let tr = m[0][0] + m[1][1] + m[2][2];
    // Divide by the largest of the four candidates for stability.
    let q = if tr > 0.0 {
        let s = 2.0 * (tr + 1.0).sqrt();
        [
            s / 4.0,
            (m[2][1] - m[1][2]) / s,
            (m[0][2] - m[2][0]) / s,
            (m[1][0] - m[0][1]) / s,
        ]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = 2.0 * (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt();
        [
            (m[2][1] - m[1][2]) / s,
            s / 4.0,
            (m[0][1] + m[1][0]) / s,
            (m[0][2] + m[2][0]) / s,
        ]
    } else if m[1][1] > m[2][2] {
        let s = 2.0 * (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt();
        [
            (m[0][2] - m[2][0]) / s,
            (m[0][1] + m[1][0]) / s,
            s / 4.0,
            (m[1][2] + m[2][1]) / s,
        ]
    } else {
        let s = 2.0 * (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt();
        [
            (m[1][0] - m[0][1]) / s,
            (m[0][2] + m[2][0]) / s,
            (m[1][2] + m[2][1]) / s,
            s / 4.0,
        ]
    };
    let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
    q.map(|x| x / n)
}

#[cfg(test)]
mod unit_quaternion_tests {
    use super::*;
    use crate::testscene::Rng;

    /// Relative to the covariance's largest entry: f64 Jacobi converges to ~1e-15.
    const COV_REL_TOL: f64 = 1e-10;

    #[test]
    fn unit_form_keeps_every_covariance() {
        let mut rng = Rng::new(5);
        for case in 0..2000 {
            let mut q: [f64; 4] = std::array::from_fn(|_| rng.normal());
            // Unnormalised on purpose, tiny and large norms too.
            let norm = [1e-3, 0.3, 1.0, 2.5][case % 4];
            q.iter_mut().for_each(|x| *x *= norm);
            let mut s: [f64; 3] = std::array::from_fn(|_| (rng.normal() * 1.5).exp() * 0.01);
            if case % 7 == 0 {
                s[case % 3] = 0.0;
            }
            if case % 11 == 0 {
                s = [0.02, 0.02, 0.02];
            }
            let (u, s2) = unit_quaternion_form(q, s);
            let n: f64 = u.iter().map(|x| x * x).sum::<f64>().sqrt();
            assert!((n - 1.0).abs() < 1e-12, "case {case}: |q| = {n}");
            let want = covariance(q, s);
            let got = covariance(u, s2);
            let big = want.iter().flatten().fold(1e-300f64, |m, x| m.max(x.abs()));
            for i in 0..3 {
                for k in 0..3 {
                    assert!(
                        (want[i][k] - got[i][k]).abs() <= COV_REL_TOL * big,
                        "case {case} [{i}][{k}] expected {} got {}",
                        want[i][k],
                        got[i][k]
                    );
                }
            }
        }
    }
}
