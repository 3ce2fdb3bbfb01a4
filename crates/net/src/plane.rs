//! The point plane and the direction encoding of the source view (spec section 3).
//!
//! The plane is perpendicular to the source camera's view axis at the depth of the world origin
//! (the head centre), one point per pixel of the `S x S` lifting maps, so each conv-branch pixel
//! has a 3D anchor that the lifting distances then push along the view axis.

use candle_core::{DType, Device, Result, Tensor, D};

/// Frequencies of the harmonic direction encoding, in order.
pub const HARMONIC_FREQS: [f64; 4] = [1.0, 2.0, 4.0, 8.0];

/// Checks `transform` is `[B, 3, 4]` and returns B.
fn batch_of(transform: &Tensor) -> Result<usize> {
    match transform.dims() {
        [b, 3, 4] if *b > 0 => Ok(*b),
        other => candle_core::bail!("transform must be [B, 3, 4] with B >= 1, got {other:?}"),
    }
}

/// Camera-space ray directions `(u/f, v/f, 1)` for the `s x s` grid, row-major
/// (index `i*s + j`), with `u_j = 1 - 2j/(s-1)` across columns and `v_i = 1 - 2i/(s-1)` down rows.
fn camera_rays(s: usize, focal: f64, dtype: DType, dev: &Device) -> Result<Tensor> {
    let denom = (s.max(2) - 1) as f64;
    let mut v = Vec::with_capacity(s * s * 3);
    for i in 0..s {
        let vi = 1.0 - 2.0 * i as f64 / denom;
        for j in 0..s {
            let uj = 1.0 - 2.0 * j as f64 / denom;
            v.extend_from_slice(&[uj / focal, vi / focal, 1.0]);
        }
    }
    Tensor::from_vec(v, (s * s, 3), dev)?.to_dtype(dtype)
}

/// Plane points `[B, s*s, 3]` and the view direction `[B, 3]` of each source camera
/// (`transform` = the release's `[R | T]`, `[B, 3, 4]`).
pub fn point_plane(transform: &Tensor, s: usize, focal: f64) -> Result<(Tensor, Tensor)> {
    let b = batch_of(transform)?;
    if s < 2 {
        candle_core::bail!("plane size must be at least 2, got {s}");
    }
    let r = transform.narrow(2, 0, 3)?; // [B,3,3]
    let t = transform.narrow(2, 3, 1)?; // [B,3,1]
                                        // Column form: camera -> world is p = R (c - T); the camera centre is -R T and the
                                        // forward axis R (0,0,1)^T, i.e. R's last column.
    let origin = r.matmul(&t)?.neg()?.squeeze(2)?; // [B,3]
    let dir = r.narrow(2, 2, 1)?.squeeze(2)?.contiguous()?; // [B,3]
    let distance = (&origin * &dir)?.sum_keepdim(1)?.abs()?; // [B,1]
    let rays = camera_rays(s, focal, transform.dtype(), transform.device())?;
    // World rays R d: as rows, d^T R^T.
    let rays = rays
        .unsqueeze(0)?
        .broadcast_as((b, s * s, 3))?
        .contiguous()?
        .matmul(&r.transpose(1, 2)?.contiguous()?)?; // [B,s*s,3]
    let points = rays
        .broadcast_mul(&distance.unsqueeze(2)?)?
        .broadcast_add(&origin.unsqueeze(1)?)?;
    Ok((points, dir))
}

/// Harmonic embedding of `[B, 3]` directions: `[sin(x_c f_k) (12), cos(x_c f_k) (12), x (3)]`,
/// with index `c*4 + k` inside each block.
pub fn dir_encoding(dir: &Tensor) -> Result<Tensor> {
    let b = match dir.dims() {
        [b, 3] => *b,
        other => candle_core::bail!("direction must be [B, 3], got {other:?}"),
    };
    let freqs = Tensor::new(&HARMONIC_FREQS, dir.device())?.to_dtype(dir.dtype())?;
    let e = dir
        .unsqueeze(2)?
        .broadcast_mul(&freqs.reshape((1, 1, HARMONIC_FREQS.len()))?)?
        .reshape((b, 3 * HARMONIC_FREQS.len()))?;
    Tensor::cat(&[e.sin()?, e.cos()?, dir.clone()], D::Minus1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use gagavatar_splat::Camera;

    const TOL: f64 = 1e-12; // f64 arithmetic on O(10) values

    fn tm(dist: f64, yaw: f64, pitch: f64) -> Tensor {
        let m = Camera::look_at_origin_matrix(dist, yaw, pitch);
        let flat: Vec<f64> = m.iter().flatten().copied().collect();
        Tensor::from_vec(flat, (1, 3, 4), &Device::Cpu).unwrap()
    }

    #[test]
    fn plane_is_perpendicular_to_the_view_axis_through_the_origin_depth() {
        let t = tm(9.0, 0.3, -0.2);
        let (p, d) = point_plane(&t, 7, 12.0).unwrap();
        let p: Vec<Vec<f64>> = p.squeeze(0).unwrap().to_vec2().unwrap();
        let d: Vec<f64> = d.squeeze(0).unwrap().to_vec1().unwrap();
        // Every plane point is at signed distance 0 from the plane through the world origin
        // normal to the view direction.
        for (i, q) in p.iter().enumerate() {
            let dot: f64 = q.iter().zip(&d).map(|(a, b)| a * b).sum();
            assert!(dot.abs() < 1e-9, "point {i}: q.dir = {dot}, expected 0");
        }
        // The centre pixel (3,3) of an odd grid lies on the view axis: it is the world origin.
        let c = &p[3 * 7 + 3];
        for (k, v) in c.iter().enumerate() {
            assert!(
                v.abs() < 1e-9,
                "centre point coordinate {k}: {v}, expected 0"
            );
        }
        let n: f64 = d.iter().map(|x| x * x).sum::<f64>();
        assert!((n - 1.0).abs() < TOL, "|dir|^2 = {n}");
    }

    #[test]
    fn encoding_layout() {
        let d = Tensor::new(&[[0.1f64, -0.2, 0.3]], &Device::Cpu).unwrap();
        let e: Vec<f64> = dir_encoding(&d)
            .unwrap()
            .squeeze(0)
            .unwrap()
            .to_vec1()
            .unwrap();
        assert_eq!(e.len(), 27);
        let x = [0.1, -0.2, 0.3];
        for c in 0..3 {
            for (k, f) in HARMONIC_FREQS.iter().enumerate() {
                let i = c * 4 + k;
                assert!(
                    (e[i] - (x[c] * f).sin()).abs() < TOL,
                    "sin at {i}: {} vs {}",
                    e[i],
                    (x[c] * f).sin()
                );
                assert!((e[12 + i] - (x[c] * f).cos()).abs() < TOL, "cos at {i}");
            }
            assert_eq!(e[24 + c], x[c]);
        }
    }

    #[test]
    fn bad_shapes_are_errors() {
        let bad = Tensor::zeros((3, 4), DType::F32, &Device::Cpu).unwrap();
        assert!(point_plane(&bad, 8, 12.0).is_err());
        assert!(dir_encoding(&bad).is_err());
    }
}
