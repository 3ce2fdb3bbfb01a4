//! The float type the kernels are generic over: f32 on the hot path, f64 for finite-difference
//! checks and strict golden comparisons.

use candle_core::WithDType;
use std::fmt::Debug;
use std::ops::{Add, AddAssign, Div, Mul, MulAssign, Neg, Sub, SubAssign};

pub trait Real:
    WithDType
    + Copy
    + Send
    + Sync
    + Debug
    + Default
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
    + SubAssign
    + MulAssign
    + 'static
{
    const ZERO: Self;
    const ONE: Self;
    fn lit(v: f64) -> Self;
    fn as_f64(self) -> f64;
    /// exp for the compositing hot loop: branch-free so loops over pixels vectorise (f32), or
    /// the standard one (f64, where exactness matters more than speed).
    fn fexp(self) -> Self;
    /// `self * a + b` with one rounding (a fused multiply-add; slow in software on CPUs
    /// without FMA, which only the portable kernels would meet).
    fn mul_add(self, a: Self, b: Self) -> Self;
    fn sqrt(self) -> Self;
    fn ceil(self) -> Self;
    fn floor(self) -> Self;
    fn fmin(self, o: Self) -> Self;
    fn fmax(self, o: Self) -> Self;
}

macro_rules! impl_real {
    ($t:ty $(, $extra:item)*) => {
        impl Real for $t {
            $($extra)*
            const ZERO: Self = 0.0;
            const ONE: Self = 1.0;
            #[inline(always)]
            fn lit(v: f64) -> Self {
                v as $t
            }
            #[inline(always)]
            fn as_f64(self) -> f64 {
                self as f64
            }
            #[inline(always)]
            fn mul_add(self, a: Self, b: Self) -> Self {
                <$t>::mul_add(self, a, b)
            }
            #[inline(always)]
            fn sqrt(self) -> Self {
                <$t>::sqrt(self)
            }
            #[inline(always)]
            fn ceil(self) -> Self {
                <$t>::ceil(self)
            }
            #[inline(always)]
            fn floor(self) -> Self {
                <$t>::floor(self)
            }
            #[inline(always)]
            fn fmin(self, o: Self) -> Self {
                <$t>::min(self, o)
            }
            #[inline(always)]
            fn fmax(self, o: Self) -> Self {
                <$t>::max(self, o)
            }
        }
    };
}
impl_real!(
    f32,
    #[inline(always)]
    fn fexp(self) -> f32 {
        exp_f32(self)
    }
);
impl_real!(
    f64,
    #[inline(always)]
    fn fexp(self) -> f64 {
        self.exp()
    }
);

/// Branch-free single-precision exp (Cody-Waite range reduction and a degree-7 minimax
/// polynomial in Horner form with fused multiply-adds, within ~2 ulp of the true value on
/// [-87, 0]), vectorisable by the compiler. [`crate::lanes::Z16`] computes the same operations.
#[inline(always)]
pub fn exp_f32(x: f32) -> f32 {
    // max/min rather than clamp: clamp's NaN handling keeps the compiler from vectorising.
    #[allow(clippy::manual_clamp)]
    let x = x.max(EXP_LO).min(EXP_HI);
    // Adding and subtracting 1.5 * 2^23 rounds to the nearest integer without a branch.
    let shifted = x.mul_add(LOG2E, ROUND);
    let k = shifted - ROUND;
    let r = k.mul_add(-LN2_HI, x);
    let r = k.mul_add(-LN2_LO, r);
    let mut p = EXP_POLY[0];
    for c in &EXP_POLY[1..] {
        p = p.mul_add(r, *c);
    }
    // The low mantissa bits of `shifted` hold k itself (offset by ROUND's bit pattern), so the
    // exponent of 2^k comes from integer arithmetic that vectorises, unlike a float-to-int cast.
    // k is in [-126, 127], so 2^k is a normal number and the product is one rounding, like
    // the AVX-512 `scalef`.
    let kbits = shifted.to_bits().wrapping_sub(ROUND.to_bits());
    let scale = f32::from_bits(kbits.wrapping_add(127) << 23);
    p * scale
}

/// Range of [`exp_f32`]'s argument (outside, it is clamped; alphas there are far below 1/255).
pub const EXP_LO: f32 = -87.0;
pub const EXP_HI: f32 = 88.0;
pub const LOG2E: f32 = std::f32::consts::LOG2_E;
/// ln 2 in two parts: the first has few enough mantissa bits that k * LN2_HI is exact.
pub const LN2_HI: f32 = 0.693_359_4;
pub const LN2_LO: f32 = -2.121_944_4e-4;
pub const ROUND: f32 = 12_582_912.0;
/// exp(r) on [-ln2/2, ln2/2], highest power first: r^7/5040 ... r + 1 (minimax-adjusted).
pub const EXP_POLY: [f32; 8] = [
    1.987_569_2e-4,
    1.398_2e-3,
    8.333_452e-3,
    4.166_579_6e-2,
    1.666_666_5e-1,
    0.5,
    1.0,
    1.0,
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_exp_is_within_a_few_ulp() {
        // Relative error of 4 ulp at f32 (2^-23 each): the polynomial's error plus rounding.
        const EXP_REL_TOL: f64 = 4.0 * 1.2e-7;
        let mut worst = 0.0f64;
        let mut x = -87.0f32;
        while x <= 0.0 {
            let got = exp_f32(x) as f64;
            let want = (x as f64).exp();
            let rel = ((got - want) / want).abs();
            assert!(
                rel <= EXP_REL_TOL,
                "x={x}: expected {want}, got {got} (rel {rel:e})"
            );
            worst = worst.max(rel);
            x += 0.000_731;
        }
        assert_eq!(exp_f32(0.0), 1.0);
    }
}
