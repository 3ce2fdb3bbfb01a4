//! Bilinear resampling as two matrix products, `Y = Mh X Mw^T`, so it is differentiable through
//! candle's matmul backward (candle has no backward for its own resize). The interpolation
//! matrices follow PyTorch's `F.interpolate(mode="bilinear")` for the three ways the model uses
//! it (spec section 6).

use candle_core::{DType, Result, Tensor};

/// Which bilinear resampling rule.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResizeMode {
    /// `align_corners=False`, no antialias: source `(o + 0.5) in/out - 0.5`, clamped at 0.
    HalfPixel,
    /// `align_corners=True`: source `o (in - 1)/(out - 1)`; the corners map onto each other.
    AlignCorners,
    /// `antialias=True` (`align_corners=False`): when shrinking by `s = in/out > 1` the triangle
    /// filter is widened to support `s`; when enlarging it equals [`ResizeMode::HalfPixel`].
    Antialias,
}

/// Dense interpolation matrix `[out, in]` (row o holds the weights of output sample o).
pub fn interp_matrix(input: usize, output: usize, mode: ResizeMode) -> Vec<f64> {
    let mut m = vec![0.0f64; output * input];
    if input == 0 || output == 0 {
        return m;
    }
    let scale = input as f64 / output as f64;
    for o in 0..output {
        let row = &mut m[o * input..(o + 1) * input];
        match mode {
            ResizeMode::HalfPixel => {
                let src = ((o as f64 + 0.5) * scale - 0.5).max(0.0);
                two_taps(row, src, input);
            }
            ResizeMode::AlignCorners => {
                let src = if output > 1 {
                    o as f64 * (input as f64 - 1.0) / (output as f64 - 1.0)
                } else {
                    0.0
                };
                two_taps(row, src, input);
            }
            ResizeMode::Antialias => {
                // PyTorch's separable AA kernel: support = scale (or 1 when enlarging), taps
                // over [xmin, xmax) with truncating casts, weights normalised to sum 1.
                let support = scale.max(1.0);
                let inv = 1.0 / support;
                let center = scale * (o as f64 + 0.5);
                let xmin = ((center - support + 0.5) as i64).max(0) as usize;
                let xmax = ((center + support + 0.5) as i64).clamp(0, input as i64) as usize;
                let mut total = 0.0;
                for (j, r) in row.iter_mut().enumerate().take(xmax).skip(xmin) {
                    let x = (j as f64 - center + 0.5) * inv;
                    let w = (1.0 - x.abs()).max(0.0);
                    *r = w;
                    total += w;
                }
                if total > 0.0 {
                    for r in &mut row[xmin..xmax] {
                        *r /= total;
                    }
                }
            }
        }
    }
    m
}

fn two_taps(row: &mut [f64], src: f64, input: usize) {
    let i0 = (src.floor() as usize).min(input - 1);
    let i1 = (i0 + 1).min(input - 1);
    let l = (src - i0 as f64).clamp(0.0, 1.0);
    row[i0] += 1.0 - l;
    row[i1] += l;
}

fn matrix(input: usize, output: usize, mode: ResizeMode, like: &Tensor) -> Result<Tensor> {
    let m = interp_matrix(input, output, mode);
    Tensor::from_vec(m, (output, input), like.device())?.to_dtype(like.dtype())
}

/// Resizes the last two dims of `x` ([..., H, W]) to `(out_h, out_w)`.
pub fn resize(x: &Tensor, out_h: usize, out_w: usize, mode: ResizeMode) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    if dims.len() < 2 {
        candle_core::bail!("resize needs at least 2 dims, got {:?}", dims);
    }
    let (h, w) = (dims[dims.len() - 2], dims[dims.len() - 1]);
    if h == 0 || w == 0 || out_h == 0 || out_w == 0 {
        candle_core::bail!("resize of {h}x{w} to {out_h}x{out_w}: sizes must be positive");
    }
    if !matches!(x.dtype(), DType::F32 | DType::F64) {
        candle_core::bail!("resize supports f32 and f64, got {:?}", x.dtype());
    }
    let lead: usize = dims[..dims.len() - 2].iter().product();
    let mut y = x.reshape((lead * h, w))?;
    if out_w != w {
        let mw = matrix(w, out_w, mode, x)?;
        y = y.matmul(&mw.t()?)?;
    }
    let mut y = y.reshape((lead, h, out_w))?;
    if out_h != h {
        let mh = matrix(h, out_h, mode, x)?;
        y = mh.broadcast_left(lead)?.contiguous()?.matmul(&y)?;
    }
    let mut out_dims = dims;
    let n = out_dims.len();
    out_dims[n - 2] = out_h;
    out_dims[n - 1] = out_w;
    y.reshape(out_dims)
}
