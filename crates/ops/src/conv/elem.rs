//! The element types the kernels run on (f32, f64), a thin wrapper over the `gemm` crate, and
//! runtime selection of the widest SIMD level for the loops we vectorise ourselves.

use std::fmt::Debug;
use std::ops::{Add, AddAssign, Mul, Sub};

pub(crate) trait Elem:
    Copy
    + Send
    + Sync
    + Debug
    + Default
    + PartialEq
    + 'static
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + AddAssign
{
    const ZERO: Self;
    const ONE: Self;
    /// A constant of the transform matrices (exact in both types for the values used).
    fn c(v: f64) -> Self;
    /// The slice as f32, when `Self` is f32 (for the hand-vectorised f32 kernels).
    fn as_f32(_s: &[Self]) -> Option<&[f32]> {
        None
    }
    fn as_f32_mut(_s: &mut [Self]) -> Option<&mut [f32]> {
        None
    }
    fn to_f32(self) -> f32;
}

impl Elem for f32 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
    #[inline(always)]
    fn c(v: f64) -> Self {
        v as f32
    }
    fn as_f32(s: &[Self]) -> Option<&[f32]> {
        Some(s)
    }
    fn as_f32_mut(s: &mut [Self]) -> Option<&mut [f32]> {
        Some(s)
    }
    fn to_f32(self) -> f32 {
        self
    }
}

impl Elem for f64 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
    #[inline(always)]
    fn c(v: f64) -> Self {
        v
    }
    fn to_f32(self) -> f32 {
        self as f32
    }
}

/// A raw pointer that tasks share to write disjoint parts of one output buffer.
#[derive(Clone, Copy)]
pub(crate) struct SendPtr<T>(pub *mut T);
// SAFETY: every user writes a region no other task touches (documented at each use).
unsafe impl<T> Send for SendPtr<T> {}
unsafe impl<T> Sync for SendPtr<T> {}

impl<T> SendPtr<T> {
    /// Through a method, so closures capture the whole (Sync) wrapper, not the raw field.
    #[inline(always)]
    pub fn get(&self) -> *mut T {
        self.0
    }
}

/// Row-major strided matrix operand: element (i, j) at `ptr + i*rs + j*cs`.
#[derive(Clone, Copy)]
pub(crate) struct Mat<T> {
    pub ptr: *const T,
    pub rs: isize,
    pub cs: isize,
}

/// `dst (m x n) = [dst +] lhs (m x k) * rhs (k x n)`.
///
/// # Safety
/// Every pointer must be valid for the strided extents, and `dst` must not alias the operands.
#[allow(clippy::too_many_arguments)]
pub(crate) unsafe fn gemm<T: Elem>(
    m: usize,
    n: usize,
    k: usize,
    dst: *mut T,
    dst_rs: isize,
    dst_cs: isize,
    accumulate: bool,
    lhs: Mat<T>,
    rhs: Mat<T>,
    threads: usize,
) {
    if m == 0 || n == 0 {
        return;
    }
    let par = if threads > 1 {
        gemm::Parallelism::Rayon(threads)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: forwarded from the caller.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst,
            dst_cs,
            dst_rs,
            accumulate,
            lhs.ptr,
            lhs.cs,
            lhs.rs,
            rhs.ptr,
            rhs.cs,
            rhs.rs,
            T::ONE,
            T::ONE,
            false,
            false,
            false,
            par,
        )
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum SimdLevel {
    Portable,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    #[cfg(target_arch = "x86_64")]
    Avx512,
}

/// The widest level this CPU runs, capped by [`limit_simd`]; `GAGAVATAR_NO_AVX512` (any value)
/// caps it at AVX2 from the start.
pub(crate) fn simd_level() -> SimdLevel {
    use std::sync::atomic::Ordering;
    let cap = SIMD_CAP.load(Ordering::Relaxed);
    #[cfg(target_arch = "x86_64")]
    {
        let detected = detected_level();
        if cap >= 2 && detected == SimdLevel::Avx512 {
            return SimdLevel::Avx512;
        }
        if cap >= 1 && detected != SimdLevel::Portable {
            return SimdLevel::Avx2;
        }
    }
    let _ = cap;
    SimdLevel::Portable
}

/// The level our own loops run at now, as [`limit_simd`] counts them (0 portable, 1 AVX2+FMA,
/// 2 AVX-512): tests read it to know which level a comparison really exercised.
pub fn active_simd_level() -> u8 {
    match simd_level() {
        SimdLevel::Portable => 0,
        #[cfg(target_arch = "x86_64")]
        SimdLevel::Avx2 => 1,
        #[cfg(target_arch = "x86_64")]
        SimdLevel::Avx512 => 2,
    }
}

static SIMD_CAP: std::sync::atomic::AtomicU8 = std::sync::atomic::AtomicU8::new(u8::MAX);

/// Caps the instruction sets our own loops use: 0 portable, 1 AVX2+FMA, 2 (or more) AVX-512.
/// For tests and benchmarks (every level must give the same results up to rounding); it does
/// not affect the `gemm` crate, which picks its kernels itself.
pub fn limit_simd(level: u8) {
    SIMD_CAP.store(level, std::sync::atomic::Ordering::Relaxed);
}

#[cfg(target_arch = "x86_64")]
fn detected_level() -> SimdLevel {
    use std::sync::OnceLock;
    static LEVEL: OnceLock<SimdLevel> = OnceLock::new();
    *LEVEL.get_or_init(|| {
        let no512 = std::env::var_os("GAGAVATAR_NO_AVX512").is_some();
        if !no512 && std::arch::is_x86_feature_detected!("avx512f") {
            return SimdLevel::Avx512;
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            return SimdLevel::Avx2;
        }
        SimdLevel::Portable
    })
}

/// Defines `fn $name<T: Elem>(args)` compiled three times (portable, AVX2, AVX-512) and picked
/// at run time: the loops inside are plain slice code that LLVM vectorises to the enabled width.
macro_rules! multiversion {
    ($(#[$meta:meta])* $vis:vis fn $name:ident<T: Elem>($($arg:ident : $ty:ty),* $(,)?) $body:block) => {
        $(#[$meta])*
        #[allow(clippy::too_many_arguments)]
        $vis fn $name<T: Elem>($($arg: $ty),*) {
            #[inline(always)]
            #[allow(clippy::too_many_arguments)]
            fn imp<T: Elem>($($arg: $ty),*) $body
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
            #[allow(clippy::too_many_arguments)]
            fn v4<T: Elem>($($arg: $ty),*) { imp($($arg),*) }
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2,fma")]
            #[allow(clippy::too_many_arguments)]
            fn v3<T: Elem>($($arg: $ty),*) { imp($($arg),*) }
            match $crate::conv::elem::simd_level() {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: the level was detected on this CPU.
                $crate::conv::elem::SimdLevel::Avx512 => unsafe { v4($($arg),*) },
                #[cfg(target_arch = "x86_64")]
                // SAFETY: as above.
                $crate::conv::elem::SimdLevel::Avx2 => unsafe { v3($($arg),*) },
                $crate::conv::elem::SimdLevel::Portable => imp($($arg),*),
            }
        }
    };
}
pub(crate) use multiversion;

multiversion! {
    /// Sum with 16 independent partial sums, so it vectorises (and rounds less than a chain).
    pub(crate) fn sum_into<T: Elem>(v: &[T], out: &mut T) {
        let mut acc = [T::ZERO; 16];
        let chunks = v.chunks_exact(16);
        let rest = chunks.remainder();
        for c in chunks {
            for (a, x) in acc.iter_mut().zip(c) {
                *a += *x;
            }
        }
        let mut s = T::ZERO;
        for a in acc {
            s += a;
        }
        for x in rest {
            s += *x;
        }
        *out = s;
    }
}

pub(crate) fn sum<T: Elem>(v: &[T]) -> T {
    let mut s = T::ZERO;
    sum_into(v, &mut s);
    s
}

/// Outputs from this size on are fresh `mmap`s on glibc (its threshold tops out at 32 MiB), whose
/// first touch faults in every 4 KiB page; transparent huge pages cut those faults 512-fold
/// (45 MiB: 25 ms -> 13 ms to allocate and fill on the development VM).
const HUGE_OUTPUT_BYTES: usize = 8 << 20;

/// A zeroed output buffer. `calloc` leaves a fresh mapping untouched, so advising huge pages
/// here, before the kernels write, still takes effect; on reused heap memory it is harmless.
pub(crate) fn alloc_output<T: Elem>(n: usize) -> Vec<T> {
    let v = vec![T::ZERO; n];
    #[cfg(target_os = "linux")]
    {
        let bytes = n * std::mem::size_of::<T>();
        if bytes >= HUGE_OUTPUT_BYTES {
            const HUGE: usize = 2 << 20;
            let start = v.as_ptr() as usize;
            let lo = start.next_multiple_of(HUGE);
            let hi = (start + bytes) / HUGE * HUGE;
            if hi > lo {
                // SAFETY: [lo, hi) lies inside the allocation; the advice only changes how
                // the kernel backs the pages, never their contents. Failure is harmless.
                unsafe {
                    libc::madvise(lo as *mut libc::c_void, hi - lo, libc::MADV_HUGEPAGE);
                }
            }
        }
    }
    v
}

/// Splits `units` (rows of one image, of `b` images) into equal chunks of about `per` units:
/// enough chunks for every thread, their number rounded up to a multiple of the thread count
/// (so no thread waits on another's last chunk), as long as chunks keep `min` units.
pub(crate) fn balanced_chunk(
    units: usize,
    per: usize,
    b: usize,
    threads: usize,
    min: usize,
) -> usize {
    let per = per.clamp(1, units.max(1));
    let mut chunks = units.div_ceil(per);
    let total = b * chunks;
    let want = total.max(2 * threads).next_multiple_of(threads.max(1));
    let more = want.div_ceil(b.max(1)).min(units);
    if more > chunks && units / more >= min.max(1) {
        chunks = more;
    }
    units.div_ceil(chunks.max(1))
}
