//! The ViT's inference kernels (DINOv2 in `gagavatar-net`), fused and without a backward: a
//! two-pass layer norm, blocked attention, exact-erf GELU and an in-place row softmax. The row
//! kernels are compiled for AVX-512 and AVX2 when the CPU has them, with the same arithmetic in
//! every version (`rows`), so results do not depend on the CPU. Callers keep differentiable
//! fallbacks for values that track gradients.

use candle_core::{
    backend::BackendStorage, bail, CpuStorage, CustomOp1, CustomOp3, InplaceOp1, InplaceOp2,
    InplaceOp3, Layout, Result, Shape, Tensor,
};
use rayon::prelude::*;

use crate::conv::elem::SendPtr;
use crate::storage::contiguous;

/// Layer norm over the last dim of `x` with `weight` and `bias` (f32 or f64), two-pass.
pub fn layer_norm(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    x.contiguous()?
        .apply_op3_no_bwd(weight, bias, &LayerNormOp { eps })
}

/// `softmax(q k^T) v` over contiguous f32 `[heads, N, d]` (q already scaled); see
/// [`ATTN_ROWS`].
pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
    q.apply_op3_no_bwd(k, v, &AttentionOp { bf16: false })
}

/// [`attention`] with both products in bf16 (f32 sums, f32 softmax): `--precision bf16`.
pub fn attention_bf16(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
    crate::bf16::Precision::Bf16
        .check()
        .map_err(candle_core::Error::wrap)?;
    q.apply_op3_no_bwd(k, v, &AttentionOp { bf16: true })
}

/// Exact (erf) GELU, `x (1 + erf(x / sqrt 2)) / 2`, f32 or f64.
pub fn gelu_erf(x: &Tensor) -> Result<Tensor> {
    x.contiguous()?.apply_op1_no_bwd(&GeluErfOp)
}

/// What follows one of the ViT's linear products `y = x W^T` (`[M, N]`), applied in place:
/// `y` is a fresh f32 product that its caller owns alone, so no second `[M, N]` buffer and no
/// extra pass over memory is needed.
#[derive(Debug, Clone, Copy)]
pub enum LinearEpilogue<'a> {
    /// `y + bias`.
    Bias(&'a Tensor),
    /// `gelu(y + bias)`, exact (erf) GELU: the MLP's first layer.
    BiasGelu(&'a Tensor),
    /// `residual + ls (y + bias)`: LayerScale and the residual connection after the attention's
    /// projection and after the MLP.
    LayerScale {
        bias: &'a Tensor,
        ls: &'a Tensor,
        residual: &'a Tensor,
    },
}

/// Applies `e` to `y` in place (see [`LinearEpilogue`]); f32, contiguous operands.
pub fn linear_epilogue(y: &Tensor, e: LinearEpilogue) -> Result<()> {
    if !y.is_contiguous() {
        bail!("linear epilogue: the product must be contiguous");
    }
    match e {
        LinearEpilogue::Bias(b) => y.inplace_op2(&b.contiguous()?, &BiasOp { gelu: false }),
        LinearEpilogue::BiasGelu(b) => y.inplace_op2(&b.contiguous()?, &BiasOp { gelu: true }),
        LinearEpilogue::LayerScale { bias, ls, residual } => {
            if residual.elem_count() != y.elem_count() {
                bail!(
                    "layer scale: residual {:?} does not match the product {:?}",
                    residual.dims(),
                    y.dims()
                );
            }
            let bias_ls = Tensor::stack(&[bias.flatten_all()?, ls.flatten_all()?], 0)?;
            y.inplace_op3(&bias_ls, &residual.contiguous()?, &LayerScaleOp)
        }
    }
}

/// The row length of an in-place epilogue's product, checked against a per-column vector.
fn epilogue_row(l: &Layout, per_column: usize, what: &str) -> Result<usize> {
    let n = l.dims().last().copied().unwrap_or(0);
    if n == 0 || per_column != n {
        bail!(
            "{what}: product {:?} does not match a vector of {per_column}",
            l.dims()
        );
    }
    Ok(n)
}

fn contiguous_mut<'a>(d: &'a mut [f32], l: &Layout, what: &str) -> Result<&'a mut [f32]> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&mut d[a..b]),
        None => bail!("{what}: the product must be contiguous"),
    }
}

struct BiasOp {
    gelu: bool,
}

impl InplaceOp2 for BiasOp {
    fn name(&self) -> &'static str {
        "vit-bias"
    }

    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<()> {
        let (CpuStorage::F32(y), CpuStorage::F32(b)) = (s1, s2) else {
            bail!("linear epilogue: f32 operands only");
        };
        let b = contiguous(b, l2, "linear epilogue", "bias")?;
        let n = epilogue_row(l1, b.len(), "linear epilogue")?;
        let y = contiguous_mut(y, l1, "linear epilogue")?;
        let block = n * (16_384 / n).max(1);
        y.par_chunks_mut(block).for_each(|y| {
            if self.gelu {
                rows::bias_gelu(y, n, b);
            } else {
                for r in y.chunks_exact_mut(n) {
                    r.iter_mut().zip(b).for_each(|(v, b)| *v += b);
                }
            }
        });
        Ok(())
    }
}

struct LayerScaleOp;

impl InplaceOp3 for LayerScaleOp {
    fn name(&self) -> &'static str {
        "vit-layer-scale"
    }

    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<()> {
        let (CpuStorage::F32(y), CpuStorage::F32(bl), CpuStorage::F32(res)) = (s1, s2, s3) else {
            bail!("layer scale: f32 operands only");
        };
        let bl = contiguous(bl, l2, "layer scale", "bias and scale")?;
        let res = contiguous(res, l3, "layer scale", "residual")?;
        let n = epilogue_row(l1, bl.len() / 2, "layer scale")?;
        let (b, ls) = bl.split_at(n);
        let y = contiguous_mut(y, l1, "layer scale")?;
        let block = n * (16_384 / n).max(1);
        y.par_chunks_mut(block)
            .zip(res.par_chunks(block))
            .for_each(|(y, r)| rows::layer_scale(y, n, r, b, ls));
        Ok(())
    }
}

/// Attention straight from the qkv product `[B, N, 3C]` (q, k and v of head `h` in columns
/// `h d`, `C + h d` and `2C + h d`, `d = C / heads`): `softmax(scale q k^T) v` per head,
/// written to `[B, N, C]` with head `h` in columns `h d`, the layout the projection reads. The
/// same blocked computation as [`attention`], reading and writing strided rows instead of
/// permuted copies; the scale multiplies the logits inside the first product.
pub fn attention_qkv(qkv: &Tensor, heads: usize, scale: f64) -> Result<Tensor> {
    qkv.apply_op1_no_bwd(&AttentionQkvOp {
        heads,
        scale: scale as f32,
    })
}

struct AttentionQkvOp {
    heads: usize,
    scale: f32,
}

impl CustomOp1 for AttentionQkvOp {
    fn name(&self) -> &'static str {
        "vit-attention-qkv"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let CpuStorage::F32(qkv) = s else {
            bail!("attention: the fused kernel runs in f32");
        };
        let (b, n, c3) = l.shape().dims3()?;
        let h = self.heads;
        if c3 % 3 != 0 || h == 0 || (c3 / 3) % h != 0 {
            bail!(
                "attention: qkv {:?} does not split into 3 x {h} heads",
                l.dims()
            );
        }
        let qkv = contiguous(qkv, l, "attention", "qkv")?;
        let c = c3 / 3;
        let d = c / h;
        let mut out = vec![0f32; b * n * c];
        if n == 0 || d == 0 {
            return Ok((CpuStorage::F32(out), Shape::from((b, n, c))));
        }
        let rows = ATTN_ROWS.min(n);
        // Each task writes only its own head's columns (see below).
        let dst = SendPtr(out.as_mut_ptr());
        (0..b * h).into_par_iter().for_each_init(
            || vec![0f32; rows * n],
            |logits, task| {
                let (bi, hi) = (task / h, task % h);
                let base = bi * n * c3 + hi * d;
                let (q, k, v) = (&qkv[base..], &qkv[base + c..], &qkv[base + 2 * c..]);
                for r0 in (0..n).step_by(rows) {
                    let r = rows.min(n - r0);
                    let lg = &mut logits[..r * n];
                    // SAFETY: q rows r0..r0+r, k and v rows 0..n are read at row stride 3C from
                    // `qkv` (d values each, inside the slice); the logits are this task's own
                    // r x n buffer; the output block (rows r0..r0+r of this batch item, columns
                    // h d .. h d + d at row stride C) is written by this task alone.
                    unsafe {
                        gemm::gemm(
                            r,
                            n,
                            d,
                            lg.as_mut_ptr(),
                            1,
                            n as isize,
                            false,
                            q[r0 * c3..].as_ptr(),
                            1,
                            c3 as isize,
                            k.as_ptr(),
                            c3 as isize,
                            1,
                            0.0,
                            self.scale,
                            false,
                            false,
                            false,
                            gemm::Parallelism::None,
                        );
                        rows::softmax(lg, n);
                        gemm::gemm(
                            r,
                            d,
                            n,
                            dst.get().add((bi * n + r0) * c + hi * d),
                            1,
                            c as isize,
                            false,
                            lg.as_ptr(),
                            1,
                            n as isize,
                            v.as_ptr(),
                            1,
                            c3 as isize,
                            0.0,
                            1.0,
                            false,
                            false,
                            false,
                            gemm::Parallelism::None,
                        );
                    }
                }
            },
        );
        Ok((CpuStorage::F32(out), Shape::from((b, n, c))))
    }
}

/// Row-wise layer norm over the last dim with a two-pass (mean, then centred variance) reduction:
/// candle's fused op uses `E[x^2] - E[x]^2` in f32, which cancels badly on the large-magnitude
/// channels of the DINOv2 residual stream.
struct LayerNormOp {
    eps: f64,
}

impl LayerNormOp {
    fn check(&self, lx: &Layout, w: usize, b: usize) -> Result<usize> {
        let n = lx.dims().last().copied().unwrap_or(0);
        if n == 0 || w != n || b != n {
            bail!(
                "layer norm: input {:?} does not match weight [{w}] / bias [{b}]",
                lx.dims()
            );
        }
        Ok(n)
    }
}

impl CustomOp3 for LayerNormOp {
    fn name(&self) -> &'static str {
        "vit-layer-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        const WHAT: &str = "layer norm";
        let storage = match (s1, s2, s3) {
            (CpuStorage::F32(x), CpuStorage::F32(w), CpuStorage::F32(b)) => {
                let x = contiguous(x, l1, WHAT, "input")?;
                let w = contiguous(w, l2, WHAT, "weight")?;
                let b = contiguous(b, l3, WHAT, "bias")?;
                let n = self.check(l1, w.len(), b.len())?;
                let mut out = vec![0f32; x.len()];
                let eps = self.eps as f32;
                par_rows(x, &mut out, n, |x, o| rows::layer_norm(x, o, n, w, b, eps));
                CpuStorage::F32(out)
            }
            (CpuStorage::F64(x), CpuStorage::F64(w), CpuStorage::F64(b)) => {
                let x = contiguous(x, l1, WHAT, "input")?;
                let w = contiguous(w, l2, WHAT, "weight")?;
                let b = contiguous(b, l3, WHAT, "bias")?;
                let n = self.check(l1, w.len(), b.len())?;
                let mut out = vec![0f64; x.len()];
                par_rows(x, &mut out, n, |x, o| {
                    for (x, o) in x.chunks_exact(n).zip(o.chunks_exact_mut(n)) {
                        let mean = x.iter().sum::<f64>() / n as f64;
                        let var = x.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n as f64;
                        let inv = 1.0 / (var + self.eps).sqrt();
                        for (((o, v), w), b) in o.iter_mut().zip(x).zip(w).zip(b) {
                            *o = (v - mean) * inv * w + b;
                        }
                    }
                });
                CpuStorage::F64(out)
            }
            _ => bail!(
                "layer norm supports f32 or f64 operands of one dtype, got {:?}",
                s1.dtype()
            ),
        };
        Ok((storage, l1.shape().clone()))
    }
}

/// Query rows per block of the fused attention: one block's logits (256 x 1370 f32, 1.4 MiB at
/// the release size) stay in the core's L2 and L3 from the first GEMM through the softmax to
/// the second. Whole-head logits (7.3 MiB) took a third of the attention time in the softmax
/// alone. 256 rows beat 128 by 3-5% on the release ViT (Zen 4, 2 threads, medians 1636 vs
/// 1703 ms over three runs of each): every block repacks k and v for its two products, and
/// half the blocks halve that.
pub const ATTN_ROWS: usize = 256;

/// Inference attention `softmax(q k^T) v` over contiguous f32 `[heads, N, d]` (q already
/// scaled), heads in parallel and each head in blocks of [`ATTN_ROWS`] query rows: single-thread
/// GEMMs on an L2-resident logits block and the in-place row softmax between them.
struct AttentionOp {
    /// Both products in bf16 (checked available by the constructor).
    bf16: bool,
}

impl CustomOp3 for AttentionOp {
    fn name(&self) -> &'static str {
        "vit-attention"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (CpuStorage::F32(q), CpuStorage::F32(k), CpuStorage::F32(v)) = (s1, s2, s3) else {
            bail!("attention: the fused kernel runs in f32");
        };
        let (heads, n, d) = l1.shape().dims3()?;
        if l2.shape() != l1.shape() || l3.shape() != l1.shape() {
            bail!(
                "attention: q {:?}, k {:?} and v {:?} must share one shape",
                l1.dims(),
                l2.dims(),
                l3.dims()
            );
        }
        let q = contiguous(q, l1, "attention", "q")?;
        let k = contiguous(k, l2, "attention", "k")?;
        let v = contiguous(v, l3, "attention", "v")?;
        let mut out = vec![0f32; heads * n * d];
        if n == 0 || d == 0 {
            return Ok((CpuStorage::F32(out), l1.shape().clone()));
        }
        let rows = ATTN_ROWS.min(n);
        if self.bf16 {
            attention_bf16_heads(q, k, v, n, d, rows, &mut out);
            return Ok((CpuStorage::F32(out), l1.shape().clone()));
        }
        out.par_chunks_mut(n * d).enumerate().for_each_init(
            || vec![0f32; rows * n],
            |logits, (h, out_h)| {
                let (qh, kh, vh) = (
                    &q[h * n * d..(h + 1) * n * d],
                    &k[h * n * d..(h + 1) * n * d],
                    &v[h * n * d..(h + 1) * n * d],
                );
                for (b, out_b) in out_h.chunks_mut(rows * d).enumerate() {
                    let r = out_b.len() / d;
                    let lg = &mut logits[..r * n];
                    // SAFETY: every operand is a live slice covering the extents given (q block
                    // r x d, k read as its transpose d x n, logits r x n, v n x d, out r x d);
                    // the destinations do not alias the sources.
                    unsafe {
                        gemm::gemm(
                            r,
                            n,
                            d,
                            lg.as_mut_ptr(),
                            1,
                            n as isize,
                            false,
                            qh[b * rows * d..].as_ptr(),
                            1,
                            d as isize,
                            kh.as_ptr(),
                            d as isize,
                            1,
                            0.0,
                            1.0,
                            false,
                            false,
                            false,
                            gemm::Parallelism::None,
                        );
                    }
                    rows::softmax(lg, n);
                    // SAFETY: as above.
                    unsafe {
                        gemm::gemm(
                            r,
                            d,
                            n,
                            out_b.as_mut_ptr(),
                            1,
                            d as isize,
                            false,
                            lg.as_ptr(),
                            1,
                            n as isize,
                            vh.as_ptr(),
                            1,
                            d as isize,
                            0.0,
                            1.0,
                            false,
                            false,
                            false,
                            gemm::Parallelism::None,
                        );
                    }
                }
            },
        );
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }
}

/// The bf16 form of [`AttentionOp`]'s loop: per head, k and v packed once, then per block of
/// query rows the logits GEMM, the f32 softmax and the value GEMM.
fn attention_bf16_heads(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    n: usize,
    d: usize,
    rows: usize,
    out: &mut [f32],
) {
    use crate::bf16::{self as kernel, Bias};
    #[derive(Default)]
    struct Scratch {
        logits: Vec<f32>,
        kt: Vec<u32>,
        vp: Vec<u32>,
        a: Vec<u32>,
    }
    out.par_chunks_mut(n * d)
        .enumerate()
        .for_each_init(Scratch::default, |s, (h, out_h)| {
            let head = h * n * d..(h + 1) * n * d;
            let (qh, kh, vh) = (&q[head.clone()], &k[head.clone()], &v[head]);
            kernel::pack_b_transposed(kh, n, d, &mut s.kt, false);
            s.logits.resize(rows * n, 0.0);
            // SAFETY: `attention_bf16` checked the CPU; each GEMM gets a live operand of the
            // extents given (q block r x d, k^T d x n, logits r x n, v n x d, out r x d), and
            // its destination is this task's own buffer.
            unsafe {
                kernel::pack_b_rows(vh, n, d, d, &mut s.vp);
                for (b, out_b) in out_h.chunks_mut(rows * d).enumerate() {
                    let r = out_b.len() / d;
                    let lg = &mut s.logits[..r * n];
                    kernel::convert_rows(&qh[b * rows * d..][..r * d], r, d, &mut s.a);
                    let dp = d.div_ceil(2);
                    kernel::gemm(&s.a, r, dp, &s.kt, n, lg.as_mut_ptr(), n, Bias::None, false);
                    rows::softmax(lg, n);
                    kernel::convert_rows(lg, r, n, &mut s.a);
                    let np = n.div_ceil(2);
                    kernel::gemm(
                        &s.a,
                        r,
                        np,
                        &s.vp,
                        d,
                        out_b.as_mut_ptr(),
                        d,
                        Bias::None,
                        false,
                    );
                }
            }
        });
}

struct GeluErfOp;

impl CustomOp1 for GeluErfOp {
    fn name(&self) -> &'static str {
        "vit-gelu-erf"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let storage = match s {
            CpuStorage::F32(x) => {
                let x = contiguous(x, l, "gelu", "input")?;
                let mut out = vec![0f32; x.len()];
                par_rows(x, &mut out, 1, rows::gelu_erf);
                CpuStorage::F32(out)
            }
            CpuStorage::F64(x) => {
                let x = contiguous(x, l, "gelu", "input")?;
                let mut out = vec![0f64; x.len()];
                par_rows(x, &mut out, 1, |x, o| {
                    for (o, &v) in o.iter_mut().zip(x) {
                        let e = candle_core::cpu::erf::erf_f64(v * std::f64::consts::FRAC_1_SQRT_2);
                        *o = 0.5 * v * (1.0 + e);
                    }
                });
                CpuStorage::F64(out)
            }
            _ => bail!("gelu supports f32 and f64, got {:?}", s.dtype()),
        };
        Ok((storage, l.shape().clone()))
    }
}

/// Softmax over the last dim (the attention rows), in place: the logits are a fresh tensor
/// nobody else holds, and a second [B H, N, N] buffer would be the largest allocation
/// of the ViT.
pub fn softmax_in_place(x: &Tensor) -> Result<()> {
    if !x.is_contiguous() {
        bail!("softmax: logits must be contiguous");
    }
    x.inplace_op1(&SoftmaxOp)
}

struct SoftmaxOp;

impl InplaceOp1 for SoftmaxOp {
    fn name(&self) -> &'static str {
        "vit-softmax"
    }

    fn cpu_fwd(&self, s: &mut CpuStorage, l: &Layout) -> Result<()> {
        let n = l.dims().last().copied().unwrap_or(0);
        let Some((o0, o1)) = l.contiguous_offsets() else {
            bail!("softmax: logits must be contiguous");
        };
        if n == 0 {
            bail!("softmax of an empty row: {:?}", l.dims());
        }
        let block = n * (16_384 / n).max(1);
        match s {
            CpuStorage::F32(x) => x[o0..o1]
                .par_chunks_mut(block)
                .for_each(|x| rows::softmax(x, n)),
            CpuStorage::F64(x) => x[o0..o1].par_chunks_mut(block).for_each(|x| {
                for r in x.chunks_exact_mut(n) {
                    let max = r.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                    r.iter_mut().for_each(|v| *v = (*v - max).exp());
                    let sum: f64 = r.iter().sum();
                    r.iter_mut().for_each(|v| *v /= sum);
                }
            }),
            _ => bail!("softmax supports f32 and f64, got {:?}", s.dtype()),
        }
        Ok(())
    }
}

/// Runs `f` on blocks of whole rows of `row` elements (about 16k values each) on the rayon pool.
fn par_rows<T: Send + Sync>(
    x: &[T],
    out: &mut [T],
    row: usize,
    f: impl Fn(&[T], &mut [T]) + Send + Sync,
) {
    let block = row * (16_384 / row).max(1);
    out.par_chunks_mut(block)
        .zip(x.par_chunks(block))
        .for_each(|(o, x)| f(x, o));
}

/// f32 row kernels for the ViT, compiled for AVX-512 or AVX2 when the CPU has them (same
/// arithmetic in every version, so the results do not depend on the CPU).
mod rows {
    /// `exp` for `x <= 88`: Cody-Waite reduction by ln 2 and a degree-7 polynomial (Cephes'
    /// `expf` coefficients), about 1 ulp; 0 below the f32 normal range.
    #[inline(always)]
    fn exp(x: f32) -> f32 {
        const LN2_HI: f32 = 0.693_359_4;
        const LN2_LO: f32 = -2.121_944_4e-4;
        let n = (x * std::f32::consts::LOG2_E + 0.5).floor();
        let r = x - n * LN2_HI - n * LN2_LO;
        let p = ((((1.987_569_1e-4 * r + 1.398_2e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
            + 1.666_666_5e-1)
            * r
            + 0.5;
        let y = p * (r * r) + r + 1.0;
        // 2^n built in the exponent field. The biased exponent (an integer in 1..=254) is read
        // from the mantissa of `e + 2^23` by a bit cast: a float-to-int `as` cast saturates and
        // maps NaN, which compiles to per-lane scalar code and kept these loops from
        // vectorising (the softmax took a third of the attention time).
        const MANTISSA: f32 = 8_388_608.0;
        let e = n.max(-126.0) + 127.0;
        let scale = f32::from_bits((e + MANTISSA).to_bits().wrapping_sub(MANTISSA.to_bits()) << 23);
        if x < -87.3 {
            0.0
        } else {
            y * scale
        }
    }

    /// Sum with 16 independent accumulators, so the loop vectorises.
    #[inline(always)]
    fn sum(x: &[f32]) -> f32 {
        let mut acc = [0f32; 16];
        let chunks = x.chunks_exact(16);
        let tail: f32 = chunks.remainder().iter().sum();
        for c in chunks {
            for (a, v) in acc.iter_mut().zip(c) {
                *a += v;
            }
        }
        acc.iter().sum::<f32>() + tail
    }

    #[inline(always)]
    fn max(x: &[f32]) -> f32 {
        let mut acc = [f32::NEG_INFINITY; 16];
        let chunks = x.chunks_exact(16);
        let tail = chunks
            .remainder()
            .iter()
            .copied()
            .fold(f32::NEG_INFINITY, f32::max);
        for c in chunks {
            for (a, &v) in acc.iter_mut().zip(c) {
                *a = a.max(v);
            }
        }
        acc.iter().copied().fold(tail, f32::max)
    }

    #[inline(always)]
    fn softmax_body(x: &mut [f32], n: usize) {
        for r in x.chunks_exact_mut(n) {
            let m = max(r);
            r.iter_mut().for_each(|v| *v = exp(*v - m));
            let inv = 1.0 / sum(r);
            r.iter_mut().for_each(|v| *v *= inv);
        }
    }

    /// GELU with erf from Abramowitz & Stegun 7.1.26 (|error| < 1.5e-7, the formula PyTorch's
    /// vectorised CPU `erf` uses): `erf(z) = 1 - t (a1 + t (a2 + ...)) exp(-z^2)`,
    /// `t = 1 / (1 + p z)` for `z >= 0`, odd in `z`.
    #[inline(always)]
    fn gelu(v: f32) -> f32 {
        const P: f32 = 0.327_591_1;
        const A: [f32; 5] = [
            0.254_829_6,
            -0.284_496_74,
            1.421_413_8,
            -1.453_152,
            1.061_405_4,
        ];
        let z = (v * std::f32::consts::FRAC_1_SQRT_2).abs();
        let t = 1.0 / (1.0 + P * z);
        let poly = t * (A[0] + t * (A[1] + t * (A[2] + t * (A[3] + t * A[4]))));
        let erf_abs = 1.0 - poly * exp(-z * z);
        let erf = if v < 0.0 { -erf_abs } else { erf_abs };
        0.5 * v * (1.0 + erf)
    }

    #[inline(always)]
    fn gelu_body(x: &[f32], out: &mut [f32]) {
        for (o, &v) in out.iter_mut().zip(x) {
            *o = gelu(v);
        }
    }

    /// Rows of `n` values: `y = gelu(y + b)`.
    #[inline(always)]
    fn bias_gelu_body(y: &mut [f32], n: usize, b: &[f32]) {
        for r in y.chunks_exact_mut(n) {
            for (v, &b) in r.iter_mut().zip(b) {
                *v = gelu(*v + b);
            }
        }
    }

    /// Rows of `n` values: `y = residual + ls (y + b)`.
    #[inline(always)]
    fn layer_scale_body(y: &mut [f32], n: usize, res: &[f32], b: &[f32], ls: &[f32]) {
        for (r, x) in y.chunks_exact_mut(n).zip(res.chunks_exact(n)) {
            for (((v, &x), &b), &s) in r.iter_mut().zip(x).zip(b).zip(ls) {
                *v = x + s * (*v + b);
            }
        }
    }

    #[inline(always)]
    fn layer_norm_body(x: &[f32], out: &mut [f32], n: usize, w: &[f32], b: &[f32], eps: f32) {
        for (x, o) in x.chunks_exact(n).zip(out.chunks_exact_mut(n)) {
            let mean = sum(x) / n as f32;
            for (o, &v) in o.iter_mut().zip(x) {
                *o = v - mean;
            }
            let mut sq = [0f32; 16];
            let chunks = o.chunks_exact(16);
            let tail: f32 = chunks.remainder().iter().map(|d| d * d).sum();
            for c in chunks {
                for (a, d) in sq.iter_mut().zip(c) {
                    *a += d * d;
                }
            }
            let var = (sq.iter().sum::<f32>() + tail) / n as f32;
            let inv = 1.0 / (var + eps).sqrt();
            for ((o, w), b) in o.iter_mut().zip(w).zip(b) {
                *o = *o * inv * w + b;
            }
        }
    }

    /// Defines `pub fn $name` calling `$body` through the widest instruction set available.
    macro_rules! dispatch {
        ($name:ident, $body:ident, ($($arg:ident: $ty:ty),*)) => {
            pub(super) fn $name($($arg: $ty),*) {
                #[cfg(target_arch = "x86_64")]
                {
                    #[target_feature(enable = "avx512f,avx2,fma")]
                    unsafe fn avx512($($arg: $ty),*) {
                        $body($($arg),*)
                    }
                    #[target_feature(enable = "avx2,fma")]
                    unsafe fn avx2($($arg: $ty),*) {
                        $body($($arg),*)
                    }
                    let avx2_fma = std::arch::is_x86_feature_detected!("avx2")
                        && std::arch::is_x86_feature_detected!("fma");
                    if avx2_fma && std::arch::is_x86_feature_detected!("avx512f") {
                        // SAFETY: the CPU supports every feature the function is compiled for.
                        return unsafe { avx512($($arg),*) };
                    }
                    if avx2_fma {
                        // SAFETY: as above.
                        return unsafe { avx2($($arg),*) };
                    }
                }
                $body($($arg),*)
            }
        };
    }

    dispatch!(softmax, softmax_body, (x: &mut [f32], n: usize));
    dispatch!(gelu_erf, gelu_body, (x: &[f32], out: &mut [f32]));
    dispatch!(bias_gelu, bias_gelu_body, (y: &mut [f32], n: usize, b: &[f32]));
    dispatch!(
        layer_scale,
        layer_scale_body,
        (y: &mut [f32], n: usize, res: &[f32], b: &[f32], ls: &[f32])
    );
    dispatch!(
        layer_norm,
        layer_norm_body,
        (x: &[f32], out: &mut [f32], n: usize, w: &[f32], b: &[f32], eps: f32)
    );

    #[cfg(test)]
    mod tests {
        use super::*;

        /// Deterministic values in [-1, 1) (a 64-bit LCG), so failures reproduce.
        fn values(n: usize, seed: u64) -> Vec<f32> {
            let mut s = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
            (0..n)
                .map(|_| {
                    s = s
                        .wrapping_mul(6_364_136_223_846_793_005)
                        .wrapping_add(1_442_695_040_888_963_407);
                    ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
                })
                .collect()
        }

        /// Polynomial `exp`: under 2 f32 ulps (8e-8 measured).
        const EXP_REL_TOL: f64 = 2e-7;
        /// GELU: A&S erf's 1.5e-7 absolute error times |x| / 2, plus f32 rounding.
        const GELU_TOL: f64 = 3e-7;
        /// Softmax and layer norm outputs: f32 rounding of O(1) values over rows of <= 1000.
        const ROW_TOL: f64 = 2e-6;

        #[test]
        fn exp_matches_f64() {
            let mut worst = (0f32, 0f64);
            for i in 0..=200_000 {
                let x = -87.0 + 97.0 * i as f32 / 200_000.0;
                let want = (x as f64).exp();
                let rel = ((exp(x) as f64 - want) / want).abs();
                if rel > worst.1 {
                    worst = (x, rel);
                }
            }
            assert!(
                worst.1 < EXP_REL_TOL,
                "exp({}) relative error {:.2e}",
                worst.0,
                worst.1
            );
            assert_eq!(exp(-90.0), 0.0);
            assert_eq!(exp(0.0), 1.0);
        }

        #[test]
        fn gelu_matches_f64_erf() {
            let x: Vec<f32> = (0..=40_000).map(|i| -10.0 + i as f32 / 2000.0).collect();
            let mut out = vec![0f32; x.len()];
            gelu_erf(&x, &mut out);
            for (i, (&v, &o)) in x.iter().zip(&out).enumerate() {
                let v = v as f64;
                let want =
                    0.5 * v * (1.0 + candle_core::cpu::erf::erf_f64(v / std::f64::consts::SQRT_2));
                let tol = GELU_TOL * v.abs().max(1.0);
                assert!(
                    (o as f64 - want).abs() <= tol,
                    "gelu index {i} (x = {v}): expected {want}, actual {o}"
                );
            }
        }

        #[test]
        fn softmax_and_layer_norm_match_f64() {
            // Rows of 16 + 7 and 1000 + 5 values (tails off the 16-lane chunks); the layer-norm
            // rows sit on a mean of 300, where `E[x^2] - E[x]^2` in f32 would lose every digit.
            for n in [23usize, 1005] {
                let x: Vec<f32> = values(3 * n, n as u64).iter().map(|v| 8.0 * v).collect();
                let mut sm = x.clone();
                softmax(&mut sm, n);
                let shifted: Vec<f32> = x.iter().map(|v| v + 300.0).collect();
                let (w, b) = (values(n, 1), values(n, 2));
                let mut ln = vec![0f32; x.len()];
                layer_norm(&shifted, &mut ln, n, &w, &b, 1e-6);
                for r in 0..3 {
                    let row: Vec<f64> = x[r * n..(r + 1) * n].iter().map(|&v| v as f64).collect();
                    let max = row.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                    let total: f64 = row.iter().map(|v| (v - max).exp()).sum();
                    let mean = row.iter().sum::<f64>() / n as f64;
                    let var = row.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64;
                    for j in 0..n {
                        let i = r * n + j;
                        let want = (row[j] - max).exp() / total;
                        assert!(
                            (sm[i] as f64 - want).abs() <= ROW_TOL,
                            "softmax n={n} index {i}: expected {want}, actual {}",
                            sm[i]
                        );
                        let want =
                            (row[j] - mean) / (var + 1e-6).sqrt() * w[j] as f64 + b[j] as f64;
                        assert!(
                            (ln[i] as f64 - want).abs() <= ROW_TOL * 10.0,
                            "layer norm n={n} index {i}: expected {want}, actual {}",
                            ln[i]
                        );
                    }
                }
            }
        }

        /// The vectorised builds do the same operations in the same order as the portable one.
        #[test]
        fn dispatched_kernels_equal_the_portable_ones() {
            let n = 777;
            let x: Vec<f32> = values(4 * n, 9).iter().map(|v| 10.0 * v).collect();
            let (w, b) = (values(n, 3), values(n, 4));
            let (mut fast, mut slow) = (x.clone(), x.clone());
            softmax(&mut fast, n);
            softmax_body(&mut slow, n);
            assert_eq!(fast, slow, "softmax");
            let (mut fast, mut slow) = (vec![0f32; x.len()], vec![0f32; x.len()]);
            gelu_erf(&x, &mut fast);
            gelu_body(&x, &mut slow);
            assert_eq!(fast, slow, "gelu");
            layer_norm(&x, &mut fast, n, &w, &b, 1e-6);
            layer_norm_body(&x, &mut slow, n, &w, &b, 1e-6);
            assert_eq!(fast, slow, "layer norm");
            let (mut fast, mut slow) = (x.clone(), x.clone());
            bias_gelu(&mut fast, n, &b);
            bias_gelu_body(&mut slow, n, &b);
            assert_eq!(fast, slow, "bias + gelu");
            let res = values(4 * n, 5);
            let (mut fast, mut slow) = (x.clone(), x.clone());
            layer_scale(&mut fast, n, &res, &b, &w);
            layer_scale_body(&mut slow, n, &res, &b, &w);
            assert_eq!(fast, slow, "layer scale");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bf16::round_bf16;
    use candle_core::Device;
    use gagavatar_testkit::uniform_values as values;

    /// bf16 attention against an f64 attention of the same rounded q and k: the probabilities
    /// are rounded to bf16 before the value product (relative 2^-9 each, averaging out over
    /// the row), so the output moves by well under 1% of max |v|.
    const BF16_ATTENTION_TOL: f64 = 5e-3;

    #[test]
    fn bf16_attention_matches_f64_attention() -> Result<()> {
        if !gagavatar_testkit::bf16_or_skip("bf16_attention_matches_f64_attention") {
            return Ok(());
        }
        // Two heads, an odd token count across two query blocks, an odd head width.
        let (h, n, d) = (2, ATTN_ROWS + 77, 15);
        let (qv, kv, vv) = (
            values(h * n * d, 1),
            values(h * n * d, 2),
            values(h * n * d, 3),
        );
        // Logits of a few units, as a scaled ViT's are.
        let qv: Vec<f32> = qv.iter().map(|x| 3.0 * x).collect();
        let dev = Device::Cpu;
        let t = |v: &[f32]| Tensor::from_vec(v.to_vec(), (h, n, d), &dev);
        let got: Vec<f32> = attention_bf16(&t(&qv)?, &t(&kv)?, &t(&vv)?)?
            .flatten_all()?
            .to_vec1()?;
        let mut worst = (0, 0.0, 0.0);
        for hh in 0..h {
            for i in 0..n {
                let at = |x: &[f32], r: usize, c: usize| x[(hh * n + r) * d + c];
                let logits: Vec<f64> = (0..n)
                    .map(|j| {
                        (0..d)
                            .map(|c| {
                                round_bf16(at(&qv, i, c)) as f64 * round_bf16(at(&kv, j, c)) as f64
                            })
                            .sum()
                    })
                    .collect();
                let max = logits.iter().cloned().fold(f64::MIN, f64::max);
                let e: Vec<f64> = logits.iter().map(|l| (l - max).exp()).collect();
                let sum: f64 = e.iter().sum();
                for c in 0..d {
                    let want: f64 = (0..n).map(|j| e[j] / sum * at(&vv, j, c) as f64).sum();
                    let o = (hh * n + i) * d + c;
                    let diff = (got[o] as f64 - want).abs();
                    if diff.is_nan() || diff > worst.1 {
                        worst = (o, diff, want);
                    }
                }
            }
        }
        assert!(
            worst.1 <= BF16_ATTENTION_TOL,
            "at {}: expected {}, got {} (tolerance {BF16_ATTENTION_TOL})",
            worst.0,
            worst.2,
            got[worst.0]
        );
        Ok(())
    }

    /// f32 sums of up to a few hundred products in another order than f64's.
    const F32_TOL: f64 = 2e-5;

    fn assert_close_f64(what: &str, want: &[f64], got: &[f32], tol: f64) {
        assert_eq!(want.len(), got.len(), "{what}: lengths");
        for (i, (&w, &g)) in want.iter().zip(got).enumerate() {
            let d = (w - g as f64).abs();
            assert!(
                d <= tol * w.abs().max(1.0),
                "{what} index {i}: expected {w}, actual {g} (tolerance {tol})"
            );
        }
    }

    /// Attention read from the qkv product equals f64 attention of the strided q, k and v, for
    /// two batch items, three heads, an odd token count over two query blocks and odd widths.
    #[test]
    fn attention_from_qkv_matches_f64() -> Result<()> {
        let (b, h, n, d) = (2, 3, ATTN_ROWS + 41, 7);
        let c = h * d;
        let qkv = values(b * n * 3 * c, 9);
        let scale = 1.0 / (d as f64).sqrt();
        let dev = Device::Cpu;
        let t = Tensor::from_vec(qkv.clone(), (b, n, 3 * c), &dev)?;
        let got: Vec<f32> = attention_qkv(&t, h, scale)?.flatten_all()?.to_vec1()?;
        let at = |bi: usize, i: usize, col: usize| qkv[(bi * n + i) * 3 * c + col] as f64;
        let mut want = vec![0f64; b * n * c];
        for bi in 0..b {
            for hh in 0..h {
                for i in 0..n {
                    let logits: Vec<f64> = (0..n)
                        .map(|j| {
                            scale
                                * (0..d)
                                    .map(|k| at(bi, i, hh * d + k) * at(bi, j, c + hh * d + k))
                                    .sum::<f64>()
                        })
                        .collect();
                    let max = logits.iter().cloned().fold(f64::MIN, f64::max);
                    let e: Vec<f64> = logits.iter().map(|l| (l - max).exp()).collect();
                    let sum: f64 = e.iter().sum();
                    for k in 0..d {
                        want[(bi * n + i) * c + hh * d + k] = (0..n)
                            .map(|j| e[j] / sum * at(bi, j, 2 * c + hh * d + k))
                            .sum();
                    }
                }
            }
        }
        assert_close_f64("attention from qkv", &want, &got, F32_TOL);
        let bad = Tensor::zeros((1, 4, 10), candle_core::DType::F32, &dev)?;
        assert!(
            attention_qkv(&bad, 3, 1.0).is_err(),
            "10 columns are not 3 x 3 heads"
        );
        Ok(())
    }

    /// The in-place epilogues against f64: bias, bias + GELU, LayerScale with the residual.
    #[test]
    fn linear_epilogues_match_f64() -> Result<()> {
        let (m, n) = (37, 19);
        let dev = Device::Cpu;
        let (yv, bv, lsv, rv) = (
            values(m * n, 11),
            values(n, 12),
            values(n, 13),
            values(m * n, 14),
        );
        let y = |v: &[f32]| Tensor::from_vec(v.to_vec(), (m, n), &dev);
        let bias = Tensor::from_vec(bv.clone(), n, &dev)?;
        let ls = Tensor::from_vec(lsv.clone(), n, &dev)?;
        let res = Tensor::from_vec(rv.clone(), (1, m, n), &dev)?;
        let gelu64 =
            |v: f64| 0.5 * v * (1.0 + candle_core::cpu::erf::erf_f64(v / std::f64::consts::SQRT_2));
        let each = |f: &dyn Fn(usize, f64) -> f64| -> Vec<f64> {
            (0..m * n)
                .map(|i| f(i, yv[i] as f64 + bv[i % n] as f64))
                .collect()
        };
        let cases: [(&str, LinearEpilogue, Vec<f64>); 3] = [
            ("bias", LinearEpilogue::Bias(&bias), each(&|_, v| v)),
            (
                "bias + gelu",
                LinearEpilogue::BiasGelu(&bias),
                each(&|_, v| gelu64(v)),
            ),
            (
                "layer scale",
                LinearEpilogue::LayerScale {
                    bias: &bias,
                    ls: &ls,
                    residual: &res,
                },
                each(&|i, v| rv[i] as f64 + lsv[i % n] as f64 * v),
            ),
        ];
        for (what, e, want) in cases {
            let t = y(&yv)?;
            linear_epilogue(&t, e)?;
            let got: Vec<f32> = t.flatten_all()?.to_vec1()?;
            assert_close_f64(what, &want, &got, F32_TOL);
        }
        let short = Tensor::from_vec(bv[..n - 1].to_vec(), n - 1, &dev)?;
        assert!(linear_epilogue(&y(&yv)?, LinearEpilogue::Bias(&short)).is_err());
        let wrong = Tensor::zeros((m, n + 1), candle_core::DType::F32, &dev)?;
        let e = LinearEpilogue::LayerScale {
            bias: &bias,
            ls: &ls,
            residual: &wrong,
        };
        assert!(linear_epilogue(&y(&yv)?, e).is_err());
        Ok(())
    }
}
