//! The release's camera (spec section 2): a 3x4 `transform_matrix` `[R | T]` in PyTorch3D's
//! row-vector convention, an NDC focal length and the image size, turned into the splatting
//! convention (+X right, +Y down, +Z forward).

use crate::error::{Result, SplatError};

/// Largest image side accepted; beyond this the tile grid indices would not fit comfortably and a
/// request that large is almost certainly a mistake.
pub const MAX_IMAGE_SIDE: usize = 16384;

/// A pinhole camera in the splatting convention.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    pub width: usize,
    pub height: usize,
    /// NDC focal length (the release uses 12 for both axes).
    pub focal: f64,
    /// World-to-view rotation in column form: `view = rot * p + trans`.
    pub rot: [[f64; 3]; 3],
    pub trans: [f64; 3],
}

impl Camera {
    /// `tm` is the release's `transform_matrix` (rows of `[R | T]`). PyTorch3D maps a world row
    /// vector `p` to `p R + T`, i.e. column form `R^T p + T`; its +X points left and +Y up, so the
    /// first two camera coordinates are negated to reach the splatting convention.
    pub fn from_transform_matrix(
        tm: &[[f64; 4]; 3],
        focal: f64,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        if width == 0 || height == 0 || width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
            return Err(SplatError::ImageSize {
                width,
                height,
                max: MAX_IMAGE_SIDE,
            });
        }
        if !(focal.is_finite() && focal > 0.0) {
            return Err(SplatError::Camera(format!(
                "focal must be finite and positive, got {focal}"
            )));
        }
        for (r, row) in tm.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                if !v.is_finite() {
                    return Err(SplatError::Camera(format!(
                        "transform_matrix[{r}][{c}] is not finite ({v})"
                    )));
                }
            }
        }
        let flip = [-1.0, -1.0, 1.0];
        let mut rot = [[0.0; 3]; 3];
        let mut trans = [0.0; 3];
        for i in 0..3 {
            for (j, rot_ij) in rot[i].iter_mut().enumerate() {
                // (R^T)_{ij} = R_{ji}
                *rot_ij = flip[i] * tm[j][i];
            }
            trans[i] = flip[i] * tm[i][3];
        }
        Ok(Self {
            width,
            height,
            focal,
            rot,
            trans,
        })
    }

    /// Focal lengths in pixels: `size / (2 tan(fov/2))` with `tan(fov/2) = 1 / focal`.
    pub fn focal_px(&self) -> (f64, f64) {
        (
            self.width as f64 * self.focal * 0.5,
            self.height as f64 * self.focal * 0.5,
        )
    }

    /// Camera centre in world space (`-R T` in the release's column form).
    pub fn center(&self) -> [f64; 3] {
        // view = rot p + trans = 0  =>  p = -rot^T trans (rot is orthonormal for real cameras).
        let mut c = [0.0; 3];
        for (j, cj) in c.iter_mut().enumerate() {
            *cj = -(0..3).map(|i| self.rot[i][j] * self.trans[i]).sum::<f64>();
        }
        c
    }

    /// A camera at `distance` on the +Z axis of the world looking at the origin, rotated by `yaw`
    /// (about world Y) and `pitch` (about world X), in the release's matrix layout. Handy for
    /// tests, benchmarks and orbit views. Yaw 0 (R = I) sits on -Z and sees the back of a FLAME
    /// head; the release's frontal camera, R = diag(-1, 1, -1), is yaw = pi.
    pub fn look_at_origin_matrix(distance: f64, yaw: f64, pitch: f64) -> [[f64; 4]; 3] {
        // PyTorch3D camera looking down its +Z. A camera placed at (0,0,-d) looking at the origin
        // with R = I has T = (0,0,d). Rotating the world by Ry(yaw) Rx(pitch) before the camera
        // gives orbit views: camera-space q = R^T p + T with R^T = Rx(pitch) Ry(yaw).
        let (sy, cy) = yaw.sin_cos();
        let (sp, cp) = pitch.sin_cos();
        let ry = [[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]];
        let rx = [[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]];
        let mut rt = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                rt[i][j] = (0..3).map(|k| rx[i][k] * ry[k][j]).sum();
            }
        }
        let mut tm = [[0.0; 4]; 3];
        for i in 0..3 {
            for j in 0..3 {
                tm[i][j] = rt[j][i];
            }
        }
        tm[2][3] = distance;
        tm
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identity_camera_flips_x_and_y() {
        let tm = Camera::look_at_origin_matrix(9.0, 0.0, 0.0);
        let cam = Camera::from_transform_matrix(&tm, 12.0, 512, 512).unwrap();
        assert_eq!(
            cam.rot,
            [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]
        );
        assert_eq!(cam.trans, [0.0, 0.0, 9.0]);
        assert_eq!(cam.focal_px(), (3072.0, 3072.0));
        let c = cam.center();
        assert!((c[2] + 9.0).abs() < 1e-12, "{c:?}");
    }

    #[test]
    fn bad_cameras_are_errors() {
        let tm = Camera::look_at_origin_matrix(9.0, 0.1, 0.2);
        assert!(Camera::from_transform_matrix(&tm, 12.0, 0, 5).is_err());
        assert!(Camera::from_transform_matrix(&tm, 0.0, 5, 5).is_err());
        assert!(Camera::from_transform_matrix(&tm, f64::NAN, 5, 5).is_err());
        let mut bad = tm;
        bad[1][2] = f64::INFINITY;
        assert!(Camera::from_transform_matrix(&bad, 12.0, 5, 5).is_err());
    }

    #[test]
    fn orbit_camera_keeps_origin_at_distance() {
        let tm = Camera::look_at_origin_matrix(9.0, 0.4, -0.3);
        let cam = Camera::from_transform_matrix(&tm, 12.0, 64, 64).unwrap();
        let c = cam.center();
        let d = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
        assert!((d - 9.0).abs() < 1e-12);
    }
}
