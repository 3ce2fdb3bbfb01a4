//! The release camera and the rotation algebra the fit needs, in f64.
//!
//! Camera (TRACKING.md section 4, GAGAVATAR.md section 2): a FLAME point `p` (row vector, already
//! x5) goes to camera space as `X = p R + T` (column form `X = R^T p + T`), then to 512-crop
//! pixels as `u = 256 (1 - 12 X/Z)`, `v = 256 (1 - 12 Y/Z)`. This is PyTorch3D's
//! `transform_points_screen`: a continuous coordinate with the image's top-left *corner* at 0, so
//! pixel `(i, j)` has its centre at `(j + 0.5, i + 0.5)`. Every 2D point in this crate (crop and
//! frame pixels, landmarks) uses that corner convention; the splatting renderer's pixel-centre
//! index is `u - 0.5`.
//!
//! Rotations of FLAME joints go through the release's Rodrigues (`|r + 1e-8|` as the angle, see
//! `gagavatar_flame::rodrigues`), differentiated analytically here. Camera rotations are updated
//! multiplicatively (`R <- R Exp(d)`), a minimal 3-parameter step with no singularity.

/// The crop the model works at.
pub const CROP_SIZE: f64 = 512.0;
/// The release camera's focal length in NDC units.
pub const NDC_FOCAL: f64 = 12.0;
/// Focal length in crop pixels: `NDC_FOCAL * CROP_SIZE / 2`.
pub const FOCAL_PX: f64 = NDC_FOCAL * CROP_SIZE / 2.0;
/// The release's epsilon inside the Rodrigues norm.
pub const RODRIGUES_EPS: f64 = gagavatar_flame::rodrigues::RODRIGUES_EPS;

pub type Mat3 = [[f64; 3]; 3];
pub type Vec3 = [f64; 3];

pub const IDENTITY: Mat3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

pub fn matmul(a: &Mat3, b: &Mat3) -> Mat3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

pub fn transpose(a: &Mat3) -> Mat3 {
    std::array::from_fn(|i| std::array::from_fn(|j| a[j][i]))
}

pub fn matvec(a: &Mat3, v: &Vec3) -> Vec3 {
    std::array::from_fn(|i| a[i][0] * v[0] + a[i][1] * v[1] + a[i][2] * v[2])
}

/// `a^T v`.
pub fn matvec_t(a: &Mat3, v: &Vec3) -> Vec3 {
    std::array::from_fn(|i| a[0][i] * v[0] + a[1][i] * v[1] + a[2][i] * v[2])
}

pub fn cross(a: &Vec3, b: &Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

pub fn dot(a: &Vec3, b: &Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub fn norm(a: &Vec3) -> f64 {
    dot(a, a).sqrt()
}

/// The cross-product matrix `[v]x` (`[v]x w = v x w`).
pub fn skew(v: &Vec3) -> Mat3 {
    [[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]]
}

/// The release's Rodrigues for a joint rotation (angle `|r + 1e-8|`, axis `r / angle`) and its
/// three partial derivatives `dR/dr_i`.
pub fn rodrigues_with_grad(r: &Vec3) -> (Mat3, [Mat3; 3]) {
    let re = r.map(|x| x + RODRIGUES_EPS);
    let theta = norm(&re);
    let d = r.map(|x| x / theta);
    let (s, c) = theta.sin_cos();
    let omc = 1.0 - c;
    let k = skew(&d);
    let k2 = matmul(&k, &k);
    let rot: Mat3 = std::array::from_fn(|i| {
        std::array::from_fn(|j| IDENTITY[i][j] + s * k[i][j] + omc * k2[i][j])
    });
    let grads = std::array::from_fn(|a| {
        // d theta / d r_a and d d / d r_a.
        let th_a = re[a] / theta;
        let d_a: Vec3 = std::array::from_fn(|i| {
            let e = if i == a { 1.0 } else { 0.0 };
            e / theta - r[i] * th_a / (theta * theta)
        });
        let ka = skew(&d_a);
        let kka = matmul(&ka, &k);
        let kak = matmul(&k, &ka);
        std::array::from_fn(|i| {
            std::array::from_fn(|j| {
                c * th_a * k[i][j]
                    + s * ka[i][j]
                    + s * th_a * k2[i][j]
                    + omc * (kka[i][j] + kak[i][j])
            })
        })
    });
    (rot, grads)
}

/// The exact exponential map of so(3) (no epsilon): used for camera updates and smoothing.
pub fn exp_so3(w: &Vec3) -> Mat3 {
    let theta = norm(w);
    let k = skew(w);
    let k2 = matmul(&k, &k);
    // sin(t)/t and (1 - cos t)/t^2 with their series near 0.
    let (a, b) = if theta < 1e-6 {
        (1.0 - theta * theta / 6.0, 0.5 - theta * theta / 24.0)
    } else {
        (theta.sin() / theta, (1.0 - theta.cos()) / (theta * theta))
    };
    std::array::from_fn(|i| std::array::from_fn(|j| IDENTITY[i][j] + a * k[i][j] + b * k2[i][j]))
}

/// The logarithm of a rotation matrix (angle in [0, pi]); inverse of [`exp_so3`].
pub fn log_so3(r: &Mat3) -> Vec3 {
    let tr = r[0][0] + r[1][1] + r[2][2];
    let cos = ((tr - 1.0) / 2.0).clamp(-1.0, 1.0);
    let theta = cos.acos();
    let v = [r[2][1] - r[1][2], r[0][2] - r[2][0], r[1][0] - r[0][1]];
    if theta < 1e-6 {
        return v.map(|x| 0.5 * x);
    }
    if std::f64::consts::PI - theta < 1e-4 {
        // Near a half turn the antisymmetric part vanishes: take the axis from R + I.
        let col = (0..3)
            .max_by(|&a, &b| r[a][a].total_cmp(&r[b][b]))
            .unwrap_or(0);
        let mut axis: Vec3 = std::array::from_fn(|i| r[i][col] + IDENTITY[i][col]);
        let n = norm(&axis);
        axis = axis.map(|x| x / n);
        // Fix the sign with the (small) antisymmetric part.
        let sign = if dot(&axis, &v) < 0.0 { -1.0 } else { 1.0 };
        return axis.map(|x| sign * theta * x);
    }
    let f = theta / (2.0 * theta.sin());
    v.map(|x| f * x)
}

/// Projects a camera-space point to 512-crop pixels (corner convention).
pub fn project(x: &Vec3) -> [f64; 2] {
    [
        CROP_SIZE / 2.0 - FOCAL_PX * x[0] / x[2],
        CROP_SIZE / 2.0 - FOCAL_PX * x[1] / x[2],
    ]
}

/// [`project`] and its Jacobian `d(u, v)/d(X, Y, Z)`.
pub fn project_with_grad(x: &Vec3) -> ([f64; 2], [[f64; 3]; 2]) {
    let iz = 1.0 / x[2];
    let uv = project(x);
    let g = [
        [-FOCAL_PX * iz, 0.0, FOCAL_PX * x[0] * iz * iz],
        [0.0, -FOCAL_PX * iz, FOCAL_PX * x[1] * iz * iz],
    ];
    (uv, g)
}

/// A release camera: `transform_matrix = [R | T]` in the row convention.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraPose {
    pub rotation: Mat3,
    pub translation: Vec3,
}

impl CameraPose {
    /// The release's frontal camera at distance `z`: `R = diag(-1, 1, -1)` (FLAME's face, which
    /// looks along +z, faces the camera), `T = (0, 0, z)`.
    pub fn frontal(z: f64) -> Self {
        Self {
            rotation: [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]],
            translation: [0.0, 0.0, z],
        }
    }

    pub fn from_matrix(m: &[[f64; 4]; 3]) -> Self {
        Self {
            rotation: std::array::from_fn(|i| std::array::from_fn(|j| m[i][j])),
            translation: [m[0][3], m[1][3], m[2][3]],
        }
    }

    pub fn matrix(&self) -> [[f64; 4]; 3] {
        std::array::from_fn(|i| {
            [
                self.rotation[i][0],
                self.rotation[i][1],
                self.rotation[i][2],
                self.translation[i],
            ]
        })
    }

    /// Camera-space position of a FLAME point: `p R + T`.
    pub fn to_camera(&self, p: &Vec3) -> Vec3 {
        let q = matvec_t(&self.rotation, p);
        [
            q[0] + self.translation[0],
            q[1] + self.translation[1],
            q[2] + self.translation[2],
        ]
    }

    /// 512-crop pixels of a FLAME point, `None` at or behind the camera plane.
    pub fn project(&self, p: &Vec3) -> Option<[f64; 2]> {
        let x = self.to_camera(p);
        (x[2] > 0.0 && x.iter().all(|v| v.is_finite())).then(|| project(&x))
    }

    /// The multiplicative update `R <- R Exp(d)`, `T <- T + t`.
    pub fn retract(&mut self, d: &Vec3, t: &Vec3) {
        self.rotation = matmul(&self.rotation, &exp_so3(d));
        for i in 0..3 {
            self.translation[i] += t[i];
        }
    }
}

/// PyTorch3D's `matrix_to_rotation_6d`: the first two rows.
pub fn rotation_to_6d(r: &Mat3) -> [f64; 6] {
    [r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2]]
}

/// PyTorch3D's `rotation_6d_to_matrix`: Gram-Schmidt on the two rows, the third their cross
/// product. Degenerate input (zero or parallel rows) gives `None`.
pub fn rotation_from_6d(d: &[f64; 6]) -> Option<Mat3> {
    let a1 = [d[0], d[1], d[2]];
    let a2 = [d[3], d[4], d[5]];
    let n1 = norm(&a1);
    if !(n1 > 1e-12) {
        return None;
    }
    let b1 = a1.map(|x| x / n1);
    let p = dot(&b1, &a2);
    let u: Vec3 = std::array::from_fn(|i| a2[i] - p * b1[i]);
    let n2 = norm(&u);
    if !(n2 > 1e-12) {
        return None;
    }
    let b2 = u.map(|x| x / n2);
    Some([b1, b2, cross(&b1, &b2)])
}

/// Angle (radians) of the rotation taking `a` to `b`.
pub fn rotation_angle_between(a: &Mat3, b: &Mat3) -> f64 {
    norm(&log_so3(&matmul(&transpose(a), b)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    /// Central differences of Rodrigues in f64; step 1e-6 on entries of size 1 gives ~1e-10.
    #[test]
    fn rodrigues_gradient_matches_finite_differences() {
        const TOL: f64 = 1e-8;
        for r in [
            [0.3, -0.2, 0.5],
            [1e-7, -3e-7, 2e-7],
            [0.0, 0.0, 0.0],
            [0.0, 0.25, 0.0],
            [-1.2, 0.4, 2.0],
        ] {
            let (_, g) = rodrigues_with_grad(&r);
            for a in 0..3 {
                let h = 1e-6;
                let mut rp = r;
                let mut rm = r;
                rp[a] += h;
                rm[a] -= h;
                let (p, _) = rodrigues_with_grad(&rp);
                let (m, _) = rodrigues_with_grad(&rm);
                for i in 0..3 {
                    for j in 0..3 {
                        let fd = (p[i][j] - m[i][j]) / (2.0 * h);
                        assert!(
                            close(fd, g[a][i][j], TOL),
                            "r {r:?} d/dr{a} [{i}][{j}]: fd {fd}, analytic {}",
                            g[a][i][j]
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn rodrigues_matches_the_flame_crate() {
        for r in [[0.3, -0.2, 0.5], [0.0, 0.0, 0.0], [1e-7, 2e-7, -1e-7]] {
            let (m, _) = rodrigues_with_grad(&r);
            let f = gagavatar_flame::rodrigues::rodrigues_f64(r);
            for i in 0..3 {
                for j in 0..3 {
                    assert!(close(m[i][j], f[i][j], 1e-15), "{r:?} [{i}][{j}]");
                }
            }
        }
    }

    #[test]
    fn exp_and_log_are_inverse() {
        for w in [
            [0.0, 0.0, 0.0],
            [1e-9, 0.0, -2e-9],
            [0.3, -0.2, 0.5],
            [0.0, 3.0, 0.0],
            [2.0, -1.0, 1.5],
            [0.0, 0.0, std::f64::consts::PI - 1e-6],
        ] {
            let r = exp_so3(&w);
            let back = log_so3(&r);
            for i in 0..3 {
                assert!(close(back[i], w[i], 1e-6), "{w:?} -> {back:?}");
            }
            let rtr = matmul(&transpose(&r), &r);
            for i in 0..3 {
                for j in 0..3 {
                    assert!(close(rtr[i][j], IDENTITY[i][j], 1e-12));
                }
            }
        }
    }

    #[test]
    fn six_d_round_trip_and_projection_centre() {
        let r = exp_so3(&[0.2, -0.7, 0.1]);
        let back = rotation_from_6d(&rotation_to_6d(&r)).unwrap();
        assert!(rotation_angle_between(&r, &back) < 1e-12);
        assert!(rotation_from_6d(&[0.0; 6]).is_none());
        assert!(rotation_from_6d(&[1.0, 0.0, 0.0, 2.0, 0.0, 0.0]).is_none());
        // The world origin in front of a frontal camera lands at the crop centre; +x (FLAME
        // left of the subject) lands right of centre (the subject faces us).
        let cam = CameraPose::frontal(9.0);
        let c = cam.project(&[0.0; 3]).unwrap();
        assert!(close(c[0], 256.0, 1e-12) && close(c[1], 256.0, 1e-12));
        let p = cam.project(&[0.1, 0.1, 0.0]).unwrap();
        assert!(p[0] > 256.0 && p[1] < 256.0, "{p:?}");
        assert!(cam.project(&[0.0, 0.0, 20.0]).is_none());
    }

    /// The corner convention agrees with the flame crate's pixel-centre projection.
    #[test]
    fn projection_matches_the_flame_crate_up_to_half_a_pixel() {
        let mut cam = CameraPose::frontal(9.3);
        cam.retract(&[0.1, 0.3, -0.05], &[0.2, -0.1, 0.0]);
        let p = [0.3, -0.2, 0.4];
        let ours = cam.project(&p).unwrap();
        let theirs = gagavatar_flame::landmarks::project_point(p, &cam.matrix(), 512, 512).unwrap();
        assert!(close(ours[0] - 0.5, theirs[0], 1e-9) && close(ours[1] - 0.5, theirs[1], 1e-9));
    }
}
