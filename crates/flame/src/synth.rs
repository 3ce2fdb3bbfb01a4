//! A deterministic synthetic FLAME-format asset: the release's exact layout and shapes (5023
//! vertices, 9976 faces, 300 + 100 blendshapes, 36 pose correctives, 5 joints, 51 / 79x17 / 70
//! landmarks) on a plausible head, so tests, the demo and synthetic training exercise every code
//! path of the licensed asset without it.
//!
//! Mesh layout (vertex and face counts are forced by the release, so the topology is chosen to
//! hit them exactly):
//! * Head: a latitude/longitude grid of 47 rings x 101 columns plus two poles (top of the skull,
//!   bottom of the neck), warped so rows and columns are denser over the face. Three holes are
//!   cut: a mouth slit (one row of 15 quads between the lips) and two 4x4-quad eye sockets
//!   (dropping their 3x3 interior vertices). 4747 + 2 - 18 = 4731 vertices, 2*4747 - 30 - 64 =
//!   9400 faces.
//! * Two eyeballs, each a closed 9-ring x 16-column sphere with poles front and back (pupil = the
//!   front pole): 146 vertices, 288 faces each.
//!
//! Totals 4731 + 292 = 5023 vertices and 9400 + 576 = 9976 faces. Every edge is shared by exactly
//! two faces except the three hole rims (32 + 16 + 16 edges); no vertex is unreferenced.
//!
//! Vertex order: head, then the eyeball at +x (the subject's left, joint 3), then the one at -x
//! (joint 4). Coordinates follow FLAME: metres, +y up, the face looks along +z, head centred near
//! the origin, about 0.18 wide before the release's x5.

use std::f64::consts::PI;

use crate::asset::{BasisLayout, FlameAsset, NUM_JOINTS, POSE_BASIS};
use crate::embedding::{LandmarkEmbedding, DYNAMIC_ROWS};

pub const SYNTH_VERTICES: usize = 5023;
pub const SYNTH_FACES: usize = 9976;
const N_SHAPE: usize = 300;
const N_EXP: usize = 100;

const N_LAT: usize = 47;
const N_LON: usize = 101;
const EYE_LAT: usize = 9;
const EYE_LON: usize = 16;
/// Mouth quads are columns -MOUTH_HALF..=MOUTH_HALF (15) of one row.
const MOUTH_HALF: i64 = 7;
/// Extra density of rows around the face's height (0 = uniform, < 1).
const LAT_WARP: f64 = 0.4;
/// Extra density of columns around the front (0 = uniform, < 1).
const LON_WARP: f64 = 0.45;
const EYE_RADIUS: f64 = 0.0115;
/// Heights (t = polar angle / pi) and azimuth of facial features.
const T_EYE: f64 = 0.455;
const PHI_EYE: f64 = 0.33;
const T_MOUTH: f64 = 0.615;

/// SplitMix64: tiny, well-mixed and fully specified, so a seed means the same asset everywhere.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    fn normal(&mut self) -> f64 {
        let u1 = self.uniform().max(1e-300);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (2.0 * PI * u2).cos()
    }
    fn unit3(&mut self) -> [f64; 3] {
        loop {
            let v = [self.normal(), self.normal(), self.normal()];
            let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            if n > 1e-6 {
                return v.map(|x| x / n);
            }
        }
    }
}

fn smoothstep(e0: f64, e1: f64, x: f64) -> f64 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

fn gauss(x: f64, s: f64) -> f64 {
    (-(x / s) * (x / s)).exp()
}

/// Row parameter s in [0, 1] -> height parameter t.
fn t_of_s(s: f64) -> f64 {
    s - LAT_WARP * (2.0 * PI * (s - 0.5)).sin() / (2.0 * PI)
}

/// Column parameter u -> azimuth phi (0 = front, +x side positive).
fn phi_of_u(u: f64) -> f64 {
    2.0 * PI * u - LON_WARP * (2.0 * PI * u).sin()
}

fn invert(f: impl Fn(f64) -> f64, target: f64, mut lo: f64, mut hi: f64) -> f64 {
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if f(mid) < target {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

fn ring_t(i: usize) -> f64 {
    t_of_s((i + 1) as f64 / (N_LAT + 1) as f64)
}

/// Azimuth of vertex column j, in (-pi, pi] so that left/right features are symmetric in phi.
fn col_phi(j: i64) -> f64 {
    let u = (j as f64 - 0.5) / N_LON as f64;
    phi_of_u(u - u.round())
}

/// Continuous grid coordinates (ring, column) of a surface parameter (t, phi).
fn grid_of(t: f64, phi: f64) -> (f64, f64) {
    let s = invert(t_of_s, t, 0.0, 1.0);
    let u = invert(phi_of_u, phi, -0.5, 0.5);
    (s * (N_LAT + 1) as f64 - 1.0, u * N_LON as f64 + 0.5)
}

/// Outward horizontal direction at azimuth phi.
fn horizontal(phi: f64) -> [f64; 3] {
    [phi.sin(), 0.0, phi.cos()]
}

/// The rest head surface at height parameter t (0 top .. 1 neck bottom) and azimuth phi.
fn surface(t: f64, phi: f64) -> [f64; 3] {
    let theta = PI * t;
    let y = 0.105 * theta.cos() - 0.075 * smoothstep(0.6, 1.0, t);
    let h = if t < 0.5 {
        theta.sin()
    } else {
        let neck = 1.0 - 0.38 * smoothstep(0.52, 0.8, t);
        neck * (1.0 - 0.85 * smoothstep(0.92, 1.0, t))
    };
    let aphi = phi.abs();
    let bump = 0.024 * gauss(t - 0.53, 0.045) * gauss(phi, 0.13) // nose
        + 0.010 * gauss(t - 0.47, 0.05) * gauss(phi, 0.08) // bridge
        + 0.012 * gauss(t - 0.69, 0.04) * gauss(phi, 0.35) // chin
        + 0.006 * gauss(t - 0.40, 0.03) * gauss(phi, 0.45) // brow
        + 0.005 * gauss(t - T_MOUTH, 0.03) * gauss(phi, 0.3) // lips
        + 0.014 * gauss(t - 0.49, 0.06) * gauss(aphi - PI / 2.0, 0.12) // ears
        - 0.006 * gauss(t - T_EYE, 0.035) * gauss(aphi - PHI_EYE, 0.12); // eye hollows
    let d = horizontal(phi);
    [
        0.078 * h * d[0] + bump * d[0],
        y,
        0.090 * h * d[2] + bump * d[2],
    ]
}

/// A smooth random vector field: a few plane waves with random directions and phases.
struct Field {
    waves: Vec<([f64; 3], [f64; 3], f64)>,
}

impl Field {
    fn new(rng: &mut Rng, amplitude: f64, wavelength: f64) -> Self {
        let waves = (0..3)
            .map(|_| {
                let k = rng.unit3().map(|x| x * 2.0 * PI / wavelength);
                let a =
                    [rng.normal(), rng.normal(), rng.normal()].map(|x| x * amplitude / 3f64.sqrt());
                (k, a, rng.uniform() * 2.0 * PI)
            })
            .collect();
        Self { waves }
    }
    fn at(&self, p: [f64; 3]) -> [f64; 3] {
        let mut out = [0.0; 3];
        for (k, a, ph) in &self.waves {
            let c = (k[0] * p[0] + k[1] * p[1] + k[2] * p[2] + ph).cos();
            for d in 0..3 {
                out[d] += a[d] * c;
            }
        }
        out
    }
}

#[derive(Clone, Copy, PartialEq)]
enum Part {
    /// Ring, column, t, phi.
    Head(usize, usize, f64, f64),
    Eye(usize),
}

/// Which whole-face motions the synthetic blendshapes may contain.
///
/// The blendshapes are random smooth fields, so each one also moves the face as a whole a
/// little (turns, shifts and scales it). Real FLAME bases nearly do not: they are principal
/// components of registered scans after a rigid alignment. A landmark fit cannot tell a code
/// that turns the face from a camera that turns, so ground-truth tests of a tracker want the
/// real property; the default keeps the bases as drawn (the assets that tests, goldens and the
/// demo already use are unchanged).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BasisMotion {
    /// The fields as drawn.
    #[default]
    AsDrawn,
    /// Each basis minus its least-squares rigid motion (3 translations, 3 rotations) over the
    /// face region.
    RigidFree,
    /// As `RigidFree`, also without a uniform scale about the face's centre.
    SimilarityFree,
}

/// Builds the synthetic asset for a seed. Geometry and topology are fixed; the seed drives the
/// blendshapes and pose correctives.
pub fn synthesize(seed: u64) -> FlameAsset {
    synthesize_with(seed, BasisMotion::AsDrawn)
}

/// Number of whole-face motion modes removed by a [`BasisMotion`].
fn motion_modes(m: BasisMotion) -> usize {
    match m {
        BasisMotion::AsDrawn => 0,
        BasisMotion::RigidFree => 6,
        BasisMotion::SimilarityFree => 7,
    }
}

/// Mode `i` of the whole-face motions at point `p` (relative to the face centre): translations
/// x, y, z, infinitesimal rotations about x, y, z, then the uniform scale.
fn motion_mode(i: usize, p: [f64; 3]) -> [f64; 3] {
    match i {
        0..=2 => {
            let mut e = [0.0; 3];
            e[i] = 1.0;
            e
        }
        3 => [0.0, -p[2], p[1]],
        4 => [p[2], 0.0, -p[0]],
        5 => [-p[1], p[0], 0.0],
        _ => p,
    }
}

/// Removes from `d` (one blendshape, per vertex) the whole-face motion that best explains it
/// over the face (weights `w`), as that motion appears through the basis's own support `s` (1
/// where the basis may move a vertex): `d - s * M p`, with `p` minimising
/// `sum_v w_v |d_v - s_v M_v p|^2`.
// The elimination reads and writes two rows of one matrix by index.
#[allow(clippy::needless_range_loop)]
fn remove_motion(d: &mut [[f64; 3]], pts: &[[f64; 3]], w: &[f64], s: &[f64], modes: usize) {
    let mut a = [[0.0f64; 7]; 7];
    let mut b = [0.0f64; 7];
    for v in 0..d.len() {
        if w[v] == 0.0 || s[v] == 0.0 {
            continue;
        }
        let m: Vec<[f64; 3]> = (0..modes)
            .map(|i| motion_mode(i, pts[v]).map(|x| x * s[v]))
            .collect();
        for i in 0..modes {
            b[i] += w[v] * (0..3).map(|c| m[i][c] * d[v][c]).sum::<f64>();
            for j in 0..modes {
                a[i][j] += w[v] * (0..3).map(|c| m[i][c] * m[j][c]).sum::<f64>();
            }
        }
    }
    // Gaussian elimination with partial pivoting on the small normal equations (positive
    // definite: the face region spans all modes).
    let n = modes;
    for col in 0..n {
        let piv = (col..n)
            .max_by(|&x, &y| a[x][col].abs().total_cmp(&a[y][col].abs()))
            .unwrap_or(col);
        a.swap(col, piv);
        b.swap(col, piv);
        if a[col][col].abs() < 1e-300 {
            return;
        }
        for r in col + 1..n {
            let f = a[r][col] / a[col][col];
            for c in col..n {
                a[r][c] -= f * a[col][c];
            }
            b[r] -= f * b[col];
        }
    }
    let mut p = [0.0f64; 7];
    for r in (0..n).rev() {
        let acc: f64 = (r + 1..n).map(|c| a[r][c] * p[c]).sum();
        p[r] = (b[r] - acc) / a[r][r];
    }
    for v in 0..d.len() {
        if s[v] == 0.0 {
            continue;
        }
        for i in 0..n {
            let m = motion_mode(i, pts[v]);
            for c in 0..3 {
                d[v][c] -= s[v] * p[i] * m[c];
            }
        }
    }
}

/// [`synthesize`] with a choice of the blendshapes' whole-face motion. `AsDrawn` gives exactly
/// [`synthesize`]'s asset.
pub fn synthesize_with(seed: u64, motion: BasisMotion) -> FlameAsset {
    let mut rng = Rng(seed ^ 0x5EED_F1A3_E000_0000);

    // --- head grid and holes
    let r_eye = (0..N_LAT)
        .min_by(|&a, &b| {
            (ring_t(a) - T_EYE)
                .abs()
                .total_cmp(&(ring_t(b) - T_EYE).abs())
        })
        .unwrap_or(0);
    let r_mouth = (0..N_LAT)
        .min_by(|&a, &b| {
            (ring_t(a) - T_MOUTH)
                .abs()
                .total_cmp(&(ring_t(b) - T_MOUTH).abs())
        })
        .unwrap_or(0);
    let c_eye = (0..N_LON as i64 / 2)
        .min_by(|&a, &b| {
            (col_phi(a) - PHI_EYE)
                .abs()
                .total_cmp(&(col_phi(b) - PHI_EYE).abs())
        })
        .unwrap_or(0);
    let eye_cols = [c_eye, 1 - c_eye]; // +x (left) then -x (right)
    let wrap = |j: i64| j.rem_euclid(N_LON as i64) as usize;
    let quad_removed = |i: usize, j: usize| -> bool {
        let ii = i as i64;
        if ii == r_mouth as i64 && (-MOUTH_HALF..=MOUTH_HALF).any(|m| wrap(m) == j) {
            return true;
        }
        eye_cols.iter().any(|&c| {
            (r_eye as i64 - 2..=r_eye as i64 + 1).contains(&ii)
                && (c - 2..=c + 1).any(|m| wrap(m) == j)
        })
    };
    let vertex_removed = |i: usize, j: usize| -> bool {
        eye_cols.iter().any(|&c| {
            (r_eye as i64 - 1..=r_eye as i64 + 1).contains(&(i as i64))
                && (c - 1..=c + 1).any(|m| wrap(m) == j)
        })
    };

    let mut verts: Vec<[f64; 3]> = Vec::with_capacity(SYNTH_VERTICES);
    let mut parts: Vec<Part> = Vec::with_capacity(SYNTH_VERTICES);
    let mut grid_index = vec![u32::MAX; N_LAT * N_LON];
    let top = 0u32;
    verts.push(surface(0.0, 0.0));
    parts.push(Part::Head(0, 0, 0.0, 0.0));
    for i in 0..N_LAT {
        for j in 0..N_LON {
            if vertex_removed(i, j) {
                continue;
            }
            let (t, phi) = (ring_t(i), col_phi(j as i64));
            grid_index[i * N_LON + j] = verts.len() as u32;
            verts.push(surface(t, phi));
            parts.push(Part::Head(i, j, t, phi));
        }
    }
    let bottom = verts.len() as u32;
    verts.push(surface(1.0, 0.0));
    parts.push(Part::Head(N_LAT - 1, 0, 1.0, 0.0));

    let mut faces: Vec<[u32; 3]> = Vec::with_capacity(SYNTH_FACES);
    let g = |i: usize, j: usize| grid_index[i * N_LON + j % N_LON];
    for j in 0..N_LON {
        faces.push([top, g(0, j), g(0, j + 1)]);
    }
    let mut quad_faces = vec![None; (N_LAT - 1) * N_LON];
    for i in 0..N_LAT - 1 {
        for j in 0..N_LON {
            if quad_removed(i, j) {
                continue;
            }
            let (a, b, c, d) = (g(i, j), g(i, j + 1), g(i + 1, j), g(i + 1, j + 1));
            quad_faces[i * N_LON + j] = Some(faces.len() as u32);
            faces.push([a, c, b]);
            faces.push([b, c, d]);
        }
    }
    for j in 0..N_LON {
        faces.push([g(N_LAT - 1, j), bottom, g(N_LAT - 1, j + 1)]);
    }

    // --- eyeballs
    // Each socket is centred on ring r_eye and its vertex column; the eyeball sits 3/4 of its
    // radius behind that surface point so its front shows through the hole.
    let eye_centres: Vec<[f64; 3]> = eye_cols
        .iter()
        .map(|&c| {
            let phi = col_phi(c);
            let p = surface(ring_t(r_eye), phi);
            let n = horizontal(phi);
            [0, 1, 2].map(|d| p[d] - 0.75 * EYE_RADIUS * n[d])
        })
        .collect();
    let mut pupil_faces = [0u32; 2];
    for (e, centre) in eye_centres.iter().enumerate() {
        let base = verts.len() as u32;
        let at = |th: f64, ps: f64| -> [f64; 3] {
            [
                centre[0] + EYE_RADIUS * th.sin() * ps.cos(),
                centre[1] + EYE_RADIUS * th.sin() * ps.sin(),
                centre[2] + EYE_RADIUS * th.cos(),
            ]
        };
        verts.push(at(0.0, 0.0));
        parts.push(Part::Eye(e));
        for k in 0..EYE_LAT {
            for m in 0..EYE_LON {
                let th = PI * (k + 1) as f64 / (EYE_LAT + 1) as f64;
                verts.push(at(th, 2.0 * PI * m as f64 / EYE_LON as f64));
                parts.push(Part::Eye(e));
            }
        }
        verts.push(at(PI, 0.0));
        parts.push(Part::Eye(e));
        let front = base;
        let back = base + 1 + (EYE_LAT * EYE_LON) as u32;
        let q = |k: usize, m: usize| base + 1 + (k * EYE_LON + m % EYE_LON) as u32;
        pupil_faces[e] = faces.len() as u32;
        for m in 0..EYE_LON {
            faces.push([front, q(0, m), q(0, m + 1)]);
        }
        for k in 0..EYE_LAT - 1 {
            for m in 0..EYE_LON {
                let (a, b, c, d) = (q(k, m), q(k, m + 1), q(k + 1, m), q(k + 1, m + 1));
                faces.push([a, c, b]);
                faces.push([b, c, d]);
            }
        }
        for m in 0..EYE_LON {
            faces.push([q(EYE_LAT - 1, m), back, q(EYE_LAT - 1, m + 1)]);
        }
    }
    debug_assert_eq!(verts.len(), SYNTH_VERTICES);
    debug_assert_eq!(faces.len(), SYNTH_FACES);
    let nv = verts.len();

    // --- skinning weights: global (lower neck), neck (head), jaw (below the mouth), eyes
    let t_upper_lip = ring_t(r_mouth);
    let t_lower_lip = ring_t(r_mouth + 1);
    let in_mouth_cols = |j: usize| (-MOUTH_HALF..=MOUTH_HALF + 1).any(|m| wrap(m) == j);
    let mut weights = vec![0f32; nv * NUM_JOINTS];
    let mut jaw_w = vec![0f64; nv];
    for (v, part) in parts.iter().enumerate() {
        let w: [f64; NUM_JOINTS] = match *part {
            Part::Eye(e) => {
                let mut w = [0.0; NUM_JOINTS];
                w[3 + e] = 1.0;
                w
            }
            Part::Head(i, j, t, phi) => {
                let rows = if in_mouth_cols(j) && (i == r_mouth || i == r_mouth + 1) {
                    if i > r_mouth {
                        1.0
                    } else {
                        0.0
                    }
                } else {
                    smoothstep(t_upper_lip - 0.01, t_lower_lip + 0.04, t)
                };
                let lateral = 1.0 - smoothstep(0.9, 1.5, phi.abs());
                let throat = 1.0 - smoothstep(0.70, 0.80, t);
                let jaw = rows * lateral * throat;
                let glob = smoothstep(0.80, 0.92, t);
                jaw_w[v] = jaw;
                [
                    (1.0 - jaw) * glob,
                    (1.0 - jaw) * (1.0 - glob),
                    jaw,
                    0.0,
                    0.0,
                ]
            }
        };
        for (k, x) in w.iter().enumerate() {
            weights[v * NUM_JOINTS + k] = *x as f32;
        }
    }

    // --- joint regressor
    let mut j_regressor = vec![0f32; NUM_JOINTS * nv];
    let ring_of = |target: f64| {
        (0..N_LAT)
            .min_by(|&a, &b| {
                (ring_t(a) - target)
                    .abs()
                    .total_cmp(&(ring_t(b) - target).abs())
            })
            .unwrap_or(0)
    };
    let mut set_rows = |joint: usize, members: Vec<usize>| {
        let w = 1.0 / members.len().max(1) as f32;
        for v in members {
            j_regressor[joint * nv + v] = w;
        }
    };
    let ring_members = |ring: usize| -> Vec<usize> {
        (0..N_LON)
            .map(|j| grid_index[ring * N_LON + j])
            .filter(|&x| x != u32::MAX)
            .map(|x| x as usize)
            .collect()
    };
    set_rows(0, ring_members(ring_of(0.93)));
    set_rows(1, ring_members(ring_of(0.78)));
    let hinge_ring = ring_of(0.56);
    let hinge_cols: Vec<i64> = [1.45f64, -1.45]
        .iter()
        .map(|&phi| {
            let (_, gj) = grid_of(0.56, phi);
            gj.round() as i64
        })
        .collect();
    let jaw_members: Vec<usize> = hinge_cols
        .iter()
        .flat_map(|&c| (c - 1..=c + 1).map(move |m| m.rem_euclid(N_LON as i64) as usize))
        .map(|j| grid_index[hinge_ring * N_LON + j] as usize)
        .collect();
    set_rows(2, jaw_members);
    for e in 0..2 {
        set_rows(
            3 + e,
            (0..nv).filter(|&v| parts[v] == Part::Eye(e)).collect(),
        );
    }

    // --- blendshapes: smooth fields; eyeballs move rigidly with identity, not with expression
    let k_total = N_SHAPE + N_EXP;
    let mut shapedirs = vec![0f32; nv * 3 * k_total];
    let face_mask = |part: &Part| -> f64 {
        match *part {
            Part::Eye(_) => 0.0,
            Part::Head(_, _, t, phi) => {
                (1.0 - smoothstep(0.7, 1.1, phi.abs()))
                    * smoothstep(0.33, 0.40, t)
                    * (1.0 - smoothstep(0.70, 0.76, t))
            }
        }
    };
    // Whole-face motion removal: weighted over the face region (what landmarks and a camera
    // see), about the region's weighted centre.
    let modes = motion_modes(motion);
    let region: Vec<f64> = parts.iter().map(face_mask).collect();
    let centre: [f64; 3] = {
        let sw: f64 = region.iter().sum();
        std::array::from_fn(|c| {
            (0..nv).map(|v| region[v] * verts[v][c]).sum::<f64>() / sw.max(1e-12)
        })
    };
    // Eyeballs move with identity as wholes: their points are the eye centres.
    let rel: Vec<[f64; 3]> = (0..nv)
        .map(|v| {
            let p = match parts[v] {
                Part::Eye(e) => eye_centres[e],
                Part::Head(..) => verts[v],
            };
            std::array::from_fn(|c| p[c] - centre[c])
        })
        .collect();
    let mut field_d = vec![[0.0f64; 3]; nv];
    for k in 0..k_total {
        let field = if k < N_SHAPE {
            Field::new(
                &mut rng,
                0.005 / (1.0 + k as f64 / 8.0).sqrt(),
                0.25 / (1.0 + k as f64 / 60.0),
            )
        } else {
            let e = (k - N_SHAPE) as f64;
            Field::new(
                &mut rng,
                0.004 / (1.0 + e / 6.0).sqrt(),
                0.12 / (1.0 + e / 40.0),
            )
        };
        for v in 0..nv {
            let d = match parts[v] {
                Part::Eye(e) if k < N_SHAPE => field.at(eye_centres[e]),
                Part::Eye(_) => [0.0; 3],
                Part::Head(..) if k < N_SHAPE => field.at(verts[v]),
                Part::Head(..) => field.at(verts[v]).map(|x| x * face_mask(&parts[v])),
            };
            field_d[v] = d;
        }
        if modes > 0 {
            // A basis's motion can only appear where the basis moves vertices: everywhere for
            // identity, through the face mask for expressions.
            let support: Vec<f64> = if k < N_SHAPE {
                vec![1.0; nv]
            } else {
                region.clone()
            };
            remove_motion(&mut field_d, &rel, &region, &support, modes);
        }
        for (v, d) in field_d.iter().enumerate() {
            for c in 0..3 {
                shapedirs[(v * 3 + c) * k_total + k] = d[c] as f32;
            }
        }
    }

    // --- pose correctives: neck bulges, jaw-line and eyelid adjustments
    let mut posedirs = vec![0f32; nv * 3 * POSE_BASIS];
    for p in 0..POSE_BASIS {
        let joint = 1 + p / 9;
        let (amp, wl) = match joint {
            1 => (0.008, 0.15),
            2 => (0.006, 0.10),
            _ => (0.002, 0.05),
        };
        let field = Field::new(&mut rng, amp, wl);
        for v in 0..nv {
            let mask = match parts[v] {
                Part::Eye(_) => 0.0,
                Part::Head(_, _, t, phi) => match joint {
                    1 => smoothstep(0.62, 0.72, t) * (1.0 - smoothstep(0.88, 0.95, t)),
                    2 => 4.0 * jaw_w[v] * (1.0 - jaw_w[v]) + 0.3 * jaw_w[v],
                    _ => {
                        let side = if joint == 3 { 1.0 } else { -1.0 };
                        gauss(t - ring_t(r_eye), 0.03)
                            * gauss(phi - side * col_phi(eye_cols[joint - 3]), 0.1)
                    }
                },
            };
            if mask == 0.0 {
                continue;
            }
            let d = field.at(verts[v]);
            for c in 0..3 {
                posedirs[(v * 3 + c) * POSE_BASIS + p] = (d[c] * mask) as f32;
            }
        }
    }

    // --- landmarks
    let embed = |gi: f64, gj: f64| -> (u32, [f32; 3]) {
        let i = gi.floor();
        let j = gj.floor();
        let (fb, fa) = (gi - i, gj - j);
        let ii = (i as i64).clamp(0, N_LAT as i64 - 2) as usize;
        let jj = wrap(j as i64);
        // Landmark sites are chosen off the holes; fall back to the nearest row above if not.
        let first = quad_faces[ii * N_LON + jj]
            .or_else(|| quad_faces[ii.saturating_sub(1) * N_LON + jj])
            .unwrap_or(0);
        if fa + fb <= 1.0 {
            (first, [(1.0 - fa - fb) as f32, fb as f32, fa as f32])
        } else {
            (
                first + 1,
                [(1.0 - fb) as f32, (1.0 - fa) as f32, (fa + fb - 1.0) as f32],
            )
        }
    };
    let at_tphi = |t: f64, phi: f64| {
        let (gi, gj) = grid_of(t, phi);
        embed(gi, gj)
    };
    let re = r_eye as f64;
    let rm = r_mouth as f64;
    let mut stat: Vec<(u32, [f32; 3])> = Vec::with_capacity(51);
    // Brows (iBUG 17..26): subject's right (-x) outer to inner, then left inner to outer.
    for phi in [
        -0.62f64, -0.5, -0.36, -0.24, -0.1, 0.1, 0.24, 0.36, 0.5, 0.62,
    ] {
        stat.push(at_tphi(0.40 - 0.02 * gauss(phi.abs() - 0.36, 0.2), phi));
    }
    // Nose bridge to tip (27..30), nostrils (31..35).
    for t in [0.44, 0.475, 0.51, 0.535] {
        stat.push(at_tphi(t, 0.0));
    }
    for phi in [-0.14, -0.07, 0.0, 0.07, 0.14] {
        stat.push(at_tphi(0.575, phi));
    }
    // Eyes (36..47) on the socket rims: right eye from its outer corner clockwise, then left
    // from its inner corner. Socket quads span rows re-2..re+2, columns c-2..c+2.
    let cr = eye_cols[1] as f64;
    let cl = eye_cols[0] as f64;
    for (di, dj) in [
        (0.0, -2.5),
        (-2.5, -0.7),
        (-2.5, 0.7),
        (0.0, 2.5),
        (2.5, 0.7),
        (2.5, -0.7),
    ] {
        stat.push(embed(re + di, cr + dj));
    }
    for (di, dj) in [
        (0.0, -2.5),
        (-2.5, -0.7),
        (-2.5, 0.7),
        (0.0, 2.5),
        (2.5, 0.7),
        (2.5, -0.7),
    ] {
        stat.push(embed(re + di, cl + dj));
    }
    // Mouth outer (48..59) and inner (60..67) around the slit (rows rm..rm+1, cols -7..8).
    let mh = MOUTH_HALF as f64;
    for (di, dj) in [
        (0.5, -mh - 0.5),
        (-1.2, -5.0),
        (-1.5, -2.0),
        (-1.4, 0.5),
        (-1.5, 3.0),
        (-1.2, 6.0),
        (0.5, mh + 1.5),
        (2.2, 6.0),
        (2.6, 3.0),
        (2.7, 0.5),
        (2.6, -2.0),
        (2.2, -5.0),
        (0.5, -mh - 0.2),
        (-0.2, -3.0),
        (-0.2, 0.5),
        (-0.2, 4.0),
        (0.5, mh + 1.2),
        (1.2, 4.0),
        (1.2, 0.5),
        (1.2, -3.0),
    ] {
        stat.push(embed(rm + di, dj));
    }
    // Dynamic contour (iBUG 0..16): the jaw line, shifted toward the silhouette with yaw.
    let mut dynamic = Vec::with_capacity(DYNAMIC_ROWS * 17);
    for row in 0..DYNAMIC_ROWS {
        let yaw_deg = if row < 40 {
            row as f64
        } else {
            39.0 - row as f64
        };
        for k in 0..17 {
            let a = (k as f64 - 8.0) / 8.0;
            let phi = (1.38 * a - 0.6 * yaw_deg.to_radians()).clamp(-1.5, 1.5);
            dynamic.push(at_tphi(0.72 - 0.22 * a * a, phi));
        }
    }
    // The 70-point `_with_eye` set: iBUG 0..67 with the frontal (static) contour, then the
    // pupils: the front pole of each eyeball, right (-x, image-left) then left.
    let mut full: Vec<(u32, [f32; 3])> = dynamic[..17].to_vec();
    full.extend_from_slice(&stat);
    full.push((pupil_faces[1], [1.0, 0.0, 0.0]));
    full.push((pupil_faces[0], [1.0, 0.0, 0.0]));
    let split = |v: &[(u32, [f32; 3])]| -> (Vec<u32>, Vec<[f32; 3]>) { v.iter().copied().unzip() };
    let (static_faces, static_bary) = split(&stat);
    let (dynamic_faces, dynamic_bary) = split(&dynamic);
    let (full_faces, full_bary) = split(&full);

    let parents = [0, 0, 1, 1, 1];
    FlameAsset {
        n_vertices: nv,
        v_template: verts.iter().flatten().map(|&x| x as f32).collect(),
        faces,
        shapedirs,
        layout: BasisLayout {
            shape: N_SHAPE,
            expression: N_EXP,
        },
        posedirs,
        j_regressor,
        weights,
        // Real FLAME files store the root's parent as uint32 -1.
        kintree_table: vec![4294967295, 0, 1, 1, 1, 0, 1, 2, 3, 4],
        parents,
        landmarks: LandmarkEmbedding {
            static_faces,
            static_bary,
            dynamic_faces,
            dynamic_bary,
            dynamic_count: 17,
            full_faces,
            full_bary,
        },
    }
}
