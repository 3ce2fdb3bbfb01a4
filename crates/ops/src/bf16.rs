//! bf16 matrix products with f32 accumulation, for `--precision bf16` on CPUs with AVX512-BF16
//! (`vdpbf16ps`: one instruction multiplies 16 pairs of bf16 and adds each pair's sum to an f32
//! lane, twice the multiply-adds of an f32 FMA).
//!
//! Operands stay f32 outside this module: activations are rounded to bf16 (nearest-even) when a
//! product starts, weights once when they are packed, and every sum is kept in f32. There is
//! no slow fallback: on a CPU without the instructions the entry points answer
//! [`Bf16Error::Unsupported`], and the caller says so in one line.
//!
//! Layout. The product `C[M, N] = A[M, K] B[K, N]` works on pairs of K: a 32-bit word holds
//! `(x[k], x[k + 1])` for even `k` (low half first). A is bf16 row-major, `K/2` words a row
//! ([`Bf16Rows`]); B is packed in panels of [`NR`] columns, each panel `K/2` rows of `NR`
//! words ([`PackedB`]). The micro-kernel keeps an `MR x NR` tile of C in 24 registers and, for
//! each pair of K, loads two panel vectors and broadcasts one word of each of the `MR` rows.

use crate::conv::elem::SendPtr;
use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp1, Layout, Shape, Tensor};
use rayon::prelude::*;

use crate::storage::contiguous;

/// Rows of C one micro-kernel call computes.
pub const MR: usize = 12;
/// Columns of C one micro-kernel call computes (two 16-lane vectors).
pub const NR: usize = 32;
/// Rows of A one parallel task walks (a multiple of `MR`): its A block stays in L2 while the
/// task runs over its panels of B.
const M_BLOCK: usize = 8 * MR;

/// What can go wrong in a bf16 product.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum Bf16Error {
    /// The CPU lacks the instructions; there is deliberately no slow path.
    #[error("--precision bf16 needs a CPU with AVX512-BF16 (AMD Zen 4 or Intel Cooper Lake / Sapphire Rapids and newer); this one has none: use the default f32")]
    Unsupported,
    /// Operand shapes that do not fit together.
    #[error("bf16 product: {0}")]
    Shape(String),
}

/// Whether this CPU runs the bf16 kernels. `GAGAVATAR_NO_BF16` (any value) says no, to try
/// what a CPU without them does.
pub fn available() -> bool {
    static AVAILABLE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *AVAILABLE.get_or_init(|| std::env::var_os("GAGAVATAR_NO_BF16").is_none() && detected())
}

fn detected() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512bf16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

fn check_available() -> Result<(), Bf16Error> {
    if available() {
        Ok(())
    } else {
        Err(Bf16Error::Unsupported)
    }
}

/// f32 -> bf16 bits as `vcvtne2ps2bf16` rounds: nearest even, subnormals flushed to a signed
/// zero, NaN kept quiet. The vector and scalar conversions must agree bit for bit.
#[inline]
pub fn to_bf16_bits(x: f32) -> u16 {
    let b = x.to_bits();
    if x.is_nan() {
        return ((b >> 16) | 0x40) as u16;
    }
    if b & 0x7f80_0000 == 0 {
        return ((b >> 16) & 0x8000) as u16;
    }
    let rounded = b.wrapping_add(0x7fff + ((b >> 16) & 1));
    (rounded >> 16) as u16
}

/// bf16 bits -> f32 (exact).
#[inline]
pub fn from_bf16_bits(h: u16) -> f32 {
    f32::from_bits((h as u32) << 16)
}

/// `x` rounded to bf16 and back: the value a bf16 product multiplies.
#[inline]
pub fn round_bf16(x: f32) -> f32 {
    from_bf16_bits(to_bf16_bits(x))
}

#[inline]
fn pair(lo: f32, hi: f32) -> u32 {
    to_bf16_bits(lo) as u32 | ((to_bf16_bits(hi) as u32) << 16)
}

/// A in bf16, row-major: `rows` rows of `k.div_ceil(2)` pair words (an odd K is padded with
/// a zero).
#[derive(Debug, Clone)]
pub struct Bf16Rows {
    rows: usize,
    k: usize,
    words: Vec<u32>,
}

impl Bf16Rows {
    /// Rounds `a` ([rows, k] row-major f32) to bf16, in parallel.
    pub fn from_f32(a: &[f32], rows: usize, k: usize) -> Result<Self, Bf16Error> {
        check_available()?;
        if a.len() != rows * k {
            return Err(Bf16Error::Shape(format!(
                "A holds {} values, not {rows} x {k}",
                a.len()
            )));
        }
        let kp = k.div_ceil(2);
        let mut words = vec![0u32; rows * kp];
        if kp > 0 {
            words
                .par_chunks_mut(kp)
                .zip(a.par_chunks(k.max(1)))
                .for_each(|(dst, src)| {
                    // SAFETY: `available()` was checked above.
                    unsafe { x86::convert_row(src, dst) }
                });
        }
        Ok(Self { rows, k, words })
    }

    /// Rows.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Columns (K).
    pub fn k(&self) -> usize {
        self.k
    }
}

/// B in bf16, packed in panels of [`NR`] columns (see the module notes); padded columns and an
/// odd K's last pair hold zeros. Pack weights once and reuse them.
#[derive(Debug, Clone)]
pub struct PackedB {
    k: usize,
    n: usize,
    words: Vec<u32>,
}

impl PackedB {
    /// Packs `B = W^T` for a weight `w` [n, k] row-major (an `nn.Linear` weight, or a conv
    /// weight flattened to [cout, cin * kh * kw]).
    pub fn from_transposed(w: &[f32], n: usize, k: usize) -> Result<Self, Bf16Error> {
        check_available()?;
        if w.len() != n * k {
            return Err(Bf16Error::Shape(format!(
                "weight holds {} values, not {n} x {k}",
                w.len()
            )));
        }
        let mut words = Vec::new();
        pack_b_transposed(w, n, k, &mut words, true);
        Ok(Self { k, n, words })
    }

    /// Packs `b` [k, n] row-major.
    pub fn from_rows(b: &[f32], k: usize, n: usize) -> Result<Self, Bf16Error> {
        check_available()?;
        if b.len() != n * k {
            return Err(Bf16Error::Shape(format!(
                "B holds {} values, not {k} x {n}",
                b.len()
            )));
        }
        let mut words = Vec::new();
        // SAFETY: `available()` was checked above.
        unsafe { pack_b_rows(b, k, n, n, &mut words) };
        Ok(Self { k, n, words })
    }

    /// K.
    pub fn k(&self) -> usize {
        self.k
    }

    /// N (columns of the product).
    pub fn n(&self) -> usize {
        self.n
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.words.len() * 4
    }
}

/// What a product adds to `C`.
#[derive(Debug, Clone, Copy)]
pub enum Bias<'a> {
    None,
    /// One value per column (a linear layer's bias, C = tokens x features).
    PerColumn(&'a [f32]),
    /// One value per row (a convolution's bias, C = channels x pixels).
    PerRow(&'a [f32]),
}

/// `C = A B + bias` with `C` [M, N] row-major f32 (overwritten).
pub fn matmul(a: &Bf16Rows, b: &PackedB, bias: Bias, c: &mut [f32]) -> Result<(), Bf16Error> {
    check_available()?;
    let (m, n, k) = (a.rows, b.n, b.k);
    if a.k != k {
        return Err(Bf16Error::Shape(format!(
            "A has {} columns but B has {k} rows",
            a.k
        )));
    }
    if c.len() != m * n {
        return Err(Bf16Error::Shape(format!(
            "C holds {} values, not {m} x {n}",
            c.len()
        )));
    }
    check_bias(bias, m, n)?;
    // SAFETY: shapes checked above; C is exclusively borrowed.
    unsafe {
        gemm(
            &a.words,
            m,
            k.div_ceil(2),
            &b.words,
            n,
            c.as_mut_ptr(),
            n,
            bias,
            true,
        )
    };
    Ok(())
}

fn check_bias(bias: Bias, m: usize, n: usize) -> Result<(), Bf16Error> {
    let (len, want, what) = match bias {
        Bias::None => return Ok(()),
        Bias::PerColumn(b) => (b.len(), n, "columns"),
        Bias::PerRow(b) => (b.len(), m, "rows"),
    };
    if len != want {
        return Err(Bf16Error::Shape(format!(
            "bias holds {len} values for {want} {what}"
        )));
    }
    Ok(())
}

/// The product on raw operands: `a` holds `m` rows of `kp` pair words, `b` the panels of `n`
/// columns over `kp` pairs (as [`PackedB`] lays them out), `c` rows of stride `ldc`.
/// `parallel` splits the work over rayon tasks (M blocks x panels); callers already inside a
/// parallel task pass `false`.
///
/// # Safety
/// The CPU must have the instructions ([`available`]); `a` must hold `m * kp` words and `b`
/// `n.div_ceil(NR) * kp * NR`; `c` must be valid for writes of `m` rows of `n` values at
/// stride `ldc`, not read or written by anyone else meanwhile; `bias` must fit (`m` or `n`).
#[allow(clippy::too_many_arguments)]
pub(crate) unsafe fn gemm(
    a: &[u32],
    m: usize,
    kp: usize,
    b: &[u32],
    n: usize,
    c: *mut f32,
    ldc: usize,
    bias: Bias,
    parallel: bool,
) {
    if m == 0 || n == 0 {
        return;
    }
    let panels = n.div_ceil(NR);
    let m_blocks = m.div_ceil(M_BLOCK);
    // The tasks that share the pointer write disjoint parts of C (see `matmul`).
    let c = SendPtr(c);
    let task = |task: usize| {
        let (mb, panel) = (task / panels, task % panels);
        let r0 = mb * M_BLOCK;
        let r1 = (r0 + M_BLOCK).min(m);
        let c0 = panel * NR;
        let cols = NR.min(n - c0);
        let bp = &b[panel * kp * NR..(panel + 1) * kp * NR];
        let mut row = r0;
        while row < r1 {
            let rows = MR.min(r1 - row);
            let mut tile = [[0f32; NR]; MR];
            // Rows past `rows` repeat the last valid one; their results are dropped.
            let ptrs: [*const u32; MR] =
                std::array::from_fn(|r| a[(row + r.min(rows - 1)) * kp..].as_ptr());
            // SAFETY: the caller vouched for the CPU and the operand sizes.
            unsafe { x86::kernel(kp, &ptrs, bp.as_ptr(), &mut tile) };
            for (r, t) in tile.iter().enumerate().take(rows) {
                // SAFETY: rows `row..row + rows`, columns `c0..c0 + cols` of C belong to this
                // task alone (tasks partition C by M block and panel).
                let dst = unsafe {
                    std::slice::from_raw_parts_mut(c.get().add((row + r) * ldc + c0), cols)
                };
                match bias {
                    Bias::PerColumn(bias) => {
                        for ((d, &v), &bv) in dst.iter_mut().zip(t).zip(&bias[c0..c0 + cols]) {
                            *d = v + bv;
                        }
                    }
                    Bias::PerRow(bias) => {
                        let bv = bias[row + r];
                        for (d, &v) in dst.iter_mut().zip(t) {
                            *d = v + bv;
                        }
                    }
                    Bias::None => dst.copy_from_slice(&t[..cols]),
                }
            }
            row += rows;
        }
    };
    let tasks = m_blocks * panels;
    if parallel && tasks > 1 {
        // Tasks run M-block-major, so neighbouring tasks (often the same thread) share A rows.
        (0..tasks).into_par_iter().for_each(task);
    } else {
        (0..tasks).for_each(task);
    }
}

/// Packs `B = W^T` for `w` [n, k] row-major into B panels in `dst` (resized); panels in
/// parallel when `parallel` (a weight packed once at load), else on this thread.
pub(crate) fn pack_b_transposed(w: &[f32], n: usize, k: usize, dst: &mut Vec<u32>, parallel: bool) {
    let kp = k.div_ceil(2);
    dst.clear();
    dst.resize(n.div_ceil(NR) * kp * NR, 0);
    if kp == 0 {
        return;
    }
    let panel = |(panel, words): (usize, &mut [u32])| {
        for (p, row) in words.chunks_exact_mut(NR).enumerate() {
            for (lane, word) in row.iter_mut().enumerate() {
                let c = panel * NR + lane;
                if c < n {
                    let src = &w[c * k..(c + 1) * k];
                    *word = pair(src[2 * p], src.get(2 * p + 1).copied().unwrap_or(0.0));
                }
            }
        }
    };
    if parallel {
        dst.par_chunks_mut(kp * NR).enumerate().for_each(panel);
    } else {
        dst.chunks_mut(kp * NR).enumerate().for_each(panel);
    }
}

/// Rounds `rows` rows of `k` f32 values to pair words in `dst` (resized), on this thread.
///
/// # Safety
/// The CPU must have the instructions ([`available`]).
pub(crate) unsafe fn convert_rows(src: &[f32], rows: usize, k: usize, dst: &mut Vec<u32>) {
    let kp = k.div_ceil(2);
    dst.clear();
    dst.resize(rows * kp, 0);
    if kp == 0 {
        return;
    }
    for (d, s) in dst.chunks_exact_mut(kp).zip(src.chunks_exact(k)) {
        // SAFETY: forwarded from the caller.
        unsafe { x86::convert_row(s, d) };
    }
}

/// Packs `k` rows of `n` f32 values (row `r` at `src[r * ld..]`) into B panels in `dst`
/// (resized), as [`PackedB`] lays them out; the vector path converts 16 column pairs at once.
///
/// # Safety
/// The CPU must have the instructions ([`available`]).
pub(crate) unsafe fn pack_b_rows(src: &[f32], k: usize, n: usize, ld: usize, dst: &mut Vec<u32>) {
    let kp = k.div_ceil(2);
    let panels = n.div_ceil(NR);
    dst.clear();
    dst.resize(panels * kp * NR, 0);
    if k == 0 || n == 0 {
        return;
    }
    assert!(
        src.len() >= (k - 1) * ld + n,
        "pack_b_rows: source too short"
    );
    for panel in 0..panels {
        for p in 0..kp {
            for half in 0..2 {
                let c0 = panel * NR + half * 16;
                if c0 >= n {
                    break;
                }
                let cols = 16.min(n - c0);
                let lo = &src[2 * p * ld + c0..][..cols];
                let hi = if 2 * p + 1 < k {
                    Some(&src[(2 * p + 1) * ld + c0..][..cols])
                } else {
                    None
                };
                let out = &mut dst[(panel * kp + p) * NR + half * 16..][..16];
                // SAFETY: forwarded from the caller.
                unsafe { x86::pack16(lo, hi, out) };
            }
        }
    }
}

/// How a model multiplies: `F32` (the default, parity with the release) or `Bf16` (bf16
/// operands, f32 sums; AVX512-BF16 only).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash)]
pub enum Precision {
    #[default]
    F32,
    Bf16,
}

impl Precision {
    /// `Ok` when this CPU runs the precision; the one-line reason otherwise.
    pub fn check(self) -> Result<(), Bf16Error> {
        match self {
            Precision::F32 => Ok(()),
            Precision::Bf16 => check_available(),
        }
    }

    /// `f32` or `bf16`.
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::Bf16 => "bf16",
        }
    }
}

impl std::str::FromStr for Precision {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "f32" | "fp32" => Ok(Precision::F32),
            "bf16" => Ok(Precision::Bf16),
            _ => Err(format!("unknown precision `{s}` (f32 or bf16)")),
        }
    }
}

/// A linear layer with its weight packed for bf16 products: `x [.., in] -> x W^T + bias`.
#[derive(Debug, Clone)]
pub struct Bf16Linear {
    weight: PackedB,
    bias: Option<Vec<f32>>,
}

impl Bf16Linear {
    /// `weight` [out, in] (any layout), `bias` [out]; f32 tensors.
    pub fn new(weight: &Tensor, bias: Option<&Tensor>) -> candle_core::Result<Self> {
        let (n, k) = weight.dims2()?;
        let w: Vec<f32> = weight.flatten_all()?.to_vec1()?;
        let weight = PackedB::from_transposed(&w, n, k).map_err(candle_core::Error::wrap)?;
        let bias = match bias {
            Some(b) => {
                let b: Vec<f32> = b.flatten_all()?.to_vec1()?;
                if b.len() != n {
                    candle_core::bail!(
                        "bf16 linear: bias holds {} values for {n} outputs",
                        b.len()
                    );
                }
                Some(b)
            }
            None => None,
        };
        Ok(Self { weight, bias })
    }

    /// `x` [.., in] f32 on the CPU -> [.., out].
    pub fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        x.contiguous()?.apply_op1_no_bwd(self)
    }

    /// Bytes of the packed weight.
    pub fn bytes(&self) -> usize {
        self.weight.bytes()
    }
}

impl CustomOp1 for Bf16Linear {
    fn name(&self) -> &'static str {
        "bf16-linear"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let CpuStorage::F32(data) = s else {
            candle_core::bail!("bf16 linear: f32 input only, got {:?}", s.dtype());
        };
        let x = contiguous(data, l, "bf16 linear", "input")?;
        let dims = l.dims();
        let k = dims.last().copied().unwrap_or(0);
        if k != self.weight.k {
            candle_core::bail!(
                "bf16 linear: input {dims:?} does not end in the weight's {} inputs",
                self.weight.k
            );
        }
        let m: usize = dims[..dims.len().saturating_sub(1)].iter().product();
        let a = Bf16Rows::from_f32(x, m, k).map_err(candle_core::Error::wrap)?;
        let mut out = vec![0f32; m * self.weight.n];
        let bias = match &self.bias {
            Some(b) => Bias::PerColumn(b),
            None => Bias::None,
        };
        matmul(&a, &self.weight, bias, &mut out).map_err(candle_core::Error::wrap)?;
        let mut shape = dims.to_vec();
        if let Some(last) = shape.last_mut() {
            *last = self.weight.n;
        }
        Ok((CpuStorage::F32(out), Shape::from(shape)))
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{pair, MR, NR};
    use std::arch::x86_64::*;

    /// Rounds one row to pair words; the vector part converts 32 values per instruction.
    ///
    /// # Safety
    /// The CPU must have AVX512F and AVX512-BF16.
    #[target_feature(enable = "avx512f,avx512bf16")]
    pub unsafe fn convert_row(src: &[f32], dst: &mut [u32]) {
        let full = src.len() / 32;
        for i in 0..full {
            let lo = _mm512_loadu_ps(src.as_ptr().add(32 * i));
            let hi = _mm512_loadu_ps(src.as_ptr().add(32 * i + 16));
            // `cvtne2ps` puts its second operand in the low half.
            let packed: __m512i = std::mem::transmute(_mm512_cvtne2ps_pbh(hi, lo));
            _mm512_storeu_si512(dst.as_mut_ptr().add(16 * i) as *mut _, packed);
        }
        for (p, word) in dst.iter_mut().enumerate().skip(16 * full) {
            let lo = src[2 * p];
            let hi = src.get(2 * p + 1).copied().unwrap_or(0.0);
            *word = pair(lo, hi);
        }
    }

    /// Up to 16 columns of two rows -> 16 pair words `(lo[c], hi[c])` (a missing `hi` row or
    /// column is zero).
    ///
    /// # Safety
    /// The CPU must have AVX512F, AVX512BW and AVX512-BF16.
    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    pub unsafe fn pack16(lo: &[f32], hi: Option<&[f32]>, out: &mut [u32]) {
        let cols = lo.len().min(16);
        let mask: __mmask16 = if cols == 16 {
            0xffff
        } else {
            (1u16 << cols) - 1
        };
        let l = _mm512_maskz_loadu_ps(mask, lo.as_ptr());
        let h = match hi {
            Some(hi) => _mm512_maskz_loadu_ps(mask, hi.as_ptr()),
            None => _mm512_setzero_ps(),
        };
        // [lo0..lo15 | hi0..hi15] as bf16, then interleaved to lo0 hi0 lo1 hi1 ...
        let both: __m512i = std::mem::transmute(_mm512_cvtne2ps_pbh(h, l));
        let idx = _mm512_set_epi16(
            31, 15, 30, 14, 29, 13, 28, 12, 27, 11, 26, 10, 25, 9, 24, 8, 23, 7, 22, 6, 21, 5, 20,
            4, 19, 3, 18, 2, 17, 1, 16, 0,
        );
        let words = _mm512_permutexvar_epi16(idx, both);
        _mm512_storeu_si512(out.as_mut_ptr() as *mut _, words);
    }

    /// `tile = sum_p a[r][p] (.) b[p]` over `kp` pairs, `MR x NR`.
    ///
    /// # Safety
    /// The CPU must have AVX512F and AVX512-BF16; each `a[r]` must point at `kp` readable words
    /// and `b` at `kp * NR`.
    #[target_feature(enable = "avx512f,avx512bf16")]
    pub unsafe fn kernel(
        kp: usize,
        a: &[*const u32; MR],
        b: *const u32,
        tile: &mut [[f32; NR]; MR],
    ) {
        let mut lo = [_mm512_setzero_ps(); MR];
        let mut hi = [_mm512_setzero_ps(); MR];
        for p in 0..kp {
            let b0: __m512bh = std::mem::transmute(_mm512_loadu_si512(b.add(p * NR) as *const _));
            let b1: __m512bh =
                std::mem::transmute(_mm512_loadu_si512(b.add(p * NR + 16) as *const _));
            for r in 0..MR {
                let av: __m512bh = std::mem::transmute(_mm512_set1_epi32(*a[r].add(p) as i32));
                lo[r] = _mm512_dpbf16_ps(lo[r], av, b0);
                hi[r] = _mm512_dpbf16_ps(hi[r], av, b1);
            }
        }
        for r in 0..MR {
            _mm512_storeu_ps(tile[r].as_mut_ptr(), lo[r]);
            _mm512_storeu_ps(tile[r].as_mut_ptr().add(16), hi[r]);
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
mod x86 {
    use super::{MR, NR};
    pub unsafe fn convert_row(_src: &[f32], _dst: &mut [u32]) {
        unreachable!("bf16 kernels are only reached after `available()`")
    }
    pub unsafe fn kernel(
        _kp: usize,
        _a: &[*const u32; MR],
        _b: *const u32,
        _t: &mut [[f32; NR]; MR],
    ) {
        unreachable!("bf16 kernels are only reached after `available()`")
    }
    pub unsafe fn pack16(_lo: &[f32], _hi: Option<&[f32]>, _out: &mut [u32]) {
        unreachable!("bf16 kernels are only reached after `available()`")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Sums of bf16 products in f32 against the same products summed in f64: only the f32
    /// accumulation differs, so the error is a few f32 ulps of the sum of magnitudes.
    const ACCUMULATION_TOL: f64 = 1e-5;

    use gagavatar_testkit::uniform_values;

    #[test]
    fn rounding_is_nearest_even() {
        // 1 + 2^-8 lies halfway between 1 and 1 + 2^-7: ties go to the even mantissa (1).
        assert_eq!(round_bf16(1.0 + 1.0 / 256.0), 1.0);
        assert_eq!(round_bf16(1.0 + 3.0 / 256.0), 1.0 + 4.0 / 256.0);
        assert_eq!(round_bf16(-2.5), -2.5);
        assert!(round_bf16(f32::NAN).is_nan());
        assert_eq!(round_bf16(f32::INFINITY), f32::INFINITY);
    }

    #[test]
    fn unsupported_cpu_is_one_error_not_a_slow_path() {
        if !available() {
            assert_eq!(
                Bf16Rows::from_f32(&[0.0; 4], 2, 2).unwrap_err(),
                Bf16Error::Unsupported
            );
            assert_eq!(Precision::Bf16.check(), Err(Bf16Error::Unsupported));
        }
        assert_eq!(Precision::F32.check(), Ok(()));
        assert_eq!(available(), gagavatar_testkit::has_bf16());
    }

    #[test]
    fn product_matches_f64_sum_of_rounded_operands() {
        if !gagavatar_testkit::bf16_or_skip("product_matches_f64_sum_of_rounded_operands") {
            return;
        }
        // Odd K, M and N off the tile sizes, and a panel wider than N.
        for &(m, k, n) in &[
            (1, 1, 1),
            (13, 7, 33),
            (100, 65, 70),
            (25, 128, 96),
            (3, 3, 5),
        ] {
            let seed = (m * 1000 + k * 10 + n) as u64;
            let a = uniform_values(m * k, seed);
            let w = uniform_values(n * k, seed + 1);
            let bias = uniform_values(n, seed + 2);
            let ar = Bf16Rows::from_f32(&a, m, k).unwrap();
            let bt = PackedB::from_transposed(&w, n, k).unwrap();
            let mut c = vec![f32::NAN; m * n];
            matmul(&ar, &bt, Bias::PerColumn(&bias), &mut c).unwrap();
            for i in 0..m {
                for j in 0..n {
                    let mut want = bias[j] as f64;
                    let mut mag = bias[j].abs() as f64;
                    for kk in 0..k {
                        let p = round_bf16(a[i * k + kk]) as f64 * round_bf16(w[j * k + kk]) as f64;
                        want += p;
                        mag += p.abs();
                    }
                    let got = c[i * n + j] as f64;
                    assert!(
                        (got - want).abs() <= ACCUMULATION_TOL * mag.max(1.0),
                        "{m}x{k}x{n} at ({i}, {j}): expected {want}, got {got}"
                    );
                }
            }
            // The same B packed from [k, n] rows gives the same bits.
            let b: Vec<f32> = (0..k * n).map(|i| w[(i % n) * k + i / n]).collect();
            let br = PackedB::from_rows(&b, k, n).unwrap();
            let mut c2 = vec![0.0; m * n];
            matmul(&ar, &br, Bias::PerColumn(&bias), &mut c2).unwrap();
            assert_eq!(c, c2, "{m}x{k}x{n}: from_rows and from_transposed differ");
        }
    }

    #[test]
    fn vector_and_scalar_rounding_agree() {
        if !gagavatar_testkit::bf16_or_skip("vector_and_scalar_rounding_agree") {
            return;
        }
        let r = uniform_values(96, 7);
        // Magnitudes from tiny to huge, plus exact halfway cases.
        let mut a: Vec<f32> = (0..96)
            .map(|i| r[i as usize] * 10f32.powi(i % 12 - 6))
            .collect();
        a[5] = 1.0 + 1.0 / 256.0;
        a[6] = 1.0 + 3.0 / 256.0;
        a[7] = -1e-40;
        a[8] = f32::MIN_POSITIVE;
        let rows = Bf16Rows::from_f32(&a, 1, 96).unwrap();
        for (p, &w) in rows.words.iter().enumerate() {
            assert_eq!(w, pair(a[2 * p], a[2 * p + 1]), "pair {p}");
        }
    }

    #[test]
    fn linear_keeps_leading_dims_and_matches_the_product() -> candle_core::Result<()> {
        if !gagavatar_testkit::bf16_or_skip("linear_keeps_leading_dims_and_matches_the_product") {
            return Ok(());
        }
        let dev = candle_core::Device::Cpu;

        let (k, n) = (37, 45);
        let x = uniform_values(2 * 3 * k, 11);
        let w = uniform_values(n * k, 12);
        let b = uniform_values(n, 13);
        let lin = Bf16Linear::new(
            &Tensor::from_vec(w.clone(), (n, k), &dev)?,
            Some(&Tensor::from_vec(b.clone(), n, &dev)?),
        )?;
        let y = lin.forward(&Tensor::from_vec(x.clone(), (2, 3, k), &dev)?)?;
        assert_eq!(y.dims(), &[2, 3, n]);
        let y: Vec<f32> = y.flatten_all()?.to_vec1()?;
        for row in 0..6 {
            for j in 0..n {
                let mut want = b[j] as f64;
                let mut mag = b[j].abs() as f64;
                for kk in 0..k {
                    let p = round_bf16(x[row * k + kk]) as f64 * round_bf16(w[j * k + kk]) as f64;
                    want += p;
                    mag += p.abs();
                }
                let got = y[row * n + j] as f64;
                assert!(
                    (got - want).abs() <= ACCUMULATION_TOL * mag.max(1.0),
                    "row {row}, column {j}: expected {want}, got {got}"
                );
            }
        }
        // A wrong input width is an error, not a panic.
        assert!(lin
            .forward(&Tensor::zeros((4, k + 1), candle_core::DType::F32, &dev)?)
            .is_err());
        Ok(())
    }

    #[test]
    fn bad_shapes_are_errors() {
        if !gagavatar_testkit::bf16_or_skip("bad_shapes_are_errors") {
            return;
        }
        assert!(matches!(
            Bf16Rows::from_f32(&[0.0; 5], 2, 3),
            Err(Bf16Error::Shape(_))
        ));
        let a = Bf16Rows::from_f32(&[0.0; 6], 2, 3).unwrap();
        let b = PackedB::from_rows(&[0.0; 8], 4, 2).unwrap();
        let mut c = vec![0.0; 4];
        assert!(matches!(
            matmul(&a, &b, Bias::None, &mut c),
            Err(Bf16Error::Shape(_))
        ));
    }
}
