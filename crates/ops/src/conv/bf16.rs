//! Convolution with bf16 products and f32 sums (`--precision bf16`, see [`crate::bf16`]),
//! inference only (no backward). The banded im2col GEMM runs on the bf16 kernel; the layers
//! the f32 path gives to Winograd F(4x4, 3x3) stay on it, in f32 (the same op as `conv2d`). Rounding Winograd's
//! transformed tiles to bf16 was tried and measured: its inverse transform (coefficients up to
//! 8) amplifies the rounding to 2.6% RMS of the output (7.8% worst of `conv(|x|, |w|)`), ten
//! times a bf16 GEMM's, while im2col in bf16 does 4x the multiplies of Winograd at 2x the rate,
//! so no bf16 form of those layers is both close and faster.

use std::sync::{Arc, OnceLock};

use candle_core::backend::BackendStorage;
use candle_core::{bail, CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::elem::SendPtr;
use super::geom::{Conv2dSpec, Geom};
use super::im2col;
use crate::bf16::{self as kernel, Bf16Error, Bias};
use crate::storage::contiguous;

/// A convolution prepared for bf16 products: the weight is rounded and packed for the im2col
/// GEMM on first use and kept, so pack a layer once and reuse it every frame. Layers that run
/// Winograd run the f32 convolution on the same (shared, not copied) weight tensor, with its
/// Winograd transform kept after the first call (4x the weight, only for those layers).
#[derive(Debug, Clone)]
pub struct Bf16Conv {
    pub(super) weight: Tensor,
    pub(super) bias: Option<Tensor>,
    bias_values: Option<Arc<Vec<f32>>>,
    pub(super) dims: [usize; 4],
    pub(super) spec: Conv2dSpec,
    /// `[cout, K]` pair words (K = cin kh kw) for the im2col GEMM.
    gemm: Arc<OnceLock<Vec<u32>>>,
    /// The f32 Winograd transform, for layers that run Winograd.
    pub(super) wino: super::winograd::WinogradCache,
}

impl Bf16Conv {
    /// `weight` [cout, cin, kh, kw], `bias` [cout], f32.
    pub fn new(weight: &Tensor, bias: Option<&Tensor>, spec: Conv2dSpec) -> Result<Self> {
        if !kernel::available() {
            return Err(candle_core::Error::wrap(Bf16Error::Unsupported));
        }
        let (cout, cin, kh, kw) = weight.dims4()?;
        let bias_values = match bias {
            Some(b) => {
                let b: Vec<f32> = b.flatten_all()?.to_vec1()?;
                if b.len() != cout {
                    bail!(
                        "bf16 conv: bias holds {} values for {cout} outputs",
                        b.len()
                    );
                }
                Some(Arc::new(b))
            }
            None => None,
        };
        Ok(Self {
            weight: weight.clone(),
            bias: bias.cloned(),
            bias_values,
            dims: [cout, cin, kh, kw],
            spec,
            gemm: Arc::default(),
            wino: super::winograd::WinogradCache::default(),
        })
    }

    /// The im2col path: packs the weight on first use, then runs the bf16 GEMM op.
    pub(super) fn gemm_forward(&self, x: &Tensor) -> Result<Tensor> {
        if self.gemm.get().is_none() {
            let [cout, cin, kh, kw] = self.dims;
            let w: Vec<f32> = self.weight.flatten_all()?.to_vec1()?;
            // A concurrent first call may have set it meanwhile; both computed the same words.
            let _ = self.gemm.set(rows_to_words(&w, cout, cin * kh * kw));
        }
        x.contiguous()?.apply_op1_no_bwd(self)
    }
}

/// `rows x k` f32 -> `rows x k/2` pair words (rounded to bf16).
fn rows_to_words(src: &[f32], rows: usize, k: usize) -> Vec<u32> {
    let kp = k.div_ceil(2);
    let mut out = vec![0u32; rows * kp];
    out.par_chunks_mut(kp.max(1))
        .zip(src.par_chunks(k.max(1)))
        .for_each(|(dst, row)| {
            for (p, w) in dst.iter_mut().enumerate() {
                let lo = kernel::to_bf16_bits(row[2 * p]) as u32;
                let hi = row
                    .get(2 * p + 1)
                    .map_or(0, |&v| kernel::to_bf16_bits(v) as u32);
                *w = lo | (hi << 16);
            }
        });
    out
}

impl CustomOp1 for Bf16Conv {
    fn name(&self) -> &'static str {
        "bf16-conv2d"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let CpuStorage::F32(data) = s else {
            bail!("bf16 conv: f32 input only, got {:?}", s.dtype());
        };
        let x = contiguous(data, l, "bf16 conv", "input")?;
        let g = Geom::new(l.dims(), &self.dims, self.spec)?;
        let Some(words) = self.gemm.get() else {
            bail!("bf16 conv: the weight was not packed (call `forward`)");
        };
        let mut y = vec![0f32; g.b * g.cout * g.oh * g.ow];
        let bias = self.bias_values.as_deref().map(|b| b.as_slice());
        gemm_forward(x, words, bias, &g, &mut y);
        Ok((CpuStorage::F32(y), Shape::from((g.b, g.cout, g.oh, g.ow))))
    }
}

/// The banded implicit-im2col path with bf16 products; `w` from [`Bf16Conv::gemm_words`].
fn gemm_forward(x: &[f32], w: &[u32], bias: Option<&[f32]>, g: &Geom, y: &mut [f32]) {
    let k = g.k();
    let kp = k.div_ceil(2);
    let (plane_in, plane_out) = (g.h * g.w, g.oh * g.ow);
    let threads = rayon::current_num_threads();
    let rows = im2col::band_rows(g, k, im2col::COL_ELEMS, threads);
    let nbands = g.oh.div_ceil(rows);
    let tasks = g.b * nbands;
    let inner = tasks < threads;
    let pointwise = im2col::is_pointwise(g);
    let yp = SendPtr(y.as_mut_ptr());
    let bias = bias.map_or(Bias::None, Bias::PerRow);
    let run = |(col, packed): &mut (Vec<f32>, Vec<u32>), task: usize| {
        let (bi, band) = (task / nbands, task % nbands);
        let (r0, r1) = (band * rows, ((band + 1) * rows).min(g.oh));
        let nb = (r1 - r0) * g.ow;
        let xb = &x[bi * g.cin * plane_in..(bi + 1) * g.cin * plane_in];
        // SAFETY: the op was built only where `available()` holds; operands are in-bounds
        // slices, and this task alone writes rows [r0, r1) of every channel of image bi.
        unsafe {
            if pointwise {
                kernel::pack_b_rows(&xb[r0 * g.ow..], k, nb, plane_in, packed);
            } else {
                col.resize(k * nb, 0.0);
                im2col::im2col_band(xb, g, r0, r1, col);
                kernel::pack_b_rows(col, k, nb, nb, packed);
            }
            let dst = yp.get().add(bi * g.cout * plane_out + r0 * g.ow);
            kernel::gemm(w, g.cout, kp, packed, nb, dst, plane_out, bias, inner);
        }
    };
    if inner {
        let mut scratch = Default::default();
        (0..tasks).for_each(|t| run(&mut scratch, t));
    } else {
        (0..tasks)
            .into_par_iter()
            .for_each_init(Default::default, run);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bf16::round_bf16;
    use crate::conv::{use_winograd, winograd, ConvAlgo};
    use candle_core::Device;
    use gagavatar_testkit::uniform_values as values;

    /// The GEMM path multiplies exactly the bf16-rounded operands and sums in f32: against an
    /// f64 sum of the same products, a few f32 ulps of `conv(|x|, |w|)`.
    const GEMM_ACCUMULATION_TOL: f64 = 1e-5;
    /// The Winograd layers stay in f32: the f32 path's bound against a direct sum
    /// (`winograd.rs`: ~4e-6 of `conv(|x|, |w|)`), with room.
    const WINOGRAD_F32_TOL: f64 = 2e-5;

    /// Direct f64 convolution of `x` and `w` (after `map`), and of their magnitudes.
    fn reference(
        x: &[f32],
        w: &[f32],
        bias: &[f32],
        g: &Geom,
        map: impl Fn(f32) -> f64,
    ) -> (Vec<f64>, Vec<f64>) {
        let n = g.b * g.cout * g.oh * g.ow;
        let (mut y, mut mag) = (vec![0f64; n], vec![0f64; n]);
        for b in 0..g.b {
            for co in 0..g.cout {
                for oy in 0..g.oh {
                    for ox in 0..g.ow {
                        let o = ((b * g.cout + co) * g.oh + oy) * g.ow + ox;
                        y[o] = bias[co] as f64;
                        mag[o] = (bias[co] as f64).abs();
                        for ci in 0..g.cin {
                            for ky in 0..g.kh {
                                for kx in 0..g.kw {
                                    let iy = (oy * g.stride + ky) as isize - g.ph as isize;
                                    let ix = (ox * g.stride + kx) as isize - g.pw as isize;
                                    if iy < 0 || ix < 0 || iy >= g.h as isize || ix >= g.w as isize
                                    {
                                        continue;
                                    }
                                    let xv = map(x[((b * g.cin + ci) * g.h + iy as usize) * g.w
                                        + ix as usize]);
                                    let wv = map(w[((co * g.cin + ci) * g.kh + ky) * g.kw + kx]);
                                    y[o] += xv * wv;
                                    mag[o] += (xv * wv).abs();
                                }
                            }
                        }
                    }
                }
            }
        }
        (y, mag)
    }

    /// Worst `|got - want| / mag` and where.
    fn worst(got: &[f32], want: &[f64], mag: &[f64]) -> (usize, f64) {
        let mut worst = (0, 0.0);
        for (i, ((&g, &w), &m)) in got.iter().zip(want).zip(mag).enumerate() {
            let e = if g.is_finite() {
                (g as f64 - w).abs() / m.max(1e-6)
            } else {
                f64::INFINITY
            };
            if e > worst.1 {
                worst = (i, e);
            }
        }
        worst
    }

    #[test]
    fn both_paths_match_a_direct_convolution() -> Result<()> {
        if !gagavatar_testkit::bf16_or_skip("both_paths_match_a_direct_convolution") {
            return Ok(());
        }
        // (b, cin, h, w, cout, k, stride, pad): Winograd (3x3, >= 128 tiles, >= 8 channels),
        // pointwise, strided, odd channel counts, a 3x3 too small for Winograd.
        let cases = [
            (1, 9, 48, 44, 17, 3, 1, 1),
            (2, 8, 45, 47, 8, 3, 1, 1),
            (1, 11, 20, 20, 33, 1, 1, 0),
            (2, 7, 19, 23, 5, 3, 2, 1),
            (1, 5, 9, 9, 6, 3, 1, 1),
            (1, 16, 16, 16, 40, 4, 4, 0),
        ];
        for (i, &(b, cin, h, w, cout, k, stride, padding)) in cases.iter().enumerate() {
            let spec = Conv2dSpec { stride, padding };
            let xs = values(b * cin * h * w, 3 * i as u64 + 1);
            let ws = values(cout * cin * k * k, 3 * i as u64 + 2);
            let bs = values(cout, 3 * i as u64 + 3);
            let dev = Device::Cpu;
            let x = Tensor::from_vec(xs.clone(), (b, cin, h, w), &dev)?;
            let wt = Tensor::from_vec(ws.clone(), (cout, cin, k, k), &dev)?;
            let bt = Tensor::from_vec(bs.clone(), cout, &dev)?;
            let conv = Bf16Conv::new(&wt, Some(&bt), spec)?;
            let got: Vec<f32> = conv.forward(&x)?.flatten_all()?.to_vec1()?;
            let g = Geom::new(x.dims(), wt.dims(), spec)?;
            let wino = use_winograd(&g, ConvAlgo::Auto) && winograd::eligible(&g);
            let (want, mag) = if wino {
                reference(&xs, &ws, &bs, &g, |v| v as f64)
            } else {
                reference(&xs, &ws, &bs, &g, |v| round_bf16(v) as f64)
            };
            let tol = if wino {
                WINOGRAD_F32_TOL
            } else {
                GEMM_ACCUMULATION_TOL
            };
            let (at, err) = worst(&got, &want, &mag);
            assert!(
                err <= tol,
                "case {i} ({}): at {at} expected {} got {} (error {err:.2e} of the magnitude, tolerance {tol:.0e})",
                if wino { "winograd" } else { "gemm" },
                want[at],
                got[at]
            );
        }
        Ok(())
    }

    #[test]
    fn an_image_alone_equals_its_batch() -> Result<()> {
        if !gagavatar_testkit::bf16_or_skip("an_image_alone_equals_its_batch") {
            return Ok(());
        }
        let dev = Device::Cpu;
        for &(k, p) in &[(3, 1), (1, 0)] {
            let x = Tensor::from_vec(values(3 * 8 * 40 * 40, 9), (3, 8, 40, 40), &dev)?;
            let w = Tensor::from_vec(values(16 * 8 * k * k, 10), (16, 8, k, k), &dev)?;
            let conv = Bf16Conv::new(
                &w,
                None,
                Conv2dSpec {
                    stride: 1,
                    padding: p,
                },
            )?;
            let all = conv.forward(&x)?;
            for i in 0..3 {
                let one = conv.forward(&x.narrow(0, i, 1)?)?;
                let diff = (one - all.narrow(0, i, 1)?)?
                    .abs()?
                    .max_all()?
                    .to_scalar::<f32>()?;
                assert_eq!(diff, 0.0, "k{k}: image {i} differs alone and in the batch");
            }
        }
        Ok(())
    }

    #[test]
    fn bad_input_is_an_error() -> Result<()> {
        if !gagavatar_testkit::bf16_or_skip("bf16 conv bad_input_is_an_error") {
            return Ok(());
        }
        let dev = Device::Cpu;
        let w = Tensor::zeros((4, 3, 3, 3), candle_core::DType::F32, &dev)?;
        let conv = Bf16Conv::new(&w, None, Conv2dSpec::default())?;
        let wrong_channels = Tensor::zeros((1, 5, 8, 8), candle_core::DType::F32, &dev)?;
        assert!(conv.forward(&wrong_channels).is_err());
        let f64_input = Tensor::zeros((1, 3, 8, 8), candle_core::DType::F64, &dev)?;
        assert!(conv.forward(&f64_input).is_err());
        let bias = Tensor::zeros(5, candle_core::DType::F32, &dev)?;
        assert!(Bf16Conv::new(&w, Some(&bias), Conv2dSpec::default()).is_err());
        Ok(())
    }
}
