//! FLAME's 70 landmarks as a function of the codes, with analytic derivatives, in f64.
//!
//! The fit never needs the 5023-vertex mesh: each landmark is a barycentric mix of 3 vertices,
//! and with the global and neck rotations at zero (the release puts the head rotation in the
//! camera, TRACKING.md section 4) every joint's world rotation `G_j` is its own local rotation
//! (`G_0 = G_1 = I` exactly: Rodrigues of 0 is I with the release's epsilon too) and its world
//! position is its rest position `J_j`. Linear blend skinning of a vertex then reads
//! `sum_j w_vj (G_j (v_posed - J_j) + J_j)`, so a landmark `k` is
//!
//! `L_k = 5 sum_j [ G_j M_kj + W_kj (I - G_j) J_j ]`
//!
//! with `W_kj = sum_c b_c w_{v_c j}` and `M_kj = sum_c b_c w_{v_c j} v_posed(v_c)`, which is
//! linear in the shape code, the expression code and the 27 pose-corrective features
//! (`R_jaw - I`, `R_eye3 - I`, `R_eye4 - I`; the neck's 9 are zero). Those per-(landmark, joint)
//! bases are gathered once per asset: a few hundred vertices' rows instead of the whole model.

use gagavatar_flame::asset::{FlameAsset, NUM_JOINTS, POSE_BASIS};
use gagavatar_flame::FLAME_SCALE;

use crate::camera::{matvec, rodrigues_with_grad, Mat3, Vec3, IDENTITY};
use crate::error::{Result, TrackError};

/// Landmarks of the release's `_with_eye` embedding: iBUG 68 then the two pupils.
pub const N_LANDMARKS: usize = 70;
/// Shape components [`LandmarkRig::for_tracking`] fits.
pub const TRACKING_SHAPE_COMPONENTS: usize = 100;
/// Pose-corrective features that can be non-zero (jaw, eye, eye; the neck's are zero).
const N_POSE_FEAT: usize = 27;
/// Columns of `posedirs` where those features start (after the neck's 9).
const POSE_FEAT_OFFSET: usize = 9;
/// Joints the fit rotates: jaw, then the two eyes (FLAME joints 2, 3, 4).
pub const POSED_JOINTS: [usize; 3] = [2, 3, 4];

/// The non-rigid FLAME codes the fit estimates (the global pose is always zero).
#[derive(Debug, Clone, PartialEq)]
pub struct FaceCodes {
    /// `[n_shape]` of the rig.
    pub shape: Vec<f64>,
    /// `[n_exp]` of the rig.
    pub expression: Vec<f64>,
    /// Jaw axis-angle (`posecode[3..6]`).
    pub jaw: Vec3,
    /// Eye axis-angles: joint 3 then joint 4 (`eyecode`).
    pub eyes: [f64; 6],
}

impl FaceCodes {
    pub fn zeros(rig: &LandmarkRig) -> Self {
        Self {
            shape: vec![0.0; rig.n_shape],
            expression: vec![0.0; rig.n_exp],
            jaw: [0.0; 3],
            eyes: [0.0; 6],
        }
    }

    /// Axis-angle of posed joint `i` (0 jaw, 1 and 2 the eyes).
    pub fn joint_rotation(&self, i: usize) -> Vec3 {
        match i {
            0 => self.jaw,
            1 => [self.eyes[0], self.eyes[1], self.eyes[2]],
            _ => [self.eyes[3], self.eyes[4], self.eyes[5]],
        }
    }
}

/// One landmark's share of one joint.
#[derive(Debug, Clone)]
struct Block {
    joint: usize,
    /// `W_kj`
    weight: f64,
    template: Vec3,
    /// `[3][n_shape]`
    shape: Vec<f64>,
    /// `[3][n_exp]`
    exp: Vec<f64>,
    /// `[3][27]`
    pose: Vec<f64>,
}

/// Which derivative columns [`LandmarkRig::evaluate`] fills, in this order: shape (if asked),
/// expression, jaw (3), eyes (6).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RigColumns {
    pub shape: bool,
}

impl RigColumns {
    pub fn count(&self, rig: &LandmarkRig) -> usize {
        (if self.shape { rig.n_shape } else { 0 }) + rig.n_exp + 9
    }
}

/// Landmark positions (FLAME space, x5) and, when asked, their derivatives
/// `[landmark][xyz][column]`.
#[derive(Debug, Clone, Default)]
pub struct RigOutput {
    pub points: Vec<Vec3>,
    /// Row-major `[N_LANDMARKS * 3][n_cols]`; empty when no derivatives were asked.
    pub jacobian: Vec<f64>,
    pub n_cols: usize,
}

/// The 70 landmarks of a FLAME asset as a small, fast function of its codes.
#[derive(Debug, Clone)]
pub struct LandmarkRig {
    pub n_shape: usize,
    pub n_exp: usize,
    scale: f64,
    blocks: Vec<Block>,
    /// Blocks of landmark k: `block_start[k]..block_start[k + 1]`.
    block_start: Vec<usize>,
    /// Rest joints `[5]`, unscaled, and their shape / expression bases `[5][3][n]`.
    joint_template: [Vec3; NUM_JOINTS],
    joint_shape: Vec<f64>,
    joint_exp: Vec<f64>,
}

impl LandmarkRig {
    /// The rig for the first `n_shape` / `n_exp` components of `asset` (the release uses all
    /// 300 / 100). The asset must carry the 70-point `_with_eye` embedding.
    pub fn new(asset: &FlameAsset, n_shape: usize, n_exp: usize) -> Result<Self> {
        let lm = &asset.landmarks;
        if lm.full_faces.len() != N_LANDMARKS {
            return Err(TrackError::Input {
                what: "FLAME asset",
                reason: format!(
                    "its full-with-eye landmark embedding has {} points; tracking needs the \
                     release's {N_LANDMARKS} (iBUG 68 + 2 pupils)",
                    lm.full_faces.len()
                ),
            });
        }
        if n_shape > asset.layout.shape || n_exp > asset.layout.expression {
            return Err(TrackError::Input {
                what: "FLAME asset",
                reason: format!(
                    "has {} shape and {} expression components, {n_shape} and {n_exp} requested",
                    asset.layout.shape, asset.layout.expression
                ),
            });
        }
        let nv = asset.n_vertices;
        let k_file = asset.n_components();
        let exp_col = |e: usize| asset.layout.shape + e;
        let mut blocks = Vec::new();
        let mut block_start = vec![0];
        for (&face, bary) in lm.full_faces.iter().zip(&lm.full_bary) {
            let tri = asset.faces[face as usize];
            for joint in 0..NUM_JOINTS {
                let coef: Vec<(usize, f64)> = (0..3)
                    .map(|c| {
                        let v = tri[c] as usize;
                        (
                            v,
                            bary[c] as f64 * asset.weights[v * NUM_JOINTS + joint] as f64,
                        )
                    })
                    .filter(|&(_, w)| w != 0.0)
                    .collect();
                if coef.is_empty() {
                    continue;
                }
                let mut b = Block {
                    joint,
                    weight: coef.iter().map(|&(_, w)| w).sum(),
                    template: [0.0; 3],
                    shape: vec![0.0; 3 * n_shape],
                    exp: vec![0.0; 3 * n_exp],
                    pose: vec![0.0; 3 * N_POSE_FEAT],
                };
                for &(v, w) in &coef {
                    for x in 0..3 {
                        b.template[x] += w * asset.v_template[v * 3 + x] as f64;
                        let row = &asset.shapedirs[(v * 3 + x) * k_file..(v * 3 + x + 1) * k_file];
                        for s in 0..n_shape {
                            b.shape[x * n_shape + s] += w * row[s] as f64;
                        }
                        for e in 0..n_exp {
                            b.exp[x * n_exp + e] += w * row[exp_col(e)] as f64;
                        }
                        let prow = &asset.posedirs[(v * 3 + x) * POSE_BASIS..][..POSE_BASIS];
                        for p in 0..N_POSE_FEAT {
                            b.pose[x * N_POSE_FEAT + p] += w * prow[POSE_FEAT_OFFSET + p] as f64;
                        }
                    }
                }
                blocks.push(b);
            }
            block_start.push(blocks.len());
        }
        // Joints regressed from the whole mesh (J_regressor is dense in principle).
        let mut joint_template = [[0.0; 3]; NUM_JOINTS];
        let mut joint_shape = vec![0.0; NUM_JOINTS * 3 * n_shape];
        let mut joint_exp = vec![0.0; NUM_JOINTS * 3 * n_exp];
        for (j, jt) in joint_template.iter_mut().enumerate() {
            for v in 0..nv {
                let w = asset.j_regressor[j * nv + v] as f64;
                if w == 0.0 {
                    continue;
                }
                for x in 0..3 {
                    jt[x] += w * asset.v_template[v * 3 + x] as f64;
                    let row = &asset.shapedirs[(v * 3 + x) * k_file..(v * 3 + x + 1) * k_file];
                    let js = &mut joint_shape[(j * 3 + x) * n_shape..][..n_shape];
                    for (s, out) in js.iter_mut().enumerate() {
                        *out += w * row[s] as f64;
                    }
                    let je = &mut joint_exp[(j * 3 + x) * n_exp..][..n_exp];
                    for (e, out) in je.iter_mut().enumerate() {
                        *out += w * row[exp_col(e)] as f64;
                    }
                }
            }
        }
        Ok(Self {
            n_shape,
            n_exp,
            scale: FLAME_SCALE,
            blocks,
            block_start,
            joint_template,
            joint_shape,
            joint_exp,
        })
    }

    /// The rig with all of the asset's components (the release: 300 shape, 100 expression).
    pub fn from_asset(asset: &FlameAsset) -> Result<Self> {
        Self::new(asset, asset.layout.shape, asset.layout.expression)
    }

    /// The tracker's default: the first [`TRACKING_SHAPE_COMPONENTS`] shape components (70
    /// landmarks cannot tell the later, small ones from the prior; fitting them triples the
    /// cost of a shape solve) and every expression component. Records still hold 300 / 100
    /// values, the rest zero.
    pub fn for_tracking(asset: &FlameAsset) -> Result<Self> {
        Self::new(
            asset,
            asset.layout.shape.min(TRACKING_SHAPE_COMPONENTS),
            asset.layout.expression,
        )
    }

    fn check_codes(&self, c: &FaceCodes) -> Result<()> {
        if c.shape.len() != self.n_shape || c.expression.len() != self.n_exp {
            return Err(TrackError::Input {
                what: "FLAME codes",
                reason: format!(
                    "{} shape / {} expression values, the rig takes {} / {}",
                    c.shape.len(),
                    c.expression.len(),
                    self.n_shape,
                    self.n_exp
                ),
            });
        }
        Ok(())
    }

    /// The 70 landmarks (FLAME space, x5).
    pub fn landmarks(&self, codes: &FaceCodes) -> Result<Vec<Vec3>> {
        Ok(self.evaluate(codes, None)?.points)
    }

    /// Landmarks and, with `columns`, their derivatives (see [`RigColumns`] for the order).
    pub fn evaluate(&self, codes: &FaceCodes, columns: Option<RigColumns>) -> Result<RigOutput> {
        self.check_codes(codes)?;
        let (ns, ne) = (self.n_shape, self.n_exp);
        // Rotations of the posed joints and the pose-corrective features.
        let mut g: [Mat3; NUM_JOINTS] = [IDENTITY; NUM_JOINTS];
        let mut dg: [[Mat3; 3]; 3] = [[[[0.0; 3]; 3]; 3]; 3];
        let mut feat = [0.0; N_POSE_FEAT];
        for (i, &j) in POSED_JOINTS.iter().enumerate() {
            let (r, d) = rodrigues_with_grad(&codes.joint_rotation(i));
            g[j] = r;
            dg[i] = d;
            for a in 0..3 {
                for b in 0..3 {
                    feat[i * 9 + a * 3 + b] = r[a][b] - IDENTITY[a][b];
                }
            }
        }
        // Joint positions (unscaled) and, for the posed ones, (I - G_j) times their bases.
        let mut joints = [[0.0; 3]; NUM_JOINTS];
        for (j, jp) in joints.iter_mut().enumerate() {
            for x in 0..3 {
                let js = &self.joint_shape[(j * 3 + x) * ns..][..ns];
                let je = &self.joint_exp[(j * 3 + x) * ne..][..ne];
                jp[x] = self.joint_template[j][x]
                    + dotv(js, &codes.shape)
                    + dotv(je, &codes.expression);
            }
        }
        let want_shape = columns.is_some_and(|c| c.shape);
        let n_cols = columns.map_or(0, |c| c.count(self));
        let off_exp = if want_shape { ns } else { 0 };
        let off_pose = off_exp + ne;
        // (I - G_j) Jbasis_j for j = 2, 3, 4: [3][n] each.
        let i_minus = |j: usize| -> Mat3 {
            std::array::from_fn(|a| std::array::from_fn(|b| IDENTITY[a][b] - g[j][a][b]))
        };
        let mut q_exp = vec![0.0; 3 * 3 * ne];
        let mut q_shape = vec![0.0; if want_shape { 3 * 3 * ns } else { 0 }];
        if columns.is_some() {
            for (i, &j) in POSED_JOINTS.iter().enumerate() {
                let m = i_minus(j);
                mat_times_rows(
                    &m,
                    &self.joint_exp[j * 3 * ne..][..3 * ne],
                    ne,
                    &mut q_exp[i * 3 * ne..][..3 * ne],
                );
                if want_shape {
                    mat_times_rows(
                        &m,
                        &self.joint_shape[j * 3 * ns..][..3 * ns],
                        ns,
                        &mut q_shape[i * 3 * ns..][..3 * ns],
                    );
                }
            }
        }

        let s = self.scale;
        let mut points = Vec::with_capacity(N_LANDMARKS);
        let mut jac = vec![
            0.0;
            if columns.is_some() {
                N_LANDMARKS * 3 * n_cols
            } else {
                0
            }
        ];
        let mut m_kj: Vec<Vec3> = Vec::with_capacity(4);
        for k in 0..N_LANDMARKS {
            let blocks = &self.blocks[self.block_start[k]..self.block_start[k + 1]];
            let mut p = [0.0; 3];
            m_kj.clear();
            for b in blocks {
                let mut m = b.template;
                for x in 0..3 {
                    m[x] += dotv(&b.shape[x * ns..][..ns], &codes.shape)
                        + dotv(&b.exp[x * ne..][..ne], &codes.expression)
                        + dotv(&b.pose[x * N_POSE_FEAT..][..N_POSE_FEAT], &feat);
                }
                let gm = matvec(&g[b.joint], &m);
                let jterm = if b.joint >= 2 {
                    let ij = matvec(&i_minus(b.joint), &joints[b.joint]);
                    ij.map(|v| b.weight * v)
                } else {
                    [0.0; 3]
                };
                for x in 0..3 {
                    p[x] += s * (gm[x] + jterm[x]);
                }
                m_kj.push(m);
            }
            points.push(p);
            if columns.is_none() {
                continue;
            }
            let rows = &mut jac[k * 3 * n_cols..(k + 1) * 3 * n_cols];
            for (bi, b) in blocks.iter().enumerate() {
                let gj = &g[b.joint];
                let posed = POSED_JOINTS.iter().position(|&j| j == b.joint);
                // Shape / expression: G_j basis + W_kj (I - G_j) Jbasis.
                let mut lin = |basis: &[f64], q: Option<&[f64]>, n: usize, off: usize| {
                    for x in 0..3 {
                        let row = &mut rows[x * n_cols + off..][..n];
                        for y in 0..3 {
                            let gxy = s * gj[x][y];
                            if gxy != 0.0 {
                                axpy(gxy, &basis[y * n..][..n], row);
                            }
                        }
                        if let Some(q) = q {
                            axpy(s * b.weight, &q[x * n..][..n], row);
                        }
                    }
                };
                let qe = posed.map(|i| &q_exp[i * 3 * ne..][..3 * ne]);
                lin(&b.exp, qe, ne, off_exp);
                if want_shape {
                    let qs = posed.map(|i| &q_shape[i * 3 * ns..][..3 * ns]);
                    lin(&b.shape, qs, ns, 0);
                }
                // Posed joints: through the corrective features (every block) and through G_j
                // (blocks of that joint).
                for (i, &j) in POSED_JOINTS.iter().enumerate() {
                    for a in 0..3 {
                        let d = &dg[i][a];
                        let mut dm = [0.0; 3];
                        for x in 0..3 {
                            let prow = &b.pose[x * N_POSE_FEAT + i * 9..][..9];
                            dm[x] = (0..9).map(|t| prow[t] * d[t / 3][t % 3]).sum();
                        }
                        let mut col = matvec(gj, &dm);
                        if b.joint == j {
                            let dgm = matvec(d, &m_kj[bi]);
                            let dgj = matvec(d, &joints[j]);
                            for x in 0..3 {
                                col[x] += dgm[x] - b.weight * dgj[x];
                            }
                        }
                        for x in 0..3 {
                            rows[x * n_cols + off_pose + i * 3 + a] += s * col[x];
                        }
                    }
                }
            }
        }
        Ok(RigOutput {
            points,
            jacobian: jac,
            n_cols,
        })
    }
}

fn dotv(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn axpy(alpha: f64, x: &[f64], y: &mut [f64]) {
    for (yi, xi) in y.iter_mut().zip(x) {
        *yi += alpha * xi;
    }
}

/// `out[3][n] = m (3x3) * rows[3][n]`.
fn mat_times_rows(m: &Mat3, rows: &[f64], n: usize, out: &mut [f64]) {
    for x in 0..3 {
        let o = &mut out[x * n..][..n];
        o.fill(0.0);
        for y in 0..3 {
            if m[x][y] != 0.0 {
                axpy(m[x][y], &rows[y * n..][..n], o);
            }
        }
    }
}
