//! Landmarks from the asset's barycentric embeddings, and their projection with the release
//! camera.
//!
//! * Static landmarks (release: 51, iBUG 17..67) sit at fixed points of the surface.
//! * The dynamic contour (release: 17, iBUG 0..16) is a silhouette, so which surface points it
//!   uses depends on head yaw: as in the standard FLAME fitters, yaw is taken from the rotation
//!   `R_global R_neck`, converted to whole degrees (clamped at +39, rounded half-to-even as
//!   `torch.round` does), and picks row `yaw` (0..39) or `39 - yaw` (40..78, negative yaw; below
//!   -39 -> 78) of the `[79, 17]` table.
//! * The full-with-eye embedding (release: 70 = 68 + 2 pupils; keys `full_lmk_*_with_eye`) is a
//!   fixed set too: iBUG 0..67 with a static jaw contour, then the pupils of the image-left eye
//!   (the subject's right, FLAME -x) and of the other eye.
//!
//! `lmk68` is the standard fitter output `[dynamic contour, static]`. The release's FLAME
//! forward returns the plain full-with-eye embedding (`full`, TRACKING.md section 4); that is
//! what its tracker fits and what `gagavatar-track` fits. (Its eyelid "reselect", which swaps 8
//! lid points for vertices, only builds VGGHead targets and is not reproduced.)

use candle_core::{DType, Tensor};

use crate::error::{FlameError, Result};
use crate::lbs::FlameModel;
use crate::rodrigues::{matmul3, rodrigues_f64};

pub use crate::embedding::{LandmarkEmbedding, DYNAMIC_ROWS};

pub const MAX_YAW_DEG: f64 = 39.0;
/// The release camera's focal length in NDC units (spec section 2).
pub const NDC_FOCAL: f64 = 12.0;

/// Yaw (radians) of a rotation matrix, as FLAME fitters compute it.
pub fn yaw_of(r: &[[f64; 3]; 3]) -> f64 {
    let sy = (r[0][0] * r[0][0] + r[1][0] * r[1][0]).sqrt();
    (-r[2][0]).atan2(sy)
}

/// Dynamic-table row for a yaw in radians.
pub fn dynamic_row(yaw: f64) -> usize {
    if yaw.is_nan() {
        // A NaN pose gives NaN vertices anyway; any valid row keeps the indexing in bounds.
        return 0;
    }
    let deg = yaw.to_degrees().min(MAX_YAW_DEG).round_ties_even();
    if deg == 0.0 {
        0
    } else if deg > 0.0 {
        deg as usize
    } else if deg < -MAX_YAW_DEG {
        DYNAMIC_ROWS - 1
    } else {
        (MAX_YAW_DEG - deg) as usize
    }
}

/// Head rotation used for the contour choice: `R_global R_neck` (the neck is zero in the
/// release's full pose, but it still goes through Rodrigues with its epsilon).
pub fn head_rotation(global: [f64; 3], neck: [f64; 3]) -> [[f64; 3]; 3] {
    matmul3(&rodrigues_f64(global), &rodrigues_f64(neck))
}

#[derive(Debug, Clone)]
pub struct Landmarks {
    /// `[B, Ld + Ls, 3]` (release: 68), dynamic contour first, scaled like the vertices.
    pub lmk68: Tensor,
    /// `[B, Lf, 3]` (release: 70) from the full-with-eye embedding: what the release's FLAME
    /// forward returns as its landmarks.
    pub full: Tensor,
    /// The dynamic-table row used for each batch element.
    pub dynamic_rows: Vec<usize>,
}

impl FlameModel {
    /// Landmarks of posed, scaled vertices `[B, V, 3]`; `pose` is the `[B, 6]` pose code used to
    /// produce them (only its global part matters, for the contour).
    pub fn landmarks(&self, vertices: &Tensor, pose: &Tensor) -> Result<Landmarks> {
        let (b, nv, three) = vertices.dims3()?;
        if nv != self.n_vertices || three != 3 {
            return Err(FlameError::Input {
                name: "vertices",
                reason: format!(
                    "shape {:?}, expected [B, {}, 3]",
                    vertices.dims(),
                    self.n_vertices
                ),
            });
        }
        if pose.dims() != [b, 6] {
            return Err(FlameError::Input {
                name: "pose",
                reason: format!("shape {:?}, expected [{b}, 6]", pose.dims()),
            });
        }
        let pose_host = pose.to_dtype(DType::F64)?.to_vec2::<f64>()?;
        let lm = &self.landmarks;
        let ld = lm.dynamic_count;
        let mut rows = Vec::with_capacity(b);
        let mut faces68 = Vec::with_capacity(b);
        let mut bary68 = Vec::with_capacity(b);
        for p in &pose_host {
            let rot = head_rotation([p[0], p[1], p[2]], [0.0; 3]);
            let row = dynamic_row(yaw_of(&rot));
            rows.push(row);
            let mut f = lm.dynamic_faces[row * ld..(row + 1) * ld].to_vec();
            f.extend_from_slice(&lm.static_faces);
            let mut w = lm.dynamic_bary[row * ld..(row + 1) * ld].to_vec();
            w.extend_from_slice(&lm.static_bary);
            faces68.push(f);
            bary68.push(w);
        }
        let lmk68 = self.embed(vertices, &faces68, &bary68)?;
        let full_f = vec![lm.full_faces.clone(); b];
        let full_w = vec![lm.full_bary.clone(); b];
        let full = self.embed(vertices, &full_f, &full_w)?;
        Ok(Landmarks {
            lmk68,
            full,
            dynamic_rows: rows,
        })
    }

    /// Barycentric interpolation, one face list per batch element (all of equal length).
    fn embed(
        &self,
        vertices: &Tensor,
        faces: &[Vec<u32>],
        bary: &[Vec<[f32; 3]>],
    ) -> Result<Tensor> {
        let b = faces.len();
        let l = faces.first().map_or(0, Vec::len);
        let nv = self.n_vertices;
        let mut idx = Vec::with_capacity(b * l * 3);
        let mut w = Vec::with_capacity(b * l * 3);
        for (bi, (fs, ws)) in faces.iter().zip(bary).enumerate() {
            for (&f, wt) in fs.iter().zip(ws) {
                let tri = self.faces[f as usize];
                for c in 0..3 {
                    idx.push((bi * nv) as u32 + tri[c]);
                    w.push(wt[c] as f64);
                }
            }
        }
        let dev = &self.device;
        let idx = Tensor::from_vec(idx, b * l * 3, dev)?;
        let w = Tensor::from_vec(w, (b * l * 3, 1), dev)?.to_dtype(vertices.dtype())?;
        let picked = vertices.reshape((b * nv, 3))?.index_select(&idx, 0)?;
        Ok(picked.broadcast_mul(&w)?.reshape((b, l, 3, 3))?.sum(2)?)
    }
}

/// Projects world points with a release `transform_matrix` to pixel coordinates.
///
/// Convention: the returned `(x, y)` are image column and row, +x right and +y down, pixel
/// centres at integers, i.e. the splatting convention (spec section 2: PyTorch3D's camera has +X
/// left and +Y up, so the first two camera coordinates are negated before the projection). This
/// is the frame in which the rendered and ground-truth images are indexed. Points at or behind the
/// camera plane (z <= 0) give `None`.
pub fn project_point(
    p: [f64; 3],
    transform: &[[f64; 4]; 3],
    width: usize,
    height: usize,
) -> Option<[f64; 2]> {
    // PyTorch3D row convention: cam = p R + T.
    let cam: [f64; 3] = std::array::from_fn(|j| {
        (0..3).map(|i| p[i] * transform[i][j]).sum::<f64>() + transform[j][3]
    });
    let z = cam[2];
    if z <= 0.0 || !z.is_finite() {
        return None;
    }
    let ndc_x = NDC_FOCAL * -cam[0] / z;
    let ndc_y = NDC_FOCAL * -cam[1] / z;
    Some([
        ((ndc_x + 1.0) * width as f64 - 1.0) / 2.0,
        ((ndc_y + 1.0) * height as f64 - 1.0) / 2.0,
    ])
}

/// Differentiable version of [`project_point`]: points `[B, N, 3]`, transforms `[B, 3, 4]` ->
/// pixels `[B, N, 2]` (no culling: points behind the camera give meaningless values).
pub fn project_points(
    points: &Tensor,
    transform: &Tensor,
    width: usize,
    height: usize,
) -> Result<Tensor> {
    let (b, _n, _) = points.dims3()?;
    if transform.dims() != [b, 3, 4] {
        return Err(FlameError::Input {
            name: "transform",
            reason: format!("shape {:?}, expected [{b}, 3, 4]", transform.dims()),
        });
    }
    let r = transform.narrow(2, 0, 3)?;
    let t = transform.narrow(2, 3, 1)?.transpose(1, 2)?; // [B, 1, 3]
    let cam = points.matmul(&r)?.broadcast_add(&t)?;
    let z = cam.narrow(2, 2, 1)?;
    let xy = cam
        .narrow(2, 0, 2)?
        .broadcast_div(&z)?
        .affine(-NDC_FOCAL, 0.0)?; // ndc
    let x = xy
        .narrow(2, 0, 1)?
        .affine(width as f64 / 2.0, (width as f64 - 1.0) / 2.0)?;
    let y = xy
        .narrow(2, 1, 1)?
        .affine(height as f64 / 2.0, (height as f64 - 1.0) / 2.0)?;
    Ok(Tensor::cat(&[&x, &y], 2)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dynamic_rows_follow_the_fitter_convention() {
        let d = |deg: f64| dynamic_row(deg.to_radians());
        assert_eq!(d(0.0), 0);
        assert_eq!(d(0.4), 0);
        assert_eq!(d(12.0), 12);
        assert_eq!(d(60.0), 39);
        assert_eq!(d(-1.0), 40);
        assert_eq!(d(-39.0), 78);
        assert_eq!(d(-75.0), 78);
        // torch.round is half-to-even.
        assert_eq!(d(2.5), 2);
        assert_eq!(d(f64::NAN), 0);
    }

    #[test]
    fn yaw_of_a_rotation_about_y() {
        let r = rodrigues_f64([0.0, 0.3, 0.0]);
        assert!((yaw_of(&r) - 0.3).abs() < 1e-7);
    }

    #[test]
    fn projection_centre_and_flip() {
        // Identity rotation, camera 1 unit in front: origin lands at the image centre.
        let tm = [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 1.0],
        ];
        let c = project_point([0.0; 3], &tm, 512, 512).unwrap();
        assert!((c[0] - 255.5).abs() < 1e-12 && (c[1] - 255.5).abs() < 1e-12);
        // +X (PyTorch3D left) lands left of centre, +Y (up) above it.
        let p = project_point([0.01, 0.01, 0.0], &tm, 512, 512).unwrap();
        assert!(p[0] < 255.5 && p[1] < 255.5);
        assert!((255.5 - p[0] - 0.12 * 256.0).abs() < 1e-9);
        assert!(project_point([0.0, 0.0, -2.0], &tm, 512, 512).is_none());
    }
}
