//! 16-lane f32 vectors for the inference kernels: one lane per channel of a 16-channel block.
//!
//! Every kernel in [`crate::kernels`] is written once against [`Lanes`] and compiled twice: with
//! [`Zmm`] (one AVX-512 register, masked loads and stores for channel counts that are not a
//! multiple of 16) on CPUs that have AVX-512F, and with [`Arr`] (a plain array the compiler
//! vectorises as far as the target allows) everywhere else. The two differ only in rounding:
//! [`Lanes::fma`] is fused in `Zmm` and a separate multiply and add in `Arr`.

/// Lanes per vector.
pub const W: usize = 16;

/// The instruction set the kernels run with, detected once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Level {
    /// Plain arrays ([`Arr`]).
    Portable,
    /// AVX-512F registers ([`Zmm`]).
    Avx512,
}

/// The level picked for this CPU; `GAGAVATAR_NO_AVX512=1` forces the portable kernels (tests
/// compare the two).
pub fn level() -> Level {
    use std::sync::OnceLock;
    static LEVEL: OnceLock<Level> = OnceLock::new();
    *LEVEL.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            let off = std::env::var_os("GAGAVATAR_NO_AVX512").is_some_and(|v| v != "0");
            if !off && std::arch::is_x86_feature_detected!("avx512f") {
                return Level::Avx512;
            }
        }
        Level::Portable
    })
}

/// A vector of 16 f32 lanes. The pointer methods are `unsafe`: the caller guarantees that the
/// lanes read or written are inside one allocation.
pub trait Lanes: Copy {
    fn splat(v: f32) -> Self;
    fn zero() -> Self;
    /// # Safety
    /// `p..p+16` readable.
    unsafe fn load(p: *const f32) -> Self;
    /// The first `n` (at most 16) lanes from `p`, zeros after.
    /// # Safety
    /// `p..p+n` readable.
    unsafe fn load_n(p: *const f32, n: usize) -> Self;
    /// # Safety
    /// `p..p+16` writable.
    unsafe fn store(self, p: *mut f32);
    /// Writes the first `n` (at most 16) lanes.
    /// # Safety
    /// `p..p+n` writable.
    unsafe fn store_n(self, p: *mut f32, n: usize);
    fn add(self, o: Self) -> Self;
    fn sub(self, o: Self) -> Self;
    fn mul(self, o: Self) -> Self;
    fn max(self, o: Self) -> Self;
    fn min(self, o: Self) -> Self;
    /// `self * a + b`.
    fn fma(self, a: Self, b: Self) -> Self;
    fn to_array(self) -> [f32; W];
}

/// Plain-array lanes.
#[derive(Clone, Copy)]
pub struct Arr(pub [f32; W]);

impl Lanes for Arr {
    #[inline(always)]
    fn splat(v: f32) -> Self {
        Arr([v; W])
    }
    #[inline(always)]
    fn zero() -> Self {
        Arr([0.0; W])
    }
    #[inline(always)]
    unsafe fn load(p: *const f32) -> Self {
        // SAFETY: the caller guarantees 16 readable values.
        Arr(unsafe { std::ptr::read_unaligned(p as *const [f32; W]) })
    }
    #[inline(always)]
    unsafe fn load_n(p: *const f32, n: usize) -> Self {
        let mut a = [0.0; W];
        for (i, v) in a.iter_mut().enumerate().take(n.min(W)) {
            // SAFETY: i < n, readable by the caller's guarantee.
            *v = unsafe { *p.add(i) };
        }
        Arr(a)
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32) {
        // SAFETY: the caller guarantees 16 writable values.
        unsafe { std::ptr::write_unaligned(p as *mut [f32; W], self.0) }
    }
    #[inline(always)]
    unsafe fn store_n(self, p: *mut f32, n: usize) {
        for (i, v) in self.0.iter().enumerate().take(n.min(W)) {
            // SAFETY: i < n, writable by the caller's guarantee.
            unsafe { *p.add(i) = *v };
        }
    }
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        Arr(std::array::from_fn(|i| self.0[i] + o.0[i]))
    }
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        Arr(std::array::from_fn(|i| self.0[i] - o.0[i]))
    }
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        Arr(std::array::from_fn(|i| self.0[i] * o.0[i]))
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        Arr(std::array::from_fn(|i| {
            if self.0[i] > o.0[i] {
                self.0[i]
            } else {
                o.0[i]
            }
        }))
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        Arr(std::array::from_fn(|i| {
            if self.0[i] < o.0[i] {
                self.0[i]
            } else {
                o.0[i]
            }
        }))
    }
    #[inline(always)]
    fn fma(self, a: Self, b: Self) -> Self {
        Arr(std::array::from_fn(|i| self.0[i] * a.0[i] + b.0[i]))
    }
    #[inline(always)]
    fn to_array(self) -> [f32; W] {
        self.0
    }
}

#[cfg(target_arch = "x86_64")]
pub use zmm::Zmm;

#[cfg(target_arch = "x86_64")]
mod zmm {
    use super::{Lanes, W};
    use std::arch::x86_64::*;

    /// One AVX-512 register. Only constructed inside functions compiled with AVX-512F enabled
    /// (see [`crate::simd::level`]).
    #[derive(Clone, Copy)]
    pub struct Zmm(pub __m512);

    #[inline(always)]
    fn mask(n: usize) -> __mmask16 {
        if n >= W {
            0xffff
        } else {
            ((1u32 << n) - 1) as __mmask16
        }
    }

    impl Lanes for Zmm {
        #[inline(always)]
        fn splat(v: f32) -> Self {
            // SAFETY: only reached from AVX-512F code (see the type's docs).
            Zmm(unsafe { _mm512_set1_ps(v) })
        }
        #[inline(always)]
        fn zero() -> Self {
            // SAFETY: as above.
            Zmm(unsafe { _mm512_setzero_ps() })
        }
        #[inline(always)]
        unsafe fn load(p: *const f32) -> Self {
            // SAFETY: 16 readable values (caller), AVX-512F enabled.
            Zmm(unsafe { _mm512_loadu_ps(p) })
        }
        #[inline(always)]
        unsafe fn load_n(p: *const f32, n: usize) -> Self {
            // SAFETY: masked lanes are not accessed; the others are readable (caller).
            Zmm(unsafe { _mm512_maskz_loadu_ps(mask(n), p) })
        }
        #[inline(always)]
        unsafe fn store(self, p: *mut f32) {
            // SAFETY: 16 writable values (caller).
            unsafe { _mm512_storeu_ps(p, self.0) }
        }
        #[inline(always)]
        unsafe fn store_n(self, p: *mut f32, n: usize) {
            // SAFETY: only the first n lanes are written; they are writable (caller).
            unsafe { _mm512_mask_storeu_ps(p, mask(n), self.0) }
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            // SAFETY: AVX-512F enabled (type invariant).
            Zmm(unsafe { _mm512_add_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            // SAFETY: as above.
            Zmm(unsafe { _mm512_sub_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn mul(self, o: Self) -> Self {
            // SAFETY: as above.
            Zmm(unsafe { _mm512_mul_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn max(self, o: Self) -> Self {
            // SAFETY: as above. vmaxps returns the second operand when either is NaN, like
            // `Arr::max`.
            Zmm(unsafe { _mm512_max_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn min(self, o: Self) -> Self {
            // SAFETY: as above.
            Zmm(unsafe { _mm512_min_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn fma(self, a: Self, b: Self) -> Self {
            // SAFETY: as above.
            Zmm(unsafe { _mm512_fmadd_ps(self.0, a.0, b.0) })
        }
        #[inline(always)]
        fn to_array(self) -> [f32; W] {
            let mut a = [0.0; W];
            // SAFETY: 16 writable values.
            unsafe { _mm512_storeu_ps(a.as_mut_ptr(), self.0) };
            a
        }
    }
}

/// Defines `fn $name(args)` that runs `$imp::<L>` with `L` = [`Zmm`] in an AVX-512F-enabled
/// copy when [`level`] says so, and with [`Arr`] otherwise. `$imp` and everything it calls
/// must be `#[inline(always)]`, so the intrinsics are inlined into the AVX-512 copy (an
/// intrinsic left in a function without the feature is an out-of-line call per operation).
macro_rules! dispatch {
    // `$imp` takes no lane type: the same code, compiled with AVX-512 enabled or not (for
    // loops the compiler vectorises itself).
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident : $ty:ty),* $(,)?) $(-> $ret:ty)? = plain $imp:ident) => {
        $(#[$meta])*
        #[allow(clippy::too_many_arguments)]
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
            #[allow(clippy::too_many_arguments)]
            unsafe fn v4($($arg: $ty),*) $(-> $ret)? {
                $imp($($arg),*)
            }
            match $crate::simd::level() {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: the level was detected on this CPU.
                $crate::simd::Level::Avx512 => unsafe { v4($($arg),*) },
                _ => $imp($($arg),*),
            }
        }
    };
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident : $ty:ty),* $(,)?) $(-> $ret:ty)? = $imp:ident) => {
        $(#[$meta])*
        #[allow(clippy::too_many_arguments)]
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
            #[allow(clippy::too_many_arguments)]
            unsafe fn v4($($arg: $ty),*) $(-> $ret)? {
                $imp::<$crate::simd::Zmm>($($arg),*)
            }
            match $crate::simd::level() {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: the level was detected on this CPU.
                $crate::simd::Level::Avx512 => unsafe { v4($($arg),*) },
                _ => $imp::<$crate::simd::Arr>($($arg),*),
            }
        }
    };
}
pub(crate) use dispatch;

#[cfg(test)]
mod tests {
    use super::*;

    fn ops<L: Lanes>() -> Vec<[f32; W]> {
        let a: Vec<f32> = (0..W).map(|i| i as f32 - 7.5).collect();
        let b: Vec<f32> = (0..W).map(|i| (i as f32 * 0.37).sin()).collect();
        // SAFETY: both hold 16 values; load_n reads 5.
        let (x, y, z) = unsafe {
            (
                L::load(a.as_ptr()),
                L::load(b.as_ptr()),
                L::load_n(a.as_ptr(), 5),
            )
        };
        let mut out = [0.0f32; W];
        // SAFETY: out holds 16 values.
        unsafe { x.max(y).store_n(out.as_mut_ptr(), 9) };
        vec![
            x.add(y).to_array(),
            x.sub(y).to_array(),
            x.mul(y).to_array(),
            x.max(y).to_array(),
            x.min(y).to_array(),
            z.to_array(),
            out,
            L::splat(2.5).add(L::zero()).to_array(),
        ]
    }

    #[test]
    fn lanes_agree() {
        let a = ops::<Arr>();
        #[cfg(target_arch = "x86_64")]
        if level() == Level::Avx512 {
            #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
            fn z() -> Vec<[f32; W]> {
                ops::<Zmm>()
            }
            // SAFETY: AVX-512F detected.
            let b = unsafe { z() };
            assert_eq!(a, b);
        }
        assert_eq!(a[5][4], -3.5);
        assert_eq!(a[5][5], 0.0);
        assert_eq!(a[6][9], 0.0);
    }
}
