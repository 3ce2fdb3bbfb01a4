//! Gaussian scenes on disk: a safetensors file with `means` [N,3], `features` [N,C],
//! `opacities` [N,1], `scales` [N,3], `rotations` [N,4], or a 3DGS `.ply`.
//!
//! A standard 3DGS `.ply` stores activated-before-use values: opacity as a logit, log scales, SH
//! DC colour and quaternions that 3DGS normalises. Files written by gagavatar carry
//! `comment gagavatar` and the raw feature channels `feat_0..`; their quaternions are the
//! release's unnormalised ones and are kept as they are.

use crate::error::{Result, SplatError};
use candle_core::{DType, Device, Tensor};
use std::path::Path;

/// The atomic-output mechanism lives in `gagavatar-formats`; re-exported for existing callers.
pub use gagavatar_formats::atomic::{replace_dir, temp_sibling, write_via_temp};

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
        let tensors = candle_core::safetensors::load(path, &Device::Cpu)
            .map_err(|e| scene_err(path, e.to_string()))?;
        let get = |name: &str, k: Option<usize>| -> Result<(Vec<f32>, usize, usize)> {
            let t = tensors
                .get(name)
                .ok_or_else(|| scene_err(path, format!("missing tensor `{name}`")))?;
            let dims = t.dims();
            let ok = dims.len() == 2 && k.is_none_or(|k| dims[1] == k);
            if !ok {
                let want = k.map_or("[N, C]".to_string(), |k| format!("[N, {k}]"));
                return Err(scene_err(
                    path,
                    format!("tensor `{name}` has shape {dims:?}, expected {want}"),
                ));
            }
            let v = t
                .to_dtype(DType::F32)
                .and_then(|t| t.flatten_all())
                .and_then(|t| t.to_vec1::<f32>())
                .map_err(|e| scene_err(path, format!("tensor `{name}`: {e}")))?;
            Ok((v, dims[0], dims[1]))
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
        let bytes = std::fs::read(path).map_err(|source| SplatError::Io {
            path: path.display().to_string(),
            source,
        })?;
        let ply = ply::parse(&bytes).map_err(|m| scene_err(path, m))?;
        let col = |name: &str| ply.names.iter().position(|p| p == name);
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
        let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
        header.push_str(PLY_MARKER);
        header.push('\n');
        header.push_str(&format!("element vertex {n}\n"));
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
        for p in &props {
            header.push_str(&format!("property float {p}\n"));
        }
        header.push_str("end_header\n");
        let mut buf = header.into_bytes();
        buf.reserve(n * props.len() * 4);
        let c = self.channels;
        for i in 0..n {
            let mut row: Vec<f32> = Vec::with_capacity(props.len());
            row.extend_from_slice(&self.means[i * 3..i * 3 + 3]);
            row.extend_from_slice(&[0.0, 0.0, 0.0]);
            for k in 0..3 {
                let colour = if k < c { self.features[i * c + k] } else { 0.0 };
                row.push(((colour as f64 - 0.5) / SH_C0) as f32);
            }
            let o = (self.opacities[i] as f64).clamp(1e-7, 1.0 - 1e-7);
            row.push((o / (1.0 - o)).ln() as f32);
            row.extend(
                self.scales[i * 3..i * 3 + 3]
                    .iter()
                    .map(|s| s.max(1e-30).ln()),
            );
            row.extend_from_slice(&self.rotations[i * 4..i * 4 + 4]);
            row.extend_from_slice(&self.features[i * c..(i + 1) * c]);
            for v in row {
                buf.extend_from_slice(&v.to_le_bytes());
            }
        }
        write_atomic(path, &buf)
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

/// Writes `bytes` to a temp file beside `path`, then renames it over `path`, so a crash never
/// leaves a half-written file.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let io = |source| SplatError::Io {
        path: path.display().to_string(),
        source,
    };
    write_via_temp(path, |tmp| std::fs::write(tmp, bytes).map_err(io), io)
}

mod ply {
    //! Minimal PLY reader: one `vertex` element of scalar properties (other elements must come
    //! after it), ascii or binary little endian.

    pub struct Ply {
        pub names: Vec<String>,
        pub comments: Vec<String>,
        pub rows: usize,
        pub values: Vec<f64>,
    }

    #[derive(Clone, Copy)]
    enum Ty {
        I8,
        U8,
        I16,
        U16,
        I32,
        U32,
        F32,
        F64,
    }

    impl Ty {
        fn parse(s: &str) -> Option<Self> {
            Some(match s {
                "char" | "int8" => Ty::I8,
                "uchar" | "uint8" => Ty::U8,
                "short" | "int16" => Ty::I16,
                "ushort" | "uint16" => Ty::U16,
                "int" | "int32" => Ty::I32,
                "uint" | "uint32" => Ty::U32,
                "float" | "float32" => Ty::F32,
                "double" | "float64" => Ty::F64,
                _ => return None,
            })
        }
        fn size(self) -> usize {
            match self {
                Ty::I8 | Ty::U8 => 1,
                Ty::I16 | Ty::U16 => 2,
                Ty::I32 | Ty::U32 | Ty::F32 => 4,
                Ty::F64 => 8,
            }
        }
        fn read(self, b: &[u8]) -> f64 {
            match self {
                Ty::I8 => b[0] as i8 as f64,
                Ty::U8 => b[0] as f64,
                Ty::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
                Ty::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
                Ty::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
                Ty::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
                Ty::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
                Ty::F64 => f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]),
            }
        }
    }

    /// Upper bound on the vertex count, so a corrupt header cannot ask for absurd memory.
    const MAX_ROWS: usize = 100_000_000;

    pub fn parse(bytes: &[u8]) -> Result<Ply, String> {
        let end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .ok_or("not a PLY file: no end_header")?;
        let header = std::str::from_utf8(&bytes[..end]).map_err(|_| "PLY header is not text")?;
        let mut lines = header.lines();
        if lines.next().map(str::trim) != Some("ply") {
            return Err("not a PLY file: missing `ply` magic".into());
        }
        let mut binary = None;
        let mut rows = None;
        let mut in_vertex = false;
        let mut names = Vec::new();
        let mut types = Vec::new();
        let mut comments = Vec::new();
        for line in lines {
            let parts: Vec<&str> = line.split_whitespace().collect();
            match parts.as_slice() {
                ["format", "binary_little_endian", _] => binary = Some(true),
                ["format", "ascii", _] => binary = Some(false),
                ["format", f, ..] => return Err(format!("unsupported PLY format `{f}`")),
                ["comment", ..] => comments.push(line.trim().to_string()),
                ["element", "vertex", n] => {
                    if rows.is_some() {
                        return Err("more than one vertex element".into());
                    }
                    let n: usize = n.parse().map_err(|_| format!("bad vertex count `{n}`"))?;
                    if n > MAX_ROWS {
                        return Err(format!("vertex count {n} exceeds {MAX_ROWS}"));
                    }
                    rows = Some(n);
                    in_vertex = true;
                }
                ["element", ..] => {
                    if rows.is_none() {
                        return Err("elements before `vertex` are not supported".into());
                    }
                    in_vertex = false;
                }
                ["property", "list", ..] if in_vertex => {
                    return Err("list properties on vertices are not supported".into())
                }
                ["property", ty, name] if in_vertex => {
                    let t = Ty::parse(ty).ok_or_else(|| format!("unknown property type `{ty}`"))?;
                    types.push(t);
                    names.push(name.to_string());
                }
                _ => {}
            }
        }
        let binary = binary.ok_or("PLY header has no format line")?;
        let rows = rows.ok_or("PLY has no vertex element")?;
        let body = &bytes[end + 11..];
        let mut values = Vec::with_capacity(rows * names.len());
        if binary {
            let stride: usize = types.iter().map(|t| t.size()).sum();
            if body.len() < rows * stride {
                return Err(format!(
                    "PLY body is truncated: {} bytes for {rows} vertices of {stride} bytes",
                    body.len()
                ));
            }
            for r in 0..rows {
                let mut off = r * stride;
                for t in &types {
                    values.push(t.read(&body[off..off + t.size()]));
                    off += t.size();
                }
            }
        } else {
            let text = std::str::from_utf8(body).map_err(|_| "ascii PLY body is not text")?;
            let mut it = text.split_whitespace();
            for _ in 0..rows * names.len() {
                let tok = it.next().ok_or("ascii PLY body is truncated")?;
                values.push(tok.parse().map_err(|_| format!("bad number `{tok}`"))?);
            }
        }
        Ok(Ply {
            names,
            comments,
            rows,
            values,
        })
    }
}
