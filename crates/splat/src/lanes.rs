//! 16-lane vectors for the compositing kernels: one lane per pixel of a 4x4 pixel block, or
//! one per channel of a 16-channel block.
//!
//! The kernels in [`crate::raster`] are written once against [`Lanes`] and compiled twice: with
//! [`P16`] (plain arrays, any [`Real`], vectorised by the compiler where it can) and, on CPUs with
//! AVX-512F, with [`Z16`] (one `__m512` register, f32 only). Every operation is an IEEE
//! operation lane by lane with the same rounding in both (Rust never fuses a*b+c on its own and
//! both fuse exactly where `mul_add` says so, `min`/`max` and comparisons are defined
//! identically below, and the exp is the same sequence of operations), so both compilations
//! give bit-identical results.

use crate::real::Real;

/// `GAGAVATAR_NO_AVX512=1` forces the array kernels (to compare paths or debug).
pub(crate) fn simd_disabled() -> bool {
    std::env::var_os("GAGAVATAR_NO_AVX512").is_some_and(|v| v != "0")
}

/// Lanes per vector: the pixels of a 4x4 block.
pub const WIDTH: usize = 16;
/// One bit per lane.
pub type Mask = u16;
/// Every lane.
pub const ALL: Mask = u16::MAX;

/// Mask of the first `n` lanes.
#[inline(always)]
pub fn first(n: usize) -> Mask {
    if n >= WIDTH {
        ALL
    } else {
        ((1u32 << n) - 1) as Mask
    }
}

pub trait Lanes<T: Real>: Copy + 'static {
    /// Per-lane tile-list positions.
    type Idx: Copy;
    fn splat(v: T) -> Self;
    #[inline(always)]
    fn zero() -> Self {
        Self::splat(T::ZERO)
    }
    /// `base + i` in lane i.
    fn iota_plus(base: T) -> Self;
    /// The first `min(16, s.len())` values of `s`, zeros after.
    fn load_first(s: &[T]) -> Self;
    /// 16 values from `s` (which must hold at least 16).
    fn load(s: &[T]) -> Self;
    /// Stores the lanes in `m` to the same positions of `d` (which must hold every lane in `m`).
    fn store_masked(self, d: &mut [T], m: Mask);
    fn to_array(self) -> [T; WIDTH];
    fn from_array(a: [T; WIDTH]) -> Self;
    fn add(self, o: Self) -> Self;
    fn sub(self, o: Self) -> Self;
    fn mul(self, o: Self) -> Self;
    fn div(self, o: Self) -> Self;
    /// `self < o ? self : o` per lane (the second operand when either is NaN).
    fn min(self, o: Self) -> Self;
    /// `self > o ? self : o` per lane (the second operand when either is NaN).
    fn max(self, o: Self) -> Self;
    fn neg(self) -> Self;
    /// The correctly rounded square root per lane.
    fn sqrt(self) -> Self;
    /// Rounds up to an integer per lane.
    fn ceil(self) -> Self;
    /// The natural log of positive normal lanes to about 1e-6 relative, for bounds only: the
    /// last bits may differ between the two kinds of lanes.
    #[inline(always)]
    fn ln_bound(self) -> Self {
        Self::from_array(self.to_array().map(|x| T::lit(x.as_f64().ln())))
    }
    /// `self * a + b` with one rounding.
    fn mul_add(self, a: Self, b: Self) -> Self;
    fn eq(self, o: Self) -> Mask;
    fn le(self, o: Self) -> Mask;
    fn lt(self, o: Self) -> Mask;
    fn gt(self, o: Self) -> Mask;
    fn ge(self, o: Self) -> Mask;
    /// `a` in the lanes of `m`, `b` elsewhere.
    fn select(m: Mask, a: Self, b: Self) -> Self;
    /// [`Real::fexp`] per lane.
    fn exp(self) -> Self;
    /// [`Lanes::exp`] of several vectors, step by step side by side so that their long
    /// dependency chains overlap.
    #[inline(always)]
    fn exp_n<const N: usize>(x: [Self; N]) -> [Self; N] {
        let mut r = x;
        for i in 0..N {
            r[i] = x[i].exp();
        }
        r
    }
    /// Sum of the lanes by halving: lanes i and i+8, then i and i+4, i+2, i+1.
    fn hsum(self) -> T;
    fn idx_zero() -> Self::Idx;
    /// `k` in the lanes of `m`, `cur` elsewhere.
    fn idx_set(m: Mask, k: u32, cur: Self::Idx) -> Self::Idx;
    /// Lanes whose index is greater than `k`.
    fn idx_gt(cur: Self::Idx, k: u32) -> Mask;
    fn idx_load_first(s: &[u32]) -> Self::Idx;
    fn idx_store_masked(cur: Self::Idx, d: &mut [u32], m: Mask);
    /// The 16x16 transpose: lane `i` of result `j` is lane `j` of `rows[i]`.
    #[inline(always)]
    fn transpose(rows: [Self; WIDTH]) -> [Self; WIDTH] {
        // (Plain loops: closures would not inherit the kernels' target features.)
        let mut a = [[T::ZERO; WIDTH]; WIDTH];
        for (i, r) in rows.iter().enumerate() {
            a[i] = r.to_array();
        }
        let mut out = rows;
        for (j, o) in out.iter_mut().enumerate() {
            let mut col = [T::ZERO; WIDTH];
            for i in 0..WIDTH {
                col[i] = a[i][j];
            }
            *o = Self::from_array(col);
        }
        out
    }
    /// Writes, in order, every position `i` with `masks[i] & bit != 0` to the front of `out`
    /// (which must hold `masks.len() + 16` values; what follows the positions is scratch) and
    /// returns how many there are.
    #[inline(always)]
    fn positions_with(masks: &[u32], bit: u32, out: &mut [u32]) -> usize {
        assert!(out.len() >= masks.len() + WIDTH);
        let mut n = 0;
        for (i, &m) in masks.iter().enumerate() {
            // Written every time, kept only when the bit is set: no branch to mispredict.
            out[n] = i as u32;
            n += (m & bit != 0) as usize;
        }
        n
    }
}

/// Portable lanes: a plain array.
#[derive(Clone, Copy, Debug)]
pub struct P16<T>(pub [T; WIDTH]);

impl<T: Real> P16<T> {
    #[inline(always)]
    fn map2(self, o: Self, f: impl Fn(T, T) -> T) -> Self {
        let mut r = self.0;
        for i in 0..WIDTH {
            r[i] = f(self.0[i], o.0[i]);
        }
        P16(r)
    }
    #[inline(always)]
    fn cmp(self, o: Self, f: impl Fn(T, T) -> bool) -> Mask {
        let mut m = 0;
        for i in 0..WIDTH {
            m |= (f(self.0[i], o.0[i]) as Mask) << i;
        }
        m
    }
}

impl<T: Real> Lanes<T> for P16<T> {
    type Idx = [u32; WIDTH];
    #[inline(always)]
    fn splat(v: T) -> Self {
        P16([v; WIDTH])
    }
    #[inline(always)]
    fn iota_plus(base: T) -> Self {
        P16(std::array::from_fn(|i| base + T::lit(i as f64)))
    }
    #[inline(always)]
    fn load_first(s: &[T]) -> Self {
        let mut r = [T::ZERO; WIDTH];
        let n = s.len().min(WIDTH);
        r[..n].copy_from_slice(&s[..n]);
        P16(r)
    }
    #[inline(always)]
    fn load(s: &[T]) -> Self {
        let mut r = [T::ZERO; WIDTH];
        r.copy_from_slice(&s[..WIDTH]);
        P16(r)
    }
    #[inline(always)]
    fn store_masked(self, d: &mut [T], m: Mask) {
        for i in 0..WIDTH {
            if m >> i & 1 != 0 {
                d[i] = self.0[i];
            }
        }
    }
    #[inline(always)]
    fn to_array(self) -> [T; WIDTH] {
        self.0
    }
    #[inline(always)]
    fn from_array(a: [T; WIDTH]) -> Self {
        P16(a)
    }
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        self.map2(o, |a, b| a + b)
    }
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        self.map2(o, |a, b| a - b)
    }
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        self.map2(o, |a, b| a * b)
    }
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        self.map2(o, |a, b| a / b)
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        self.map2(o, |a, b| if a < b { a } else { b })
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        self.map2(o, |a, b| if a > b { a } else { b })
    }
    #[inline(always)]
    fn neg(self) -> Self {
        P16(self.0.map(|a| -a))
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        P16(self.0.map(T::sqrt))
    }
    #[inline(always)]
    fn ceil(self) -> Self {
        P16(self.0.map(T::ceil))
    }
    #[inline(always)]
    fn mul_add(self, a: Self, b: Self) -> Self {
        let mut r = self.0;
        for i in 0..WIDTH {
            r[i] = self.0[i].mul_add(a.0[i], b.0[i]);
        }
        P16(r)
    }
    #[inline(always)]
    fn eq(self, o: Self) -> Mask {
        self.cmp(o, |a, b| a == b)
    }
    #[inline(always)]
    fn le(self, o: Self) -> Mask {
        self.cmp(o, |a, b| a <= b)
    }
    #[inline(always)]
    fn lt(self, o: Self) -> Mask {
        self.cmp(o, |a, b| a < b)
    }
    #[inline(always)]
    fn gt(self, o: Self) -> Mask {
        self.cmp(o, |a, b| a > b)
    }
    #[inline(always)]
    fn ge(self, o: Self) -> Mask {
        self.cmp(o, |a, b| a >= b)
    }
    #[inline(always)]
    fn select(m: Mask, a: Self, b: Self) -> Self {
        P16(std::array::from_fn(|i| {
            if m >> i & 1 != 0 {
                a.0[i]
            } else {
                b.0[i]
            }
        }))
    }
    #[inline(always)]
    fn exp(self) -> Self {
        P16(self.0.map(T::fexp))
    }
    #[inline(always)]
    fn hsum(self) -> T {
        let mut a = self.0;
        let mut width = WIDTH / 2;
        while width > 0 {
            for i in 0..width {
                a[i] += a[i + width];
            }
            width /= 2;
        }
        a[0]
    }
    #[inline(always)]
    fn idx_zero() -> Self::Idx {
        [0; WIDTH]
    }
    #[inline(always)]
    fn idx_set(m: Mask, k: u32, cur: Self::Idx) -> Self::Idx {
        std::array::from_fn(|i| if m >> i & 1 != 0 { k } else { cur[i] })
    }
    #[inline(always)]
    fn idx_gt(cur: Self::Idx, k: u32) -> Mask {
        let mut m = 0;
        for i in 0..WIDTH {
            m |= ((cur[i] > k) as Mask) << i;
        }
        m
    }
    #[inline(always)]
    fn idx_load_first(s: &[u32]) -> Self::Idx {
        let mut r = [0; WIDTH];
        let n = s.len().min(WIDTH);
        r[..n].copy_from_slice(&s[..n]);
        r
    }
    #[inline(always)]
    fn idx_store_masked(cur: Self::Idx, d: &mut [u32], m: Mask) {
        for i in 0..WIDTH {
            if m >> i & 1 != 0 {
                d[i] = cur[i];
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
pub use avx512::Z16;

#[cfg(target_arch = "x86_64")]
mod avx512 {
    //! Every method is only ever inlined into functions compiled with AVX-512F enabled, and
    //! only called after `is_x86_feature_detected!("avx512f")`; that is the safety argument of
    //! each `unsafe` block below.

    use super::{Lanes, Mask, WIDTH};
    use std::arch::x86_64::*;

    /// 16 f32 lanes in one AVX-512 register.
    #[derive(Clone, Copy, Debug)]
    pub struct Z16(__m512);

    impl Lanes<f32> for Z16 {
        type Idx = __m512i;
        #[inline(always)]
        fn splat(v: f32) -> Self {
            // SAFETY: see the module comment.
            Z16(unsafe { _mm512_set1_ps(v) })
        }
        #[inline(always)]
        fn iota_plus(base: f32) -> Self {
            // SAFETY: see the module comment.
            unsafe {
                let lanes = _mm512_setr_ps(
                    0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0, 14.0,
                    15.0,
                );
                Z16(_mm512_add_ps(_mm512_set1_ps(base), lanes))
            }
        }
        #[inline(always)]
        fn load_first(s: &[f32]) -> Self {
            let m = super::first(s.len());
            // SAFETY: the masked load reads only the first min(16, len) elements.
            Z16(unsafe { _mm512_maskz_loadu_ps(m, s.as_ptr()) })
        }
        #[inline(always)]
        fn load(s: &[f32]) -> Self {
            let s = &s[..WIDTH];
            // SAFETY: 16 elements are in bounds.
            Z16(unsafe { _mm512_loadu_ps(s.as_ptr()) })
        }
        #[inline(always)]
        fn store_masked(self, d: &mut [f32], m: Mask) {
            debug_assert!(m == 0 || d.len() > (15 - m.leading_zeros()) as usize);
            // SAFETY: the caller passes a slice that holds every lane in m; other lanes are not
            // written (masked stores suppress them, faults included).
            unsafe { _mm512_mask_storeu_ps(d.as_mut_ptr(), m, self.0) }
        }
        #[inline(always)]
        fn to_array(self) -> [f32; WIDTH] {
            let mut a = [0.0; WIDTH];
            // SAFETY: 16 floats into a 16-float array.
            unsafe { _mm512_storeu_ps(a.as_mut_ptr(), self.0) };
            a
        }
        #[inline(always)]
        fn from_array(a: [f32; WIDTH]) -> Self {
            Self::load(&a)
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            // SAFETY: see the module comment.
            Z16(unsafe { _mm512_add_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            // SAFETY: see the module comment.
            Z16(unsafe { _mm512_sub_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn mul(self, o: Self) -> Self {
            // SAFETY: see the module comment.
            Z16(unsafe { _mm512_mul_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn div(self, o: Self) -> Self {
            // SAFETY: see the module comment.
            Z16(unsafe { _mm512_div_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn min(self, o: Self) -> Self {
            // SAFETY: see the module comment. (vminps returns the second operand when either
            // is NaN, as P16::min does.)
            Z16(unsafe { _mm512_min_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn max(self, o: Self) -> Self {
            // SAFETY: see the module comment.
            Z16(unsafe { _mm512_max_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn neg(self) -> Self {
            // SAFETY: see the module comment. Flips the sign bit, as unary minus does.
            Z16(unsafe {
                _mm512_castsi512_ps(_mm512_xor_si512(
                    _mm512_castps_si512(self.0),
                    _mm512_set1_epi32(i32::MIN),
                ))
            })
        }
        #[inline(always)]
        fn mul_add(self, a: Self, b: Self) -> Self {
            // SAFETY: see the module comment.
            Z16(unsafe { _mm512_fmadd_ps(self.0, a.0, b.0) })
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            // SAFETY: see the module comment.
            Z16(unsafe { _mm512_sqrt_ps(self.0) })
        }
        #[inline(always)]
        fn ceil(self) -> Self {
            // SAFETY: see the module comment.
            Z16(unsafe {
                _mm512_roundscale_ps::<{ _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC }>(self.0)
            })
        }
        #[inline(always)]
        fn ln_bound(self) -> Self {
            // x = m 2^e with m in [sqrt(1/2), sqrt(2)), then ln m = 2 atanh(s), s = (m-1)/(m+1),
            // |s| < 0.172, from its odd series up to s^9 (next term < 3e-9).
            // SAFETY: see the module comment.
            unsafe {
                let x = self.0;
                let mut e = _mm512_getexp_ps(x);
                let mut m = _mm512_getmant_ps::<_MM_MANT_NORM_1_2, _MM_MANT_SIGN_SRC>(x);
                let big =
                    _mm512_cmp_ps_mask::<_CMP_GT_OQ>(m, _mm512_set1_ps(std::f32::consts::SQRT_2));
                m = _mm512_mask_mul_ps(m, big, m, _mm512_set1_ps(0.5));
                e = _mm512_mask_add_ps(e, big, e, _mm512_set1_ps(1.0));
                let one = _mm512_set1_ps(1.0);
                let s = _mm512_div_ps(_mm512_sub_ps(m, one), _mm512_add_ps(m, one));
                let s2 = _mm512_mul_ps(s, s);
                let mut p = _mm512_set1_ps(1.0 / 9.0);
                for c in [1.0 / 7.0, 1.0 / 5.0, 1.0 / 3.0, 1.0] {
                    p = _mm512_fmadd_ps(p, s2, _mm512_set1_ps(c));
                }
                let ln_m = _mm512_mul_ps(_mm512_add_ps(s, s), p);
                Z16(_mm512_fmadd_ps(
                    e,
                    _mm512_set1_ps(std::f32::consts::LN_2),
                    ln_m,
                ))
            }
        }
        #[inline(always)]
        fn eq(self, o: Self) -> Mask {
            // SAFETY: see the module comment.
            unsafe { _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn le(self, o: Self) -> Mask {
            // SAFETY: see the module comment.
            unsafe { _mm512_cmp_ps_mask::<_CMP_LE_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn lt(self, o: Self) -> Mask {
            // SAFETY: see the module comment.
            unsafe { _mm512_cmp_ps_mask::<_CMP_LT_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn gt(self, o: Self) -> Mask {
            // SAFETY: see the module comment.
            unsafe { _mm512_cmp_ps_mask::<_CMP_GT_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn ge(self, o: Self) -> Mask {
            // SAFETY: see the module comment.
            unsafe { _mm512_cmp_ps_mask::<_CMP_GE_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn select(m: Mask, a: Self, b: Self) -> Self {
            // SAFETY: see the module comment.
            Z16(unsafe { _mm512_mask_mov_ps(b.0, m, a.0) })
        }
        #[inline(always)]
        fn exp(self) -> Self {
            Self::exp_n([self])[0]
        }
        #[inline(always)]
        fn exp_n<const N: usize>(x: [Self; N]) -> [Self; N] {
            // crate::real::exp_f32, operation for operation, each step on all N vectors;
            // `scalef` multiplies by 2^k with the same single rounding.
            use crate::real::{EXP_HI, EXP_LO, EXP_POLY, LN2_HI, LN2_LO, LOG2E, ROUND};
            let s = Self::splat;
            let mut xs = x;
            let mut k = x;
            let mut r = x;
            let mut p = x;
            for i in 0..N {
                xs[i] = x[i].max(s(EXP_LO)).min(s(EXP_HI));
            }
            for i in 0..N {
                k[i] = xs[i].mul_add(s(LOG2E), s(ROUND)).sub(s(ROUND));
            }
            for i in 0..N {
                r[i] = k[i].mul_add(s(-LN2_HI), xs[i]);
                r[i] = k[i].mul_add(s(-LN2_LO), r[i]);
            }
            for i in 0..N {
                p[i] = s(EXP_POLY[0]);
            }
            for c in &EXP_POLY[1..] {
                for i in 0..N {
                    p[i] = p[i].mul_add(r[i], s(*c));
                }
            }
            let mut out = x;
            for i in 0..N {
                // SAFETY: see the module comment.
                out[i] = Z16(unsafe { _mm512_scalef_ps(p[i].0, k[i].0) });
            }
            out
        }
        #[inline(always)]
        fn hsum(self) -> f32 {
            // SAFETY: see the module comment.
            unsafe {
                let v = self.0;
                let lo = _mm512_castps512_ps256(v);
                let hi = _mm256_castpd_ps(_mm512_extractf64x4_pd::<1>(_mm512_castps_pd(v)));
                let a = _mm256_add_ps(lo, hi);
                let b = _mm_add_ps(_mm256_castps256_ps128(a), _mm256_extractf128_ps::<1>(a));
                let c = _mm_add_ps(b, _mm_movehl_ps(b, b));
                let d = _mm_add_ss(c, _mm_shuffle_ps::<1>(c, c));
                _mm_cvtss_f32(d)
            }
        }
        #[inline(always)]
        fn idx_zero() -> __m512i {
            // SAFETY: see the module comment.
            unsafe { _mm512_setzero_si512() }
        }
        #[inline(always)]
        fn idx_set(m: Mask, k: u32, cur: __m512i) -> __m512i {
            // SAFETY: see the module comment.
            unsafe { _mm512_mask_mov_epi32(cur, m, _mm512_set1_epi32(k as i32)) }
        }
        #[inline(always)]
        fn idx_gt(cur: __m512i, k: u32) -> Mask {
            // SAFETY: see the module comment.
            unsafe { _mm512_cmpgt_epu32_mask(cur, _mm512_set1_epi32(k as i32)) }
        }
        #[inline(always)]
        fn idx_load_first(s: &[u32]) -> __m512i {
            let m = super::first(s.len());
            // SAFETY: the masked load reads only the first min(16, len) elements.
            unsafe { _mm512_maskz_loadu_epi32(m, s.as_ptr() as *const i32) }
        }
        #[inline(always)]
        fn idx_store_masked(cur: __m512i, d: &mut [u32], m: Mask) {
            debug_assert!(m == 0 || d.len() > (15 - m.leading_zeros()) as usize);
            // SAFETY: as in store_masked.
            unsafe { _mm512_mask_storeu_epi32(d.as_mut_ptr() as *mut i32, m, cur) }
        }
        #[inline(always)]
        fn transpose(rows: [Self; WIDTH]) -> [Self; WIDTH] {
            // Four rounds of 16 shuffles: pairs of floats, pairs of pairs (as f64), then the
            // 128-bit quarters in two steps.
            // SAFETY: see the module comment.
            unsafe {
                let mut r = [_mm512_setzero_ps(); WIDTH];
                for (d, z) in r.iter_mut().zip(&rows) {
                    *d = z.0;
                }
                let mut a = r;
                for i in 0..8 {
                    a[2 * i] = _mm512_unpacklo_ps(r[2 * i], r[2 * i + 1]);
                    a[2 * i + 1] = _mm512_unpackhi_ps(r[2 * i], r[2 * i + 1]);
                }
                // b[4i + c]: in quarter q, rows 4i..4i+3 of column 4q + c.
                let mut b = a;
                let pd = _mm512_castps_pd;
                let ps = _mm512_castpd_ps;
                for i in 0..4 {
                    let (x0, x1, x2, x3) = (a[4 * i], a[4 * i + 1], a[4 * i + 2], a[4 * i + 3]);
                    b[4 * i] = ps(_mm512_unpacklo_pd(pd(x0), pd(x2)));
                    b[4 * i + 1] = ps(_mm512_unpackhi_pd(pd(x0), pd(x2)));
                    b[4 * i + 2] = ps(_mm512_unpacklo_pd(pd(x1), pd(x3)));
                    b[4 * i + 3] = ps(_mm512_unpackhi_pd(pd(x1), pd(x3)));
                }
                // Result 4q + c gathers quarter q of b[c], b[4 + c], b[8 + c], b[12 + c].
                let mut out = rows;
                for c in 0..4 {
                    let (x0, x1, x2, x3) = (b[c], b[4 + c], b[8 + c], b[12 + c]);
                    let c0 = _mm512_shuffle_f32x4::<0x44>(x0, x1);
                    let c1 = _mm512_shuffle_f32x4::<0xEE>(x0, x1);
                    let c2 = _mm512_shuffle_f32x4::<0x44>(x2, x3);
                    let c3 = _mm512_shuffle_f32x4::<0xEE>(x2, x3);
                    out[c] = Z16(_mm512_shuffle_f32x4::<0x88>(c0, c2));
                    out[4 + c] = Z16(_mm512_shuffle_f32x4::<0xDD>(c0, c2));
                    out[8 + c] = Z16(_mm512_shuffle_f32x4::<0x88>(c1, c3));
                    out[12 + c] = Z16(_mm512_shuffle_f32x4::<0xDD>(c1, c3));
                }
                out
            }
        }
        #[inline(always)]
        fn positions_with(masks: &[u32], bit: u32, out: &mut [u32]) -> usize {
            // Sixteen masks at a time: test the bit, compress the matching positions to the
            // front of a register and store all 16 lanes (a compressing store to memory is
            // microcoded and slow on some CPUs).
            assert!(out.len() >= masks.len() + WIDTH);
            let mut n = 0;
            // SAFETY: see the module comment. Loads read lanes of `masks[i..]` only (the tail
            // with a lane mask), and each store writes `out[n..n + 16]` with n <= i <
            // masks.len(), inside `out`.
            unsafe {
                let bitv = _mm512_set1_epi32(bit as i32);
                let mut pos =
                    _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
                let step = _mm512_set1_epi32(WIDTH as i32);
                let mut i = 0;
                while i < masks.len() {
                    let lanes = super::first(masks.len() - i);
                    let v = _mm512_maskz_loadu_epi32(lanes, masks.as_ptr().add(i) as *const i32);
                    let m = _mm512_test_epi32_mask(v, bitv);
                    let packed = _mm512_maskz_compress_epi32(m, pos);
                    _mm512_storeu_si512(out.as_mut_ptr().add(n) as *mut _, packed);
                    n += m.count_ones() as usize;
                    pos = _mm512_add_epi32(pos, step);
                    i += WIDTH;
                }
            }
            n
        }
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Every operation of [`Z16`] against [`P16<f32>`], bit for bit, on values that include
    /// ties, signed zeros and the exp's clamping range.
    #[test]
    fn avx512_lanes_equal_array_lanes() {
        if !gagavatar_testkit::avx512_or_skip("avx512_lanes_equal_array_lanes") {
            return;
        }
        let mut rng = Rng::new(3);
        for round in 0..200 {
            let draw = |rng: &mut Rng| -> [f32; WIDTH] {
                std::array::from_fn(|i| match (round + i) % 5 {
                    0 => 0.0,
                    1 => -0.0,
                    2 => rng.range(-100.0, 100.0) as f32,
                    _ => rng.range(-3.0, 3.0) as f32,
                })
            };
            let (a, b) = (draw(&mut rng), draw(&mut rng));
            let m = rng.below(1 << 16) as Mask;
            let (za, zb) = (Z16::load(&a), Z16::load(&b));
            let (pa, pb) = (P16(a), P16(b));
            let same = |what: &str, z: [f32; WIDTH], p: [f32; WIDTH]| {
                for i in 0..WIDTH {
                    assert_eq!(
                        z[i].to_bits(),
                        p[i].to_bits(),
                        "{what} lane {i}: expected {}, got {}",
                        p[i],
                        z[i]
                    );
                }
            };
            same("add", za.add(zb).to_array(), pa.add(pb).0);
            same("sub", za.sub(zb).to_array(), pa.sub(pb).0);
            same("mul", za.mul(zb).to_array(), pa.mul(pb).0);
            same("div", za.div(zb).to_array(), pa.div(pb).0);
            same("min", za.min(zb).to_array(), pa.min(pb).0);
            same("max", za.max(zb).to_array(), pa.max(pb).0);
            same("neg", za.neg().to_array(), pa.neg().0);
            same("sqrt", za.sqrt().to_array(), pa.sqrt().0);
            same("ceil", za.ceil().to_array(), pa.ceil().0);
            assert_eq!(za.eq(zb), pa.eq(pb), "eq");
            assert_eq!(za.eq(za), pa.eq(pa), "eq (self)");
            same("exp", za.exp().to_array(), pa.exp().0);
            let (zc, pc) = (Z16::load(&a), P16(a));
            same(
                "mul_add",
                za.mul_add(zb, zc.neg()).to_array(),
                pa.mul_add(pb, pc.neg()).0,
            );
            same(
                "select",
                Z16::select(m, za, zb).to_array(),
                P16::select(m, pa, pb).0,
            );
            same(
                "iota",
                Z16::iota_plus(a[2]).to_array(),
                P16::iota_plus(a[2]).0,
            );
            assert_eq!(za.le(zb), pa.le(pb), "le");
            assert_eq!(za.lt(zb), pa.lt(pb), "lt");
            assert_eq!(za.gt(zb), pa.gt(pb), "gt");
            assert_eq!(za.ge(zb), pa.ge(pb), "ge");
            assert_eq!(za.hsum().to_bits(), pa.hsum().to_bits(), "hsum");
            let rows: [[f32; WIDTH]; WIDTH] =
                std::array::from_fn(|_| std::array::from_fn(|_| rng.range(-5.0, 5.0) as f32));
            let tz = Z16::transpose(rows.map(|r| Z16::load(&r)));
            let tp = P16::transpose(rows.map(P16));
            for j in 0..WIDTH {
                let want: [f32; WIDTH] = std::array::from_fn(|i| rows[i][j]);
                same("transpose (arrays)", tp[j].0, want);
                same("transpose", tz[j].to_array(), want);
            }
            let n = round % (WIDTH + 1);
            same(
                "load_first",
                Z16::load_first(&a[..n]).to_array(),
                P16::load_first(&a[..n]).0,
            );
            let (mut dz, mut dp) = ([7.0f32; WIDTH], [7.0f32; WIDTH]);
            za.store_masked(&mut dz, m);
            pa.store_masked(&mut dp, m);
            same("store_masked", dz, dp);
            let idx: [u32; WIDTH] = std::array::from_fn(|_| rng.below(50) as u32);
            let k = rng.below(50) as u32;
            let (iz, ip) = (Z16::idx_load_first(&idx), P16::<f32>::idx_load_first(&idx));
            assert_eq!(Z16::idx_gt(iz, k), P16::<f32>::idx_gt(ip, k), "idx_gt");
            let (mut oz, mut op) = ([0u32; WIDTH], [0u32; WIDTH]);
            Z16::idx_store_masked(Z16::idx_set(m, k, iz), &mut oz, ALL);
            P16::<f32>::idx_store_masked(P16::<f32>::idx_set(m, k, ip), &mut op, ALL);
            assert_eq!(oz, op, "idx_set");
        }
    }

    /// [`Z16::ln_bound`] against f64 ln over the range the projection feeds it (255 times an
    /// opacity) and beyond.
    #[test]
    fn avx512_ln_bound_is_close() {
        if !gagavatar_testkit::avx512_or_skip("avx512_ln_bound_is_close") {
            return;
        }
        // Relative error allowed for a bound that is then inflated by 2%.
        const LN_REL_TOL: f64 = 2e-6;
        let mut x = 1.0f32;
        while x < 1e6 {
            let xs: [f32; WIDTH] = std::array::from_fn(|i| x * (1.0 + i as f32 * 0.013));
            let got = Z16::load(&xs).ln_bound().to_array();
            for (i, (&g, &xi)) in got.iter().zip(&xs).enumerate() {
                let want = (xi as f64).ln();
                let err = (g as f64 - want).abs() / want.abs().max(1.0);
                assert!(
                    err <= LN_REL_TOL,
                    "lane {i}, x {xi}: expected {want}, got {g}"
                );
            }
            x *= 1.37;
        }
    }

    /// The compressing [`Z16::positions_with`] against the plain loop, on lists shorter than,
    /// equal to and longer than a vector, for every block bit.
    #[test]
    fn avx512_positions_equal_array_positions() {
        if !gagavatar_testkit::avx512_or_skip("avx512_positions_equal_array_positions") {
            return;
        }
        let mut rng = Rng::new(11);
        for len in [0usize, 1, 5, 15, 16, 17, 31, 33, 200] {
            let masks: Vec<u32> = (0..len).map(|_| rng.below(1 << 16) as u32).collect();
            for b in 0..WIDTH {
                let (mut oz, mut op) = (vec![0u32; len + WIDTH], vec![0u32; len + WIDTH]);
                let nz = Z16::positions_with(&masks, 1 << b, &mut oz);
                let np = P16::<f32>::positions_with(&masks, 1 << b, &mut op);
                let want: Vec<u32> = (0..len as u32)
                    .filter(|&i| masks[i as usize] >> b & 1 != 0)
                    .collect();
                assert_eq!(&op[..np], &want[..], "array lanes, len {len}, bit {b}");
                assert_eq!(&oz[..nz], &want[..], "AVX-512 lanes, len {len}, bit {b}");
            }
        }
    }
}
