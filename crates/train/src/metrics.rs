//! Validation metrics on the fine image (spec section 11): PSNR and SSIM.
//!
//! Conventions (those of the release's validation, which uses torchmetrics 1.4.2):
//! - Both images are clamped to [0, 1] first (the release clamps prediction and ground truth
//!   before measuring), so the data range is 1.
//! - PSNR is per image, `10 log10(1 / mse)` with the mean squared error over all channels and
//!   pixels of that image (`+inf` for identical images); a batch value is the mean of the
//!   per-image values (the release validates one image per batch and averages).
//! - SSIM uses an 11x11 Gaussian window (sigma 1.5, normalised to sum 1; separable),
//!   `C1 = 0.01^2`, `C2 = 0.03^2`, local variances `E[x^2] - E[x]^2` clamped at 0 and the
//!   covariance `E[xy] - E[x]E[y]`. Windows: [`SsimWindows::Reflect`] (the default, what the
//!   release's torchmetrics does: the image is mirror-padded by 5 pixels, PyTorch's `reflect`
//!   mode, and the map of `H x W` values is averaged) or [`SsimWindows::Valid`] (Wang et al.'s
//!   reference: only windows inside the image, a `(H - 10) x (W - 10)` map).
//!   [`ssim`] measures each channel separately and averages; [`ssim_gray`] first converts RGB
//!   to luma (`0.2989 R + 0.587 G + 0.114 B`, torchvision's `rgb_to_grayscale`), which is what
//!   the release reports as SSIM.
//!
//! Everything is accumulated in f64 on the host: `E[x^2] - E[x]^2` cancels badly in f32.

use candle_core::{DType, Tensor};
use rayon::prelude::*;

use crate::error::{input_err, Result};

/// SSIM window side.
pub const SSIM_WINDOW: usize = 11;
/// SSIM Gaussian standard deviation.
pub const SSIM_SIGMA: f64 = 1.5;
/// SSIM stabilisers for data range 1.
pub const SSIM_C1: f64 = 0.01 * 0.01;
pub const SSIM_C2: f64 = 0.03 * 0.03;
/// torchvision's luma weights.
pub const LUMA: [f64; 3] = [0.2989, 0.587, 0.114];

/// The normalised 1-D Gaussian, taps at offsets -5..=5.
pub fn gaussian_window() -> [f64; SSIM_WINDOW] {
    let mut g = [0.0; SSIM_WINDOW];
    let half = (SSIM_WINDOW / 2) as f64;
    for (k, v) in g.iter_mut().enumerate() {
        let d = (k as f64 - half) / SSIM_SIGMA;
        *v = (-0.5 * d * d).exp();
    }
    let s: f64 = g.iter().sum();
    g.iter_mut().for_each(|v| *v /= s);
    g
}

/// An image batch read back to the host: `[B, C, H, W]` values in f64, clamped to [0, 1].
struct HostImages {
    dims: [usize; 4],
    data: Vec<f64>,
}

fn host_images(t: &Tensor, name: &str) -> Result<HostImages> {
    let dims = match t.dims() {
        &[b, c, h, w] if b > 0 && c > 0 && h > 0 && w > 0 => [b, c, h, w],
        other => {
            return Err(input_err(
                name,
                format!("expected a non-empty [B, C, H, W] image batch, got {other:?}"),
            ))
        }
    };
    let mut data = t.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?;
    if let Some(i) = data.iter().position(|v| v.is_nan()) {
        return Err(input_err(name, format!("NaN at flat index {i}")));
    }
    data.iter_mut().for_each(|v| *v = v.clamp(0.0, 1.0));
    Ok(HostImages { dims, data })
}

fn host_pair(a: &Tensor, b: &Tensor) -> Result<(HostImages, HostImages)> {
    let (a, b) = (host_images(a, "prediction")?, host_images(b, "target")?);
    if a.dims != b.dims {
        return Err(input_err(
            "target",
            format!(
                "shape {:?} differs from the prediction's {:?}",
                b.dims, a.dims
            ),
        ));
    }
    Ok((a, b))
}

/// PSNR of one image pair (flat slices of equal length, values in [0, 1]); `+inf` when equal.
pub fn psnr_slice(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len()).max(1);
    let mse = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>() / n as f64;
    if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

/// Per-image PSNR of `[B, C, H, W]` batches (clamped to [0, 1]).
pub fn psnr_per_image(pred: &Tensor, target: &Tensor) -> Result<Vec<f64>> {
    let (a, b) = host_pair(pred, target)?;
    let per = a.dims[1] * a.dims[2] * a.dims[3];
    Ok(a.data
        .chunks(per)
        .zip(b.data.chunks(per))
        .map(|(x, y)| psnr_slice(x, y))
        .collect())
}

/// Mean over the batch of the per-image PSNR.
pub fn psnr(pred: &Tensor, target: &Tensor) -> Result<f64> {
    Ok(mean(&psnr_per_image(pred, target)?))
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// Which SSIM windows are averaged (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SsimWindows {
    /// Mirror padding by 5 (PyTorch `reflect`), one window per pixel (torchmetrics, release).
    #[default]
    Reflect,
    /// Windows inside the image only.
    Valid,
}

/// Index `i` (may be out of range by up to the pad) mirrored into `0..n` without repeating
/// the edge sample (PyTorch's `reflect`).
fn reflect(i: isize, n: usize) -> usize {
    let n = n as isize;
    let r = if i < 0 {
        -i
    } else if i >= n {
        2 * (n - 1) - i
    } else {
        i
    };
    r as usize
}

/// Mean SSIM of one single-channel `h x w` plane pair. Needs `h, w >= 11` for valid windows,
/// `h, w >= 6` for reflect padding.
pub fn ssim_plane(x: &[f64], y: &[f64], h: usize, w: usize, windows: SsimWindows) -> Result<f64> {
    if x.len() != h * w || y.len() != h * w {
        return Err(input_err(
            "image",
            format!("planes of {} and {} values for {h}x{w}", x.len(), y.len()),
        ));
    }
    let pad = SSIM_WINDOW / 2;
    match windows {
        SsimWindows::Valid => {
            if h < SSIM_WINDOW || w < SSIM_WINDOW {
                return Err(input_err(
                    "image",
                    format!(
                        "valid-window SSIM needs at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {h}x{w}"
                    ),
                ));
            }
            ssim_valid(x, y, h, w)
        }
        SsimWindows::Reflect => {
            if h <= pad || w <= pad {
                return Err(input_err(
                    "image",
                    format!("reflect-padded SSIM needs more than {pad} pixels a side, got {h}x{w}"),
                ));
            }
            let (ph, pw) = (h + 2 * pad, w + 2 * pad);
            let padded = |src: &[f64]| -> Vec<f64> {
                let mut out = Vec::with_capacity(ph * pw);
                for i in 0..ph {
                    let r = reflect(i as isize - pad as isize, h);
                    for j in 0..pw {
                        out.push(src[r * w + reflect(j as isize - pad as isize, w)]);
                    }
                }
                out
            };
            ssim_valid(&padded(x), &padded(y), ph, pw)
        }
    }
}

/// Mean SSIM over the windows that fit inside `h x w` (`h, w >= 11`, lengths checked).
fn ssim_valid(x: &[f64], y: &[f64], h: usize, w: usize) -> Result<f64> {
    let g = gaussian_window();
    let (oh, ow) = (h - SSIM_WINDOW + 1, w - SSIM_WINDOW + 1);
    // Horizontal pass: five planes (x, y, x^2, y^2, xy) of h x ow, row-parallel.
    let mut hp = vec![0.0f64; 5 * h * ow];
    hp.par_chunks_mut(5 * ow).enumerate().for_each(|(r, out)| {
        let (xr, yr) = (&x[r * w..(r + 1) * w], &y[r * w..(r + 1) * w]);
        let (o_x, rest) = out.split_at_mut(ow);
        let (o_y, rest) = rest.split_at_mut(ow);
        let (o_xx, rest) = rest.split_at_mut(ow);
        let (o_yy, o_xy) = rest.split_at_mut(ow);
        for (k, &gk) in g.iter().enumerate() {
            let (xs, ys) = (&xr[k..k + ow], &yr[k..k + ow]);
            for j in 0..ow {
                let (a, b) = (xs[j], ys[j]);
                o_x[j] += gk * a;
                o_y[j] += gk * b;
                o_xx[j] += gk * a * a;
                o_yy[j] += gk * b * b;
                o_xy[j] += gk * a * b;
            }
        }
    });
    // Vertical pass fused with the SSIM formula; each output row sums its map values.
    let total: f64 = (0..oh)
        .into_par_iter()
        .map(|i| {
            let mut acc = vec![0.0f64; 5 * ow];
            for (k, &gk) in g.iter().enumerate() {
                let src = &hp[(i + k) * 5 * ow..(i + k + 1) * 5 * ow];
                for (a, s) in acc.iter_mut().zip(src) {
                    *a += gk * s;
                }
            }
            let (mx, rest) = acc.split_at(ow);
            let (my, rest) = rest.split_at(ow);
            let (exx, rest) = rest.split_at(ow);
            let (eyy, exy) = rest.split_at(ow);
            let mut row = 0.0;
            for j in 0..ow {
                let (ux, uy) = (mx[j], my[j]);
                let sxx = (exx[j] - ux * ux).max(0.0);
                let syy = (eyy[j] - uy * uy).max(0.0);
                let sxy = exy[j] - ux * uy;
                let num = (2.0 * ux * uy + SSIM_C1) * (2.0 * sxy + SSIM_C2);
                let den = (ux * ux + uy * uy + SSIM_C1) * (sxx + syy + SSIM_C2);
                row += num / den;
            }
            row
        })
        .sum();
    Ok(total / (oh * ow) as f64)
}

/// Per-image SSIM of `[B, C, H, W]` batches: per channel averaged over channels, or on luma
/// (`luma`, needs `C = 3`).
pub fn ssim_per_image_with(
    pred: &Tensor,
    target: &Tensor,
    windows: SsimWindows,
    luma: bool,
) -> Result<Vec<f64>> {
    let (a, b) = host_pair(pred, target)?;
    let [bs, c, h, w] = a.dims;
    let plane = h * w;
    if luma {
        if c != 3 {
            return Err(input_err(
                "prediction",
                format!("luma SSIM needs 3 channels, got {c}"),
            ));
        }
        let to_luma = |d: &[f64], i: usize| -> Vec<f64> {
            let base = i * 3 * plane;
            (0..plane)
                .map(|p| {
                    LUMA[0] * d[base + p]
                        + LUMA[1] * d[base + plane + p]
                        + LUMA[2] * d[base + 2 * plane + p]
                })
                .collect()
        };
        return (0..bs)
            .map(|i| ssim_plane(&to_luma(&a.data, i), &to_luma(&b.data, i), h, w, windows))
            .collect();
    }
    let mut out = Vec::with_capacity(bs);
    for i in 0..bs {
        let mut s = 0.0;
        for ch in 0..c {
            let off = (i * c + ch) * plane;
            s += ssim_plane(
                &a.data[off..off + plane],
                &b.data[off..off + plane],
                h,
                w,
                windows,
            )?;
        }
        out.push(s / c as f64);
    }
    Ok(out)
}

/// Per-image, per-channel SSIM with reflect padding.
pub fn ssim_per_image(pred: &Tensor, target: &Tensor) -> Result<Vec<f64>> {
    ssim_per_image_with(pred, target, SsimWindows::Reflect, false)
}

/// Mean over the batch of the per-channel SSIM (reflect padding).
pub fn ssim(pred: &Tensor, target: &Tensor) -> Result<f64> {
    Ok(mean(&ssim_per_image(pred, target)?))
}

/// Mean over the batch of the luma SSIM with reflect padding: the release's validation SSIM.
pub fn ssim_gray(pred: &Tensor, target: &Tensor) -> Result<f64> {
    Ok(mean(&ssim_per_image_with(
        pred,
        target,
        SsimWindows::Reflect,
        true,
    )?))
}
