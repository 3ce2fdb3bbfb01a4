//! Axis-angle to rotation matrix, exactly as the standard FLAME code does it.
//!
//! The angle is `|r + 1e-8|` (the epsilon is added to every component before the norm), not
//! `|r| + eps`: the pretrained weights were fitted with this, and it keeps the zero rotation
//! differentiable (the norm never hits 0 at r = 0). The price is a tiny bias
//! (R(0) = I + O(1e-8)) and a singular point at r = -1e-8 (1, 1, 1), both harmless in practice.

use candle_core::Tensor;

use crate::error::Result;

/// The release's epsilon inside the norm.
pub const RODRIGUES_EPS: f64 = 1e-8;

/// `[N, 3]` axis-angle -> `[N, 3, 3]` rotations, built from elementwise ops so gradients flow.
pub fn rodrigues(r: &Tensor) -> Result<Tensor> {
    let n = r.dim(0)?;
    let angle = (r + RODRIGUES_EPS)?.sqr()?.sum_keepdim(1)?.sqrt()?; // [N, 1]
    let dir = r.broadcast_div(&angle)?;
    let s = angle.sin()?;
    let omc = angle.cos()?.affine(-1.0, 1.0)?; // 1 - cos
    let x = dir.narrow(1, 0, 1)?;
    let y = dir.narrow(1, 1, 1)?;
    let z = dir.narrow(1, 2, 1)?;
    let (xx, yy, zz) = (x.sqr()?, y.sqr()?, z.sqr()?);
    let (xy, xz, yz) = ((&x * &y)?, (&x * &z)?, (&y * &z)?);
    // R = I + sin K + (1 - cos) K^2 with K the cross-product matrix of `dir`;
    // K^2 = [[-(y²+z²), xy, xz], [xy, -(x²+z²), yz], [xz, yz, -(x²+y²)]].
    let diag =
        |a: &Tensor, b: &Tensor| -> Result<Tensor> { Ok(((a + b)? * &omc)?.affine(-1.0, 1.0)?) };
    let off = |sq: &Tensor, axis: &Tensor, sign: f64| -> Result<Tensor> {
        Ok(((sq * &omc)? + ((axis * &s)? * sign)?)?)
    };
    let entries = [
        diag(&yy, &zz)?,
        off(&xy, &z, -1.0)?,
        off(&xz, &y, 1.0)?,
        off(&xy, &z, 1.0)?,
        diag(&xx, &zz)?,
        off(&yz, &x, -1.0)?,
        off(&xz, &y, -1.0)?,
        off(&yz, &x, 1.0)?,
        diag(&xx, &yy)?,
    ];
    Ok(Tensor::cat(&entries, 1)?.reshape((n, 3, 3))?)
}

/// Host-side f64 version (same formula), for the yaw that picks the dynamic contour.
pub fn rodrigues_f64(r: [f64; 3]) -> [[f64; 3]; 3] {
    let angle = r
        .iter()
        .map(|v| (v + RODRIGUES_EPS) * (v + RODRIGUES_EPS))
        .sum::<f64>()
        .sqrt();
    let [x, y, z] = r.map(|v| v / angle);
    let (s, c) = angle.sin_cos();
    let omc = 1.0 - c;
    [
        [
            1.0 - omc * (y * y + z * z),
            omc * x * y - s * z,
            omc * x * z + s * y,
        ],
        [
            omc * x * y + s * z,
            1.0 - omc * (x * x + z * z),
            omc * y * z - s * x,
        ],
        [
            omc * x * z - s * y,
            omc * y * z + s * x,
            1.0 - omc * (x * x + y * y),
        ],
    ]
}

pub fn matmul3(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut out = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    out
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)] // index loops read closer to the matrix maths
mod tests {
    use super::*;
    use candle_core::{DType, Device};

    fn to_mats(t: &Tensor) -> Vec<Vec<Vec<f64>>> {
        t.to_dtype(DType::F64).unwrap().to_vec3::<f64>().unwrap()
    }

    #[test]
    fn zero_rotation_is_identity_up_to_the_epsilon() {
        let r = Tensor::zeros((1, 3), DType::F64, &Device::Cpu).unwrap();
        let m = to_mats(&rodrigues(&r).unwrap());
        for i in 0..3 {
            for j in 0..3 {
                let want = if i == j { 1.0 } else { 0.0 };
                // Off-diagonal terms are sin(|eps|)*dir = O(1e-8) by construction.
                assert!(
                    (m[0][i][j] - want).abs() < 2e-8,
                    "[{i}][{j}] = {}",
                    m[0][i][j]
                );
            }
        }
    }

    #[test]
    fn matches_host_version_and_is_orthonormal() {
        let vals = [0.3, -0.2, 0.5, 1e-7, -3e-7, 2e-7, 0.0, 0.0, 1.5];
        let r = Tensor::from_slice(&vals, (3, 3), &Device::Cpu).unwrap();
        let m = to_mats(&rodrigues(&r).unwrap());
        for n in 0..3 {
            let h = rodrigues_f64([vals[3 * n], vals[3 * n + 1], vals[3 * n + 2]]);
            for i in 0..3 {
                for j in 0..3 {
                    assert!((m[n][i][j] - h[i][j]).abs() < 1e-14);
                    let dot: f64 = (0..3).map(|k| h[i][k] * h[j][k]).sum();
                    let want = if i == j { 1.0 } else { 0.0 };
                    // The epsilon makes `dir` slightly non-unit: O(1e-8 / |r|) off orthonormal.
                    assert!((dot - want).abs() < 1e-7, "row dot {n} {i} {j}: {dot}");
                }
            }
        }
    }

    #[test]
    fn rotation_about_z_by_quarter_turn() {
        let h = rodrigues_f64([0.0, 0.0, std::f64::consts::FRAC_PI_2]);
        // x axis maps to y axis.
        assert!((h[1][0] - 1.0).abs() < 1e-7 && h[0][0].abs() < 1e-7);
    }
}
