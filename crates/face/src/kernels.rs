//! The CPU kernels of the face networks: NHWC f32, channels in 16-lane blocks ([`crate::simd`]).
//!
//! The networks are MobileNet-like: 1x1 convolutions (a matrix product over pixels, the bulk of
//! the arithmetic), 3x3/5x5 depthwise convolutions, a few small full convolutions, pooling and
//! resampling. Each kernel fuses what TFLite runs as separate ops around it (bias, the residual
//! add with its zero channel padding, the activation), so a BlazeBlock is two passes over memory
//! instead of five. Large ops split their output rows over the face thread pool
//! ([`crate::pool`]); small ones (most ops of the attention branches work on 16x16 maps or
//! smaller) run on the calling thread, since a fork costs more than their arithmetic.

use crate::simd::{dispatch, Lanes, W};
use crate::tensor::Nhwc;

/// Multiply-adds above which an op splits its rows over threads.
const PARALLEL_MACS: usize = 400_000;

/// The activation applied after bias (and residual): TFLite's separate RELU / PRELU /
/// HARD_SWISH ops, fused.
#[derive(Debug, Clone, PartialEq)]
pub enum Act {
    None,
    Relu,
    /// Per-channel slopes for negative inputs, zero-padded to whole 16-lane blocks.
    PRelu(Vec<f32>),
    /// `x * min(max(x + 3, 0), 6) / 6`.
    HardSwish,
}

impl Act {
    /// PReLU with slopes `alpha` (one per channel).
    pub fn prelu(alpha: &[f32]) -> Act {
        let mut a = alpha.to_vec();
        a.resize(alpha.len().div_ceil(W) * W, 0.0);
        Act::PRelu(a)
    }

    /// Applies the activation to the 16 channels starting at `ch` (a multiple of 16).
    #[inline(always)]
    fn apply<L: Lanes>(&self, v: L, ch: usize) -> L {
        match self {
            Act::None => v,
            Act::Relu => v.max(L::zero()),
            Act::PRelu(a) => {
                // SAFETY: `a` is padded to whole blocks and `ch` is a block start inside it.
                let s = unsafe { L::load(a.as_ptr().add(ch)) };
                let z = L::zero();
                v.min(z).fma(s, v.max(z))
            }
            Act::HardSwish => {
                let r6 = v.add(L::splat(3.0)).max(L::zero()).min(L::splat(6.0));
                v.mul(r6).mul(L::splat(1.0 / 6.0))
            }
        }
    }

    /// The activation of one value of channel `ch` (scalar ops).
    pub fn apply_scalar(&self, v: f32, ch: usize) -> f32 {
        match self {
            Act::None => v,
            Act::Relu => v.max(0.0),
            Act::PRelu(a) => v.max(0.0) + a[ch] * v.min(0.0),
            Act::HardSwish => v * (v + 3.0).clamp(0.0, 6.0) / 6.0,
        }
    }
}

/// Runs `f(first_row, rows_slice)` over row bands of `out` (rows of `row_len` values), split
/// over the face thread pool when the op is big enough to pay for it (`macs`: its work in
/// multiply-adds or an equivalent).
pub(crate) fn for_rows<T: Send>(
    out: &mut [T],
    rows: usize,
    row_len: usize,
    macs: usize,
    f: impl Fn(usize, &mut [T]) + Sync,
) {
    let threads = crate::pool::threads();
    if threads <= 1 || macs < PARALLEL_MACS || rows < 2 || row_len == 0 {
        f(0, out);
        return;
    }
    let parts = threads.min(rows);
    let per = rows.div_ceil(parts);
    let bands = out
        .chunks_mut(per * row_len)
        .map(std::sync::Mutex::new)
        .collect::<Vec<std::sync::Mutex<&mut [T]>>>();
    crate::pool::run(bands.len(), &|i| {
        if let Ok(mut band) = bands[i].lock() {
            f(i * per, &mut band);
        }
    });
}

// ---------------------------------------------------------------------------------------------
// Matrix product with fused epilogue: 1x1 convolutions and im2col'd full convolutions.

/// Weights of a convolution as the matrix-product kernel reads them: the reduction axis `k`
/// (input channels, or kh*kw*cin for a full convolution) by the output channels, the output
/// channels cut into 16-lane blocks and the blocks into groups of `nb` that one pass computes.
#[derive(Debug, Clone)]
pub struct Packed {
    pub k: usize,
    pub cout: usize,
    /// Blocks per group (1 to 4).
    pub nb: usize,
    pub groups: usize,
    /// `[groups][k][nb * 16]`, zeros past `cout`.
    pub w: Vec<f32>,
    /// `[groups * nb * 16]`, zeros past `cout`.
    pub bias: Vec<f32>,
}

impl Packed {
    /// Packs `w` given as `[cout][k]` (TFLite's OHWI kernel flattened) and `bias` `[cout]`.
    pub fn new(w: &[f32], bias: &[f32], cout: usize, k: usize) -> Packed {
        assert_eq!(w.len(), cout * k, "kernel size");
        assert_eq!(bias.len(), cout, "bias size");
        let blocks = cout.div_ceil(W);
        let nb = blocks.clamp(1, 4);
        let groups = blocks.div_ceil(nb);
        let gw = nb * W;
        let mut pw = vec![0.0f32; groups * k * gw];
        for o in 0..cout {
            let (g, j) = (o / gw, o % gw);
            for kk in 0..k {
                pw[(g * k + kk) * gw + j] = w[o * k + kk];
            }
        }
        let mut pb = vec![0.0f32; groups * gw];
        pb[..cout].copy_from_slice(bias);
        Packed {
            k,
            cout,
            nb,
            groups,
            w: pw,
            bias: pb,
        }
    }
}

impl Packed {
    /// The same convolution applied to the input scaled per channel: `W diag(s)`.
    pub fn scale_inputs(&self, s: &[f32]) -> Packed {
        assert_eq!(s.len(), self.k, "input scales");
        let mut p = self.clone();
        let gw = self.nb * W;
        for (row, &f) in p.w.chunks_exact_mut(gw).zip(s.iter().cycle()) {
            for v in row {
                *v *= f;
            }
        }
        p
    }

    /// The same convolution with its outputs (bias included) scaled per channel.
    pub fn scale_outputs(&self, s: &[f32]) -> Packed {
        assert_eq!(s.len(), self.cout, "output scales");
        let mut p = self.clone();
        let gw = self.nb * W;
        for row in p.w.chunks_exact_mut(gw).enumerate() {
            let g = row.0 / self.k;
            for (j, v) in row.1.iter_mut().enumerate() {
                if let Some(f) = s.get(g * gw + j) {
                    *v *= f;
                }
            }
        }
        for (v, f) in p.bias.iter_mut().zip(s) {
            *v *= f;
        }
        p
    }
}

/// What a 1x1 convolution adds before its activation: nothing, a map of the same pixels, or the
/// 2x2 max pool of a map twice the size (a stride-2 BlazeBlock's skip). Either has at most the
/// output's channels; the rest count as zero (TFLite's channel padding before the add).
#[derive(Clone, Copy)]
pub enum Residual<'a> {
    None,
    Same(&'a Nhwc),
    MaxPool2(&'a Nhwc),
}

/// `out[p][o] = act(bias[o] + sum_k x[p][k] w[o][k] + res[p][o])` for the pixels of `x`
/// (rows of `k` values, `xs` apart), `ow` output pixels per row.
struct Mm<'a> {
    x: &'a [f32],
    xs: usize,
    pk: &'a Packed,
    res: Residual<'a>,
    ow: usize,
    act: &'a Act,
}

#[inline(always)]
fn mm_rows<L: Lanes>(m: &Mm, p0: usize, out: &mut [f32]) {
    let rows = out.len() / m.pk.cout;
    match m.pk.nb {
        1 => mm_nb::<L, 1, 16>(m, p0, rows, out),
        2 => mm_nb::<L, 2, 14>(m, p0, rows, out),
        3 => mm_nb::<L, 3, 9>(m, p0, rows, out),
        _ => mm_nb::<L, 4, 6>(m, p0, rows, out),
    }
}

dispatch!(fn mm_rows_d(m: &Mm, p0: usize, out: &mut [f32]) = mm_rows);

#[inline(always)]
fn mm_nb<L: Lanes, const NB: usize, const MR: usize>(
    m: &Mm,
    p0: usize,
    rows: usize,
    out: &mut [f32],
) {
    let mut r = 0;
    while r + MR <= rows {
        mm_tile::<L, NB, MR>(m, p0 + r, r, out);
        r += MR;
    }
    // The last pixels in tiles of their own size, so the weights are read a few more times,
    // not once per pixel (the attention branches have 2x2 and 4x4 maps).
    while rows - r >= 6 {
        mm_tile::<L, NB, 6>(m, p0 + r, r, out);
        r += 6;
    }
    match rows - r {
        1 => mm_tile::<L, NB, 1>(m, p0 + r, r, out),
        2 => mm_tile::<L, NB, 2>(m, p0 + r, r, out),
        3 => mm_tile::<L, NB, 3>(m, p0 + r, r, out),
        4 => mm_tile::<L, NB, 4>(m, p0 + r, r, out),
        5 => mm_tile::<L, NB, 5>(m, p0 + r, r, out),
        _ => {}
    }
}

#[inline(always)]
fn mm_tile<L: Lanes, const NB: usize, const MR: usize>(
    m: &Mm,
    p: usize,
    r: usize,
    out: &mut [f32],
) {
    let pk = m.pk;
    let (k, cout, gw) = (pk.k, pk.cout, NB * W);
    debug_assert!((p + MR - 1) * m.xs + k <= m.x.len());
    debug_assert!((r + MR) * cout <= out.len());
    let xp = m.x.as_ptr();
    for g in 0..pk.groups {
        let mut acc = [[L::zero(); NB]; MR];
        // SAFETY: bias holds groups * gw values.
        let b: [L; NB] =
            std::array::from_fn(|j| unsafe { L::load(pk.bias.as_ptr().add(g * gw + j * W)) });
        for a in acc.iter_mut() {
            *a = b;
        }
        let wg = pk.w[g * k * gw..(g + 1) * k * gw].as_ptr();
        for kk in 0..k {
            // SAFETY: kk < k, j * W + 16 <= gw: inside group g's weights.
            let wv: [L; NB] = std::array::from_fn(|j| unsafe { L::load(wg.add(kk * gw + j * W)) });
            for (i, a) in acc.iter_mut().enumerate() {
                // SAFETY: pixel p + i < rows of x (debug-asserted above), kk < k.
                let xv = L::splat(unsafe { *xp.add((p + i) * m.xs + kk) });
                for j in 0..NB {
                    a[j] = xv.fma(wv[j], a[j]);
                }
            }
        }
        for (i, a) in acc.iter().enumerate() {
            for (j, &v) in a.iter().enumerate() {
                let ch = g * gw + j * W;
                if ch >= cout {
                    break;
                }
                let n = (cout - ch).min(W);
                let mut v = v;
                match m.res {
                    Residual::None => {}
                    Residual::Same(r) => {
                        if ch < r.c {
                            // SAFETY: pixel p + i of the residual (same pixels as the output),
                            // channels ch.. clipped to its count.
                            let rv = unsafe {
                                L::load_n(
                                    r.data.as_ptr().add((p + i) * r.c + ch),
                                    (r.c - ch).min(W),
                                )
                            };
                            v = v.add(rv);
                        }
                    }
                    Residual::MaxPool2(r) => {
                        if ch < r.c {
                            let (oy, ox) = ((p + i) / m.ow, (p + i) % m.ow);
                            let nc = (r.c - ch).min(W);
                            let at = |y: usize, x: usize| {
                                // SAFETY: (y, x) inside the residual map (checked by the
                                // callers below), channels ch.. clipped to its count.
                                unsafe {
                                    L::load_n(r.data.as_ptr().add((y * r.w + x) * r.c + ch), nc)
                                }
                            };
                            let (y0, x0) = (2 * oy, 2 * ox);
                            let mut mx = at(y0, x0);
                            if x0 + 1 < r.w {
                                mx = mx.max(at(y0, x0 + 1));
                            }
                            if y0 + 1 < r.h {
                                mx = mx.max(at(y0 + 1, x0));
                                if x0 + 1 < r.w {
                                    mx = mx.max(at(y0 + 1, x0 + 1));
                                }
                            }
                            v = v.add(mx);
                        }
                    }
                }
                let v = m.act.apply(v, ch);
                // SAFETY: row r + i of out, channels ch..ch+n < cout.
                unsafe { v.store_n(out.as_mut_ptr().add((r + i) * cout + ch), n) };
            }
        }
    }
}

/// A 1x1 convolution (stride 1) with fused bias, residual and activation.
pub fn pointwise(x: &Nhwc, pk: &Packed, res: Residual, act: &Act) -> Nhwc {
    assert_eq!(x.c, pk.k, "1x1 convolution input channels");
    let p = x.pixels();
    match res {
        Residual::None => {}
        Residual::Same(r) => {
            assert_eq!((r.h, r.w), (x.h, x.w), "residual size");
            assert!(r.c <= pk.cout, "residual channels");
        }
        Residual::MaxPool2(r) => {
            assert_eq!(
                (r.h.div_ceil(2), r.w.div_ceil(2)),
                (x.h, x.w),
                "pooled residual size"
            );
            assert!(r.c <= pk.cout, "residual channels");
        }
    }
    let mut out = Nhwc::uninit(x.h, x.w, pk.cout);
    let m = Mm {
        x: &x.data,
        xs: x.c,
        pk,
        res,
        ow: x.w,
        act,
    };
    for_rows(&mut out.data, p, pk.cout, p * pk.k * pk.cout, |p0, o| {
        mm_rows_d(&m, p0, o)
    });
    out
}

/// Geometry of a full or depthwise convolution: kernel size, stride, the zero padding before
/// the first row/column, and the output size.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Geom {
    pub kh: usize,
    pub kw: usize,
    pub stride: usize,
    pub pad_top: usize,
    pub pad_left: usize,
    pub oh: usize,
    pub ow: usize,
}

impl Geom {
    /// TFLite SAME padding for an `h x w` input: output `ceil(in / stride)`, the padding split
    /// with the odd one after (so a stride-2 3x3 on an even size pads 0 before, 1 after).
    pub fn same(h: usize, w: usize, k: usize, stride: usize) -> Geom {
        let oh = h.div_ceil(stride);
        let ow = w.div_ceil(stride);
        let ph = ((oh - 1) * stride + k).saturating_sub(h);
        let pw = ((ow - 1) * stride + k).saturating_sub(w);
        Geom {
            kh: k,
            kw: k,
            stride,
            pad_top: ph / 2,
            pad_left: pw / 2,
            oh,
            ow,
        }
    }

    /// TFLite VALID padding.
    pub fn valid(h: usize, w: usize, k: usize, stride: usize) -> Geom {
        Geom {
            kh: k,
            kw: k,
            stride,
            pad_top: 0,
            pad_left: 0,
            oh: (h - k) / stride + 1,
            ow: (w - k) / stride + 1,
        }
    }

    /// Explicit symmetric padding `pad` on every side (a ZeroPadding2D layer before a VALID
    /// convolution).
    pub fn padded(h: usize, w: usize, k: usize, stride: usize, pad: usize) -> Geom {
        Geom {
            kh: k,
            kw: k,
            stride,
            pad_top: pad,
            pad_left: pad,
            oh: (h + 2 * pad - k) / stride + 1,
            ow: (w + 2 * pad - k) / stride + 1,
        }
    }

    /// The range of kernel rows that land inside an input of `size` rows for output row `o`
    /// (`pad` before), and the input row of kernel row 0.
    #[inline(always)]
    fn taps(o: usize, stride: usize, pad: usize, k: usize, size: usize) -> (usize, usize, isize) {
        let i0 = (o * stride) as isize - pad as isize;
        let lo = (-i0).max(0) as usize;
        let hi = ((size as isize - i0).max(0) as usize).min(k);
        (lo, hi.max(lo), i0)
    }
}

/// A full convolution (`pk` packed from an OHWI kernel, `k = kh*kw*cin`) computed as a matrix
/// product over gathered patches, in bands of output rows.
pub fn conv(x: &Nhwc, pk: &Packed, g: Geom, act: &Act) -> Nhwc {
    let kdim = g.kh * g.kw * x.c;
    assert_eq!(pk.k, kdim, "convolution reduction size");
    let p = g.oh * g.ow;
    let mut out = Nhwc::uninit(g.oh, g.ow, pk.cout);
    for_rows(
        &mut out.data,
        g.oh,
        g.ow * pk.cout,
        p * kdim * pk.cout,
        |r0, band| {
            let rows = band.len() / (g.ow * pk.cout);
            // Patches of a few rows at a time, so the buffer stays in L2.
            let step = (32768 / (g.ow * kdim).max(1)).clamp(1, rows.max(1));
            let mut patch = crate::tensor::take(step * g.ow * kdim);
            let mut r = 0;
            while r < rows {
                let n = step.min(rows - r);
                let pb = &mut patch[..n * g.ow * kdim];
                for dy in 0..n {
                    let oy = r0 + r + dy;
                    let (ky0, ky1, iy0) = Geom::taps(oy, g.stride, g.pad_top, g.kh, x.h);
                    for ox in 0..g.ow {
                        let (kx0, kx1, ix0) = Geom::taps(ox, g.stride, g.pad_left, g.kw, x.w);
                        let patch = &mut pb[(dy * g.ow + ox) * kdim..(dy * g.ow + ox + 1) * kdim];
                        if ky1 - ky0 < g.kh || kx1 - kx0 < g.kw {
                            // At the border: the padding taps are zeros.
                            patch.fill(0.0);
                        }
                        for ky in ky0..ky1 {
                            let iy = (iy0 + ky as isize) as usize;
                            let src = (iy * x.w + (ix0 + kx0 as isize) as usize) * x.c;
                            let dst = (ky * g.kw + kx0) * x.c;
                            let len = (kx1 - kx0) * x.c;
                            patch[dst..dst + len].copy_from_slice(&x.data[src..src + len]);
                        }
                    }
                }
                let m = Mm {
                    x: pb,
                    xs: kdim,
                    pk,
                    res: Residual::None,
                    ow: g.ow,
                    act,
                };
                let o = &mut band[r * g.ow * pk.cout..(r + n) * g.ow * pk.cout];
                mm_rows_d(&m, 0, o);
                r += n;
            }
            crate::tensor::give(patch);
        },
    );
    out
}

// ---------------------------------------------------------------------------------------------
// Depthwise convolution.

/// Depthwise weights: `[kh][kw][c]` (TFLite's `[1, kh, kw, c]`), bias `[c]`.
#[derive(Debug, Clone)]
pub struct DwWeights {
    pub kh: usize,
    pub kw: usize,
    pub c: usize,
    pub w: Vec<f32>,
    pub bias: Vec<f32>,
}

struct Dw<'a> {
    x: &'a Nhwc,
    dw: &'a DwWeights,
    g: Geom,
    act: &'a Act,
    /// Add the input back after the activation (`x + act(dw(x))`, stride 1 only).
    add_input: bool,
}

#[inline(always)]
fn dw_rows<L: Lanes>(d: &Dw, r0: usize, out: &mut [f32]) {
    match (d.dw.kh, d.dw.kw) {
        (3, 3) => dw_rows_k::<L, 3>(d, r0, out),
        (5, 5) => dw_rows_k::<L, 5>(d, r0, out),
        _ => dw_rows_k::<L, 0>(d, r0, out),
    }
}

dispatch!(fn dw_rows_d(d: &Dw, r0: usize, out: &mut [f32]) = dw_rows);

/// One output row of one channel block of a depthwise convolution: what the border pixels
/// and the epilogue need.
struct DwRow<'a, L: Lanes> {
    d: &'a Dw<'a>,
    oy: usize,
    cb: usize,
    n: usize,
    /// The row's kernel-row range and the input row of kernel row 0.
    ky: (usize, usize, isize),
    kw: usize,
    wt: &'a [L; 25],
    bias: L,
}

impl<L: Lanes> DwRow<'_, L> {
    /// Pixel `ox`'s sum over the taps inside the input.
    #[inline(always)]
    fn general(&self, ox: usize) -> L {
        let (x, g, c, cb, n) = (self.d.x, self.d.g, self.d.x.c, self.cb, self.n);
        let (ky0, ky1, iy0) = self.ky;
        let kh = self.d.dw.kh;
        let (kx0, kx1, ix0) = Geom::taps(ox, g.stride, g.pad_left, self.kw, x.w);
        let (xp, wp) = (x.data.as_ptr(), self.d.dw.w.as_ptr());
        let mut acc = self.bias;
        for ky in ky0..ky1 {
            let row = (iy0 + ky as isize) as usize * x.w;
            for kx in kx0..kx1 {
                let ix = (ix0 + kx as isize) as usize;
                let t = ky * self.kw + kx;
                let wv = if kh * self.kw <= 25 {
                    self.wt[t]
                } else {
                    // SAFETY: tap t, channels cb..cb+n.
                    unsafe { L::load_n(wp.add(t * c + cb), n) }
                };
                // SAFETY: the tap ranges keep (row, ix) inside the input.
                let v = unsafe { L::load_n(xp.add((row + ix) * c + cb), n) };
                acc = v.fma(wv, acc);
            }
        }
        acc
    }

    /// The activation, and the input added back when asked.
    #[inline(always)]
    fn finish(&self, ox: usize, acc: L) -> L {
        let mut v = self.d.act.apply(acc, self.cb);
        if self.d.add_input {
            let x = self.d.x;
            // SAFETY: stride 1 with the output size equal to the input's: pixel (oy, ox)
            // exists in the input.
            v = v.add(unsafe {
                L::load_n(
                    x.data.as_ptr().add((self.oy * x.w + ox) * x.c + self.cb),
                    self.n,
                )
            });
        }
        v
    }
}

/// `K` is the kernel size when it is known at compile time (3 or 5: the taps unroll), 0 for
/// any other size.
#[inline(always)]
fn dw_rows_k<L: Lanes, const K: usize>(d: &Dw, r0: usize, out: &mut [f32]) {
    let (x, dw, g) = (d.x, d.dw, d.g);
    let (kh, kw) = if K > 0 { (K, K) } else { (dw.kh, dw.kw) };
    let c = x.c;
    let rows = out.len() / (g.ow * c);
    let xp = x.data.as_ptr();
    let wp = dw.w.as_ptr();
    for cb in (0..c).step_by(W) {
        let n = (c - cb).min(W);
        // SAFETY: channels cb..cb+n of the bias.
        let bias = unsafe { L::load_n(dw.bias.as_ptr().add(cb), n) };
        let mut wt = [L::zero(); 25];
        if kh * kw <= 25 {
            for (t, v) in wt.iter_mut().enumerate().take(kh * kw) {
                // SAFETY: tap t < kh*kw, channels cb..cb+n.
                *v = unsafe { L::load_n(wp.add(t * c + cb), n) };
            }
        }
        // Output columns whose taps are all inside the input's width.
        let ox_lo = g.pad_left.div_ceil(g.stride).min(g.ow);
        let ox_hi = if x.w + g.pad_left >= kw {
            ((x.w + g.pad_left - kw) / g.stride + 1).clamp(ox_lo, g.ow)
        } else {
            ox_lo
        };
        // Tap offsets from a window's top-left value (for the interior fast path).
        let mut offs = [0usize; 25];
        if K > 0 {
            for ky in 0..K {
                for kx in 0..K {
                    offs[ky * K + kx] = (ky * x.w + kx) * c;
                }
            }
        }
        for dy in 0..rows {
            let oy = r0 + dy;
            let (ky0, ky1, iy0) = Geom::taps(oy, g.stride, g.pad_top, kh, x.h);
            let out_row = dy * g.ow * c + cb;
            let row = DwRow {
                d,
                oy,
                cb,
                n,
                ky: (ky0, ky1, iy0),
                kw,
                wt: &wt,
                bias,
            };
            if K > 0 && ky0 == 0 && ky1 == K {
                for ox in (0..ox_lo).chain(ox_hi..g.ow) {
                    let v = row.finish(ox, row.general(ox));
                    // SAFETY: output row dy of this band, pixel ox, channels cb..cb+n.
                    unsafe { v.store_n(out.as_mut_ptr().add(out_row + ox * c), n) };
                }
                // Interior: every tap at a fixed offset from the window's corner, four
                // pixels at a time (four independent accumulation chains; one pixel's nine
                // dependent multiply-adds would wait on each other).
                if ox_lo < ox_hi {
                    let first = (iy0 as usize * x.w + ox_lo * g.stride - g.pad_left) * c + cb;
                    let step = g.stride * c;
                    let mut ox = ox_lo;
                    while ox + 4 <= ox_hi {
                        // SAFETY: iy0 >= 0 (full row range) and, for interior columns, every
                        // tap of the window is inside the input; channels cb..cb+n.
                        let p = unsafe { xp.add(first + (ox - ox_lo) * step) };
                        let mut acc = [bias; 4];
                        for t in 0..K * K {
                            for (u, a) in acc.iter_mut().enumerate() {
                                // SAFETY: as above, for pixel ox + u.
                                let v = unsafe { L::load_n(p.add(offs[t] + u * step), n) };
                                *a = v.fma(wt[t], *a);
                            }
                        }
                        for (u, a) in acc.into_iter().enumerate() {
                            let v = row.finish(ox + u, a);
                            // SAFETY: output row dy of this band, pixel ox + u, channels cb..
                            unsafe { v.store_n(out.as_mut_ptr().add(out_row + (ox + u) * c), n) };
                        }
                        ox += 4;
                    }
                    for ox in ox..ox_hi {
                        // SAFETY: as above.
                        let p = unsafe { xp.add(first + (ox - ox_lo) * step) };
                        let mut acc = bias;
                        for t in 0..K * K {
                            // SAFETY: as above.
                            let v = unsafe { L::load_n(p.add(offs[t]), n) };
                            acc = v.fma(wt[t], acc);
                        }
                        let v = row.finish(ox, acc);
                        // SAFETY: output row dy of this band, pixel ox, channels cb..cb+n.
                        unsafe { v.store_n(out.as_mut_ptr().add(out_row + ox * c), n) };
                    }
                }
            } else {
                for ox in 0..g.ow {
                    let v = row.finish(ox, row.general(ox));
                    // SAFETY: output row dy of this band, pixel ox, channels cb..cb+n.
                    unsafe { v.store_n(out.as_mut_ptr().add(out_row + ox * c), n) };
                }
            }
        }
    }
}

/// A depthwise convolution with fused bias and activation.
pub fn depthwise(x: &Nhwc, dw: &DwWeights, g: Geom, act: &Act) -> Nhwc {
    depthwise_ext(x, dw, g, act, false)
}

/// [`depthwise`], with `add_input`: `x + act(dw(x))` (stride 1, same size).
pub fn depthwise_ext(x: &Nhwc, dw: &DwWeights, g: Geom, act: &Act, add_input: bool) -> Nhwc {
    assert_eq!(x.c, dw.c, "depthwise channels");
    assert_eq!((g.kh, g.kw), (dw.kh, dw.kw), "depthwise kernel size");
    if add_input {
        assert_eq!(
            (g.oh, g.ow, g.stride),
            (x.h, x.w, 1),
            "depthwise with its input added"
        );
    }
    let mut out = Nhwc::uninit(g.oh, g.ow, x.c);
    let d = Dw {
        x,
        dw,
        g,
        act,
        add_input,
    };
    let macs = g.oh * g.ow * x.c * g.kh * g.kw;
    for_rows(&mut out.data, g.oh, g.ow * x.c, macs * 4, |r0, o| {
        dw_rows_d(&d, r0, o)
    });
    out
}

// ---------------------------------------------------------------------------------------------
// Pooling, element-wise ops, resampling.

/// 2x2 max pooling with stride 2; output `ceil(size / 2)` (a window at an odd edge takes the
/// values it has, as TFLite's SAME pooling does; on even sizes SAME and VALID agree).
pub fn max_pool2(x: &Nhwc) -> Nhwc {
    let (oh, ow) = (x.h.div_ceil(2), x.w.div_ceil(2));
    let mut out = Nhwc::uninit(oh, ow, x.c);
    for oy in 0..oh {
        for ox in 0..ow {
            let o = &mut out.data[(oy * ow + ox) * x.c..(oy * ow + ox + 1) * x.c];
            o.copy_from_slice(x.at(2 * oy, 2 * ox));
            for (dy, dx) in [(0, 1), (1, 0), (1, 1)] {
                let (iy, ix) = (2 * oy + dy, 2 * ox + dx);
                if iy < x.h && ix < x.w {
                    for (a, &b) in o.iter_mut().zip(x.at(iy, ix)) {
                        if b > *a {
                            *a = b;
                        }
                    }
                }
            }
        }
    }
    out
}

/// `act(a + b)` element by element; `b` may have fewer channels (zero-extended).
pub fn add(a: &Nhwc, b: &Nhwc, act: &Act) -> Nhwc {
    assert_eq!((a.h, a.w), (b.h, b.w), "add sizes");
    assert!(b.c <= a.c, "add channels");
    let mut out = a.clone();
    for p in 0..a.pixels() {
        let o = &mut out.data[p * a.c..(p + 1) * a.c];
        for (v, &w) in o.iter_mut().zip(&b.data[p * b.c..(p + 1) * b.c]) {
            *v += w;
        }
        if *act != Act::None {
            for (ch, v) in o.iter_mut().enumerate() {
                *v = act.apply_scalar(*v, ch);
            }
        }
    }
    out
}

/// `a * s + b` with one scale per channel of `a` (a gated skip connection).
pub fn scale_add(a: &Nhwc, s: &[f32], b: &Nhwc) -> Nhwc {
    assert_eq!((a.h, a.w, a.c), (b.h, b.w, b.c), "scale_add shapes");
    assert_eq!(s.len(), a.c, "scale_add scales");
    let mut out = Nhwc::uninit(a.h, a.w, a.c);
    let c = a.c;
    for_rows(
        &mut out.data,
        a.pixels(),
        c,
        a.data.len() * 4,
        |p0, band| {
            let (a, b) = (
                &a.data[p0 * c..p0 * c + band.len()],
                &b.data[p0 * c..p0 * c + band.len()],
            );
            scale_add_d(a, s, b, c, band)
        },
    );
    out
}

#[inline(always)]
fn scale_add_impl<L: Lanes>(a: &[f32], s: &[f32], b: &[f32], c: usize, out: &mut [f32]) {
    for cb in (0..c).step_by(W) {
        let n = (c - cb).min(W);
        // SAFETY: channels cb..cb+n of the scales.
        let sv = unsafe { L::load_n(s.as_ptr().add(cb), n) };
        for p in 0..out.len() / c {
            let o = p * c + cb;
            // SAFETY: pixel p, channels cb..cb+n, in all three maps (same shapes).
            unsafe {
                let v = L::load_n(a.as_ptr().add(o), n).fma(sv, L::load_n(b.as_ptr().add(o), n));
                v.store_n(out.as_mut_ptr().add(o), n);
            }
        }
    }
}

dispatch!(fn scale_add_d(a: &[f32], s: &[f32], b: &[f32], c: usize, out: &mut [f32]) = scale_add_impl);

/// Applies an activation in place.
pub fn activate(x: &mut Nhwc, act: &Act) {
    let c = x.c;
    for (i, v) in x.data.iter_mut().enumerate() {
        *v = act.apply_scalar(*v, i % c);
    }
}

/// The logistic function (with [`fast_exp`]: within a few f32 ulps of `1 / (1 + e^-v)`),
/// never below `e^-80` (1.8e-35): the exact value for very negative inputs is a denormal,
/// and arithmetic on denormals (the matte's background, resized) runs a hundred times slower.
#[inline(always)]
pub fn sigmoid(v: f32) -> f32 {
    1.0 / (1.0 + fast_exp((-v).min(80.0)))
}

/// [`sigmoid`] of every value, in place (vectorised).
pub fn sigmoid_in_place(v: &mut [f32]) {
    const CHUNK: usize = 4096;
    let rows = v.len().div_ceil(CHUNK);
    // The last row may be short: bands are cut by whole rows, so only the final band is.
    for_rows(v, rows, CHUNK, rows * CHUNK * 20, |_, band| sigmoid_d(band));
}

#[inline(always)]
fn sigmoid_all(v: &mut [f32]) {
    for x in v.iter_mut() {
        *x = sigmoid(*x);
    }
}

dispatch!(fn sigmoid_d(v: &mut [f32]) = plain sigmoid_all);

/// `e^x` for f32 within about 2 ulps, branch-free so loops over it vectorise: `2^n e^r` with
/// `n = round(x / ln 2)`, `|r| <= ln 2 / 2`, and a degree-6 Taylor polynomial for `e^r`.
/// Inputs are clamped to [-87.3, 88.3] (results from about 1.2e-38 to 2.2e38).
#[inline(always)]
pub fn fast_exp(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // 1.5 * 2^23: adding it rounds to an integer (nearest-even) and leaves that integer in
    // the low mantissa bits.
    const ROUND: f32 = 12_582_912.0;
    let x = x.clamp(-87.3, 88.3);
    let t = x * LOG2E + ROUND;
    let n = t - ROUND;
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = 1.0 / 720.0;
    let p = p * r + 1.0 / 120.0;
    let p = p * r + 1.0 / 24.0;
    let p = p * r + 1.0 / 6.0;
    let p = p * r + 0.5;
    let p = p * r + 1.0;
    let p = p * r + 1.0;
    // 2^n: n + 127 (in 1..=254 after the clamp) moved into the exponent field; the bits of
    // ROUND above it shift out.
    let scale = f32::from_bits(t.to_bits().wrapping_add(127) << 23);
    p * scale
}

/// Mean over all pixels per channel (AVERAGE_POOL_2D over the whole map): a 1x1 map.
pub fn global_avg_pool(x: &Nhwc) -> Nhwc {
    let means = channel_means(x);
    Nhwc::from_vec(1, 1, x.c, means)
}

/// Per-channel means, summed in f32 per row and in f64 across rows.
pub fn channel_means(x: &Nhwc) -> Vec<f32> {
    let threads = crate::pool::threads();
    let parts = if x.data.len() * 2 >= PARALLEL_MACS {
        threads.min(x.h).max(1)
    } else {
        1
    };
    let per = x.h.div_ceil(parts);
    let partial: Vec<std::sync::Mutex<Vec<f64>>> = (0..parts)
        .map(|_| std::sync::Mutex::new(vec![0.0f64; x.c]))
        .collect();
    crate::pool::run(parts, &|i| {
        let rows = x.w * x.c;
        let (y0, y1) = (i * per, ((i + 1) * per).min(x.h));
        if let Ok(mut t) = partial[i].lock() {
            channel_sums_d(&x.data[y0 * rows..y1 * rows], x.c, x.w, &mut t);
        }
    });
    let mut total = vec![0.0f64; x.c];
    for p in partial {
        if let Ok(p) = p.into_inner() {
            for (t, v) in total.iter_mut().zip(p) {
                *t += v;
            }
        }
    }
    let n = x.pixels() as f64;
    total.iter().map(|v| (v / n) as f32).collect()
}

/// Adds each channel's sum over `x` (rows of `w` pixels summed in f32) to `total` (f64).
#[inline(always)]
fn channel_sums_impl<L: Lanes>(x: &[f32], c: usize, w: usize, total: &mut [f64]) {
    let row = w * c;
    for cb in (0..c).step_by(W) {
        let n = (c - cb).min(W);
        for r in x.chunks_exact(row) {
            let mut acc = L::zero();
            for p in 0..w {
                // SAFETY: pixel p of the row, channels cb..cb+n.
                acc = acc.add(unsafe { L::load_n(r.as_ptr().add(p * c + cb), n) });
            }
            for (t, v) in total[cb..cb + n].iter_mut().zip(acc.to_array()) {
                *t += v as f64;
            }
        }
    }
}

dispatch!(fn channel_sums_d(x: &[f32], c: usize, w: usize, total: &mut [f64]) = channel_sums_impl);

/// RESIZE_BILINEAR with `half_pixel_centers = true`, `align_corners = false` (TFLite's
/// reference arithmetic: the source coordinate `(o + 0.5) * in / out - 0.5`, neighbours
/// clamped to the map).
pub fn resize_bilinear(x: &Nhwc, oh: usize, ow: usize) -> Nhwc {
    let taps = |o: usize, n_in: usize, n_out: usize| {
        let s = (o as f32 + 0.5) * (n_in as f32 / n_out as f32) - 0.5;
        let f = s.floor();
        let lo = (f as isize).max(0) as usize;
        let hi = (s.ceil() as isize).clamp(0, n_in as isize - 1) as usize;
        (lo.min(n_in - 1), hi, s - lo as f32)
    };
    let ys: Vec<_> = (0..oh).map(|o| taps(o, x.h, oh)).collect();
    let xs: Vec<_> = (0..ow).map(|o| taps(o, x.w, ow)).collect();
    let mut out = Nhwc::uninit(oh, ow, x.c);
    for_rows(
        &mut out.data,
        oh,
        ow * x.c,
        oh * ow * x.c * 8,
        |r0, band| {
            let rows = band.len() / (ow * x.c);
            resize_d(x, &ys[r0..r0 + rows], &xs, band)
        },
    );
    out
}

type Tap = (usize, usize, f32);

#[inline(always)]
fn resize_impl<L: Lanes>(x: &Nhwc, ys: &[Tap], xs: &[Tap], out: &mut [f32]) {
    let (c, ow) = (x.c, xs.len());
    for (oy, &(y0, y1, dy)) in ys.iter().enumerate() {
        let (r0, r1) = (y0 * x.w * c, y1 * x.w * c);
        for (ox, &(x0, x1, dx)) in xs.iter().enumerate() {
            // TFLite's weights and summation order: (y0,x0), (y1,x0), (y0,x1), (y1,x1).
            let w00 = L::splat((1.0 - dy) * (1.0 - dx));
            let w10 = L::splat(dy * (1.0 - dx));
            let w01 = L::splat((1.0 - dy) * dx);
            let w11 = L::splat(dy * dx);
            for cb in (0..c).step_by(W) {
                let n = (c - cb).min(W);
                // SAFETY: the taps are inside the map (clamped), channels cb..cb+n; the output
                // pixel (oy, ox) exists.
                unsafe {
                    let p = x.data.as_ptr();
                    let a = L::load_n(p.add(r0 + x0 * c + cb), n);
                    let b = L::load_n(p.add(r0 + x1 * c + cb), n);
                    let cc = L::load_n(p.add(r1 + x0 * c + cb), n);
                    let d = L::load_n(p.add(r1 + x1 * c + cb), n);
                    let v = a.mul(w00).add(cc.mul(w10)).add(b.mul(w01)).add(d.mul(w11));
                    v.store_n(out.as_mut_ptr().add((oy * ow + ox) * c + cb), n);
                }
            }
        }
    }
}

dispatch!(fn resize_d(x: &Nhwc, ys: &[Tap], xs: &[Tap], out: &mut [f32]) = resize_impl);

/// DEPTH_TO_SPACE with block 2: `out[2y+i][2x+j][c] = in[y][x][(2i+j)*C + c]`.
pub fn depth_to_space2(x: &Nhwc) -> Nhwc {
    assert_eq!(x.c % 4, 0, "depth_to_space channels");
    let c = x.c / 4;
    let (oh, ow) = (x.h * 2, x.w * 2);
    let mut out = Nhwc::uninit(oh, ow, c);
    for y in 0..x.h {
        for xx in 0..x.w {
            let src = x.at(y, xx);
            for i in 0..2 {
                for j in 0..2 {
                    let o = ((2 * y + i) * ow + 2 * xx + j) * c;
                    out.data[o..o + c].copy_from_slice(&src[(2 * i + j) * c..(2 * i + j + 1) * c]);
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rnd(n: usize, seed: u64) -> Vec<f32> {
        let mut s = seed.wrapping_mul(0x9e3779b97f4a7c15) | 1;
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect()
    }

    /// Worst absolute difference, with its index (a NaN is an infinite difference).
    fn worst(a: &[f32], b: &[f32]) -> (usize, f32) {
        let (i, d) = gagavatar_testkit::worst_abs_diff(a, b);
        (i, d as f32)
    }

    /// f32 sums of a few hundred terms of size ~1 against an f64 reference.
    const TOL: f32 = 2e-5;

    fn naive_conv(x: &Nhwc, w: &[f32], b: &[f32], cout: usize, g: Geom, dw: bool) -> Nhwc {
        let mut out = Nhwc::zeros(g.oh, g.ow, cout);
        for oy in 0..g.oh {
            for ox in 0..g.ow {
                for o in 0..cout {
                    let mut s = b[o] as f64;
                    for ky in 0..g.kh {
                        for kx in 0..g.kw {
                            let iy = (oy * g.stride + ky) as isize - g.pad_top as isize;
                            let ix = (ox * g.stride + kx) as isize - g.pad_left as isize;
                            if iy < 0 || ix < 0 || iy >= x.h as isize || ix >= x.w as isize {
                                continue;
                            }
                            let px = x.at(iy as usize, ix as usize);
                            if dw {
                                s += px[o] as f64 * w[(ky * g.kw + kx) * cout + o] as f64;
                            } else {
                                for ci in 0..x.c {
                                    s += px[ci] as f64
                                        * w[((o * g.kh + ky) * g.kw + kx) * x.c + ci] as f64;
                                }
                            }
                        }
                    }
                    out.data[(oy * g.ow + ox) * cout + o] = s as f32;
                }
            }
        }
        out
    }

    #[test]
    fn pointwise_matches_naive_with_residual_and_prelu() {
        for &(h, w, cin, cout, cr) in &[
            (5, 7, 16, 16, 16),
            (9, 4, 24, 28, 24),
            (3, 3, 88, 96, 88),
            (1, 1, 32, 1404, 0),
            (13, 11, 42, 48, 0),
        ] {
            let x = Nhwc::from_vec(h, w, cin, rnd(h * w * cin, 1));
            let wt = rnd(cout * cin, 2);
            let b = rnd(cout, 3);
            let res = Nhwc::from_vec(h, w, cr, rnd(h * w * cr, 4));
            let alpha = rnd(cout, 5);
            let act = Act::prelu(&alpha);
            let pk = Packed::new(&wt, &b, cout, cin);
            let r = if cr > 0 {
                Residual::Same(&res)
            } else {
                Residual::None
            };
            let got = pointwise(&x, &pk, r, &act);
            let g = Geom::valid(h, w, 1, 1);
            let mut want = naive_conv(&x, &wt, &b, cout, g, false);
            for p in 0..h * w {
                for o in 0..cout {
                    let v = &mut want.data[p * cout + o];
                    if o < cr {
                        *v += res.data[p * cr + o];
                    }
                    *v = act.apply_scalar(*v, o);
                }
            }
            let (i, d) = worst(&got.data, &want.data);
            assert!(
                d < TOL,
                "{h}x{w} {cin}->{cout}: index {i}: {} vs {}",
                got.data[i],
                want.data[i]
            );
        }
    }

    #[test]
    fn pooled_residual_equals_max_pool_then_add() {
        for &(h, w) in &[(8usize, 6usize), (7, 5)] {
            let x = Nhwc::from_vec(
                h.div_ceil(2),
                w.div_ceil(2),
                24,
                rnd(h.div_ceil(2) * w.div_ceil(2) * 24, 21),
            );
            let big = Nhwc::from_vec(h, w, 20, rnd(h * w * 20, 22));
            let pk = Packed::new(&rnd(28 * 24, 23), &rnd(28, 24), 28, 24);
            let fused = pointwise(&x, &pk, Residual::MaxPool2(&big), &Act::Relu);
            let pooled = max_pool2(&big);
            let two_step = pointwise(&x, &pk, Residual::Same(&pooled), &Act::Relu);
            assert_eq!(fused.data, two_step.data, "{h}x{w}");
        }
    }

    #[test]
    fn conv_matches_naive_same_valid_and_padded() {
        let x = Nhwc::from_vec(17, 14, 3, rnd(17 * 14 * 3, 7));
        for (k, s, g, cout) in [
            (5, 2, Geom::same(17, 14, 5, 2), 24),
            (3, 2, Geom::same(17, 14, 3, 2), 16),
            (3, 2, Geom::padded(17, 14, 3, 2, 1), 32),
            (3, 3, Geom::valid(17, 14, 3, 3), 40),
            (2, 2, Geom::valid(17, 14, 2, 2), 10),
        ] {
            assert_eq!((g.kh, g.stride), (k, s));
            let wt = rnd(cout * k * k * 3, 8);
            let b = rnd(cout, 9);
            let pk = Packed::new(&wt, &b, cout, k * k * 3);
            let got = conv(&x, &pk, g, &Act::Relu);
            let mut want = naive_conv(&x, &wt, &b, cout, g, false);
            activate(&mut want, &Act::Relu);
            let (i, d) = worst(&got.data, &want.data);
            assert!(
                d < TOL,
                "k{k} s{s}: index {i}: {} vs {}",
                got.data[i],
                want.data[i]
            );
        }
    }

    #[test]
    fn depthwise_matches_naive() {
        for &(h, w, c, k, s) in &[
            (16, 16, 24, 3, 1),
            (16, 16, 28, 3, 2),
            (9, 7, 42, 3, 2),
            (12, 12, 16, 5, 1),
            (6, 5, 20, 4, 1),
            (2, 2, 16, 3, 1),
            (1, 3, 8, 5, 2),
            (3, 2, 40, 5, 1),
        ] {
            let x = Nhwc::from_vec(h, w, c, rnd(h * w * c, 11));
            let wt = rnd(k * k * c, 12);
            let b = rnd(c, 13);
            let dw = DwWeights {
                kh: k,
                kw: k,
                c,
                w: wt.clone(),
                bias: b.clone(),
            };
            let mut geoms = vec![Geom::same(h, w, k, s)];
            if h + 2 >= k && w + 2 >= k {
                geoms.push(Geom::padded(h, w, k, s, 1));
            }
            for g in geoms {
                let got = depthwise(&x, &dw, g, &Act::HardSwish);
                let mut want = naive_conv(&x, &wt, &b, c, g, true);
                activate(&mut want, &Act::HardSwish);
                let (i, d) = worst(&got.data, &want.data);
                assert!(
                    d < TOL,
                    "{h}x{w}x{c} k{k} s{s}: index {i}: {} vs {}",
                    got.data[i],
                    want.data[i]
                );
            }
        }
    }

    /// The AVX-512 kernels against the portable ones on the same data (only FMA rounding
    /// differs).
    #[test]
    fn avx512_and_portable_kernels_agree() {
        #[cfg(target_arch = "x86_64")]
        {
            let avx512 = crate::simd::level() == crate::simd::Level::Avx512;
            if !gagavatar_testkit::optional_path(
                "avx512_and_portable_kernels_agree",
                avx512,
                "the AVX-512 kernels are off (no AVX-512F, or GAGAVATAR_NO_AVX512)",
                gagavatar_testkit::REQUIRE_AVX512,
            ) {
                return;
            }
            use crate::simd::{Arr, Zmm};
            let x = Nhwc::from_vec(9, 7, 40, rnd(9 * 7 * 40, 31));
            let res = Nhwc::from_vec(18, 14, 36, rnd(18 * 14 * 36, 32));
            let pk = Packed::new(&rnd(50 * 40, 33), &rnd(50, 34), 50, 40);
            let act = Act::prelu(&rnd(50, 35));
            let m = Mm {
                x: &x.data,
                xs: 40,
                pk: &pk,
                res: Residual::MaxPool2(&res),
                ow: 7,
                act: &act,
            };
            let mut a = vec![0.0f32; 63 * 50];
            let mut b = a.clone();
            mm_rows::<Arr>(&m, 0, &mut a);
            #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
            fn z_mm(m: &Mm, out: &mut [f32]) {
                mm_rows::<Zmm>(m, 0, out)
            }
            // SAFETY: AVX-512F detected above.
            unsafe { z_mm(&m, &mut b) };
            let (i, d) = worst(&a, &b);
            assert!(d < 1e-5, "1x1: index {i}: {} vs {}", a[i], b[i]);

            let dw = DwWeights {
                kh: 5,
                kw: 5,
                c: 40,
                w: rnd(25 * 40, 36),
                bias: rnd(40, 37),
            };
            let d = Dw {
                x: &x,
                dw: &dw,
                g: Geom::same(9, 7, 5, 2),
                act: &Act::HardSwish,
                add_input: false,
            };
            let mut a = vec![0.0f32; 5 * 4 * 40];
            let mut b = a.clone();
            dw_rows::<Arr>(&d, 0, &mut a);
            #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
            fn z_dw(d: &Dw, out: &mut [f32]) {
                dw_rows::<Zmm>(d, 0, out)
            }
            // SAFETY: as above.
            unsafe { z_dw(&d, &mut b) };
            let (i, e) = worst(&a, &b);
            assert!(e < 1e-5, "depthwise: index {i}: {} vs {}", a[i], b[i]);
        }
    }

    #[test]
    fn fast_exp_and_sigmoid_are_accurate() {
        let mut worst = 0.0f64;
        let mut x = -87.0f32;
        while x < 88.0 {
            let want = (x as f64).exp();
            let rel = ((fast_exp(x) as f64 - want) / want).abs();
            worst = worst.max(rel);
            x += 0.0137;
        }
        assert!(worst < 5e-7, "worst relative error {worst}");
        assert!(fast_exp(-200.0) < 1e-37);
        assert!((sigmoid(0.0) - 0.5).abs() < 1e-7);
        assert!(sigmoid(-200.0).is_normal() && sigmoid(-200.0) < 1e-34 && sigmoid(200.0) <= 1.0);
    }

    #[test]
    fn same_padding_is_tflite_asymmetric() {
        let g = Geom::same(128, 128, 5, 2);
        assert_eq!((g.pad_top, g.oh), (1, 64));
        let g = Geom::same(128, 128, 3, 2);
        assert_eq!((g.pad_top, g.oh), (0, 64));
        let g = Geom::same(64, 64, 3, 1);
        assert_eq!((g.pad_top, g.oh), (1, 64));
    }

    #[test]
    fn pooling_resize_and_depth_to_space() {
        let x = Nhwc::from_vec(3, 3, 1, (0..9).map(|v| v as f32).collect());
        assert_eq!(max_pool2(&x).data, vec![4.0, 5.0, 7.0, 8.0]);
        let y = Nhwc::from_vec(1, 2, 1, vec![0.0, 4.0]);
        // half-pixel centres: source x = -0.25 (clamped), 0.25, 0.75, 1.25 (clamped)
        assert_eq!(resize_bilinear(&y, 1, 4).data, vec![0.0, 1.0, 3.0, 4.0]);
        let z = Nhwc::from_vec(1, 1, 4, vec![1.0, 2.0, 3.0, 4.0]);
        assert_eq!(depth_to_space2(&z).data, vec![1.0, 2.0, 3.0, 4.0]);
        let p = global_avg_pool(&x);
        assert_eq!(p.data, vec![4.0]);
    }
}
