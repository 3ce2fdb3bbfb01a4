//! Test support shared by the workspace's suites.
//!
//! Two jobs, both about tests that must not pass for the wrong reason:
//! - **Optional paths.** A test of a path this machine lacks (AVX-512 kernels, an ffmpeg encoder,
//!   a GPU) prints `SKIPPED <test>: <why>` and returns, unless the run requires that path through
//!   its environment variable (`.ci/run` sets each one the machine can honour), in which case the
//!   absence is a failure. A CI log then says what it covered, and a machine that has the path
//!   can never skip it in silence.
//! - **NaN-proof comparisons.** `f64::max` and `d > worst` both drop a NaN, so a kernel that
//!   returns NaN everywhere would pass a `max difference <= tol` check. The helpers here make a
//!   NaN the worst possible difference.

/// Set (to anything but `0`) to make a missing AVX-512 path a failure instead of a skip.
pub const REQUIRE_AVX512: &str = "GAGAVATAR_REQUIRE_AVX512";
/// Set to make a missing ffmpeg, or a missing ffmpeg encoder, a failure instead of a skip.
pub const REQUIRE_FFMPEG: &str = "GAGAVATAR_REQUIRE_FFMPEG";
/// Set to make a missing Vulkan device a failure instead of a skip.
pub const REQUIRE_GPU: &str = "GAGAVATAR_REQUIRE_GPU_TESTS";

/// Set to make a missing AVX512-BF16 (the `--precision bf16` kernels) a failure instead of a skip.
pub const REQUIRE_BF16: &str = "GAGAVATAR_REQUIRE_BF16";

/// Whether the run requires the path guarded by `var` (set, and not `0`).
pub fn required(var: &str) -> bool {
    std::env::var_os(var).is_some_and(|v| v != "0")
}

/// The gate of a test of an optional path: `true` when `available`; otherwise a failure if the
/// run requires the path (`var`), else `SKIPPED <test>: <why>` on stderr and `false`.
pub fn optional_path(test: &str, available: bool, why: &str, var: &str) -> bool {
    if available {
        return true;
    }
    assert!(
        !required(var),
        "{test}: {why}, and {var} is set, so this path must run here"
    );
    eprintln!("SKIPPED {test}: {why} ({var}=1 makes this a failure)");
    false
}

/// Whether this CPU runs AVX-512F (the level our own SIMD kernels use).
pub fn has_avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512f")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// The gate of a test of AVX-512 kernels (see [`optional_path`]).
pub fn avx512_or_skip(test: &str) -> bool {
    optional_path(
        test,
        has_avx512(),
        "this CPU has no AVX-512F",
        REQUIRE_AVX512,
    )
}

/// Whether this CPU runs the bf16 kernels (AVX512F, AVX512BW and AVX512-BF16).
pub fn has_bf16() -> bool {
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

/// The gate of a test of the bf16 kernels (see [`optional_path`]).
pub fn bf16_or_skip(test: &str) -> bool {
    optional_path(
        test,
        has_bf16(),
        "this CPU has no AVX512-BF16",
        REQUIRE_BF16,
    )
}

/// `n` deterministic values in [-1, 1) from `seed` (xorshift64), so a failing case reproduces.
pub fn uniform_values(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        })
        .collect()
}

/// `a.max(b)`, but NaN when either is NaN: the step of a NaN-keeping fold,
/// `iter.fold(0.0, max_or_nan)`, where `f64::max` would drop the NaN.
pub fn max_or_nan(a: f64, b: f64) -> f64 {
    if a.is_nan() || b.is_nan() {
        f64::NAN
    } else {
        a.max(b)
    }
}

/// The largest of `values`, or NaN when any is NaN (0 for none).
pub fn nan_max(values: impl IntoIterator<Item = f64>) -> f64 {
    values.into_iter().fold(0.0, max_or_nan)
}

/// The largest absolute difference of two equally long slices and its index; a NaN on either
/// side counts as an infinite difference (and is reported at its index).
pub fn worst_abs_diff<T: Copy + Into<f64>>(a: &[T], b: &[T]) -> (usize, f64) {
    assert_eq!(
        a.len(),
        b.len(),
        "lengths differ: {} vs {}",
        a.len(),
        b.len()
    );
    let mut worst = (0usize, 0.0f64);
    for (i, (&x, &y)) in a.iter().zip(b).enumerate() {
        let d = (x.into() - y.into()).abs();
        let d = if d.is_nan() { f64::INFINITY } else { d };
        if d > worst.1 {
            worst = (i, d);
        }
    }
    worst
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_nan_is_the_worst_difference() {
        assert!(nan_max([0.5, f64::NAN, 2.0]).is_nan());
        assert!(nan_max([f64::NAN, 0.5]).is_nan());
        assert_eq!(nan_max([0.5, 2.0, 1.0]), 2.0);
        assert_eq!(nan_max(std::iter::empty()), 0.0);
        let (i, d) = worst_abs_diff(&[1.0f32, 2.0, 3.0], &[1.0, f32::NAN, 3.5]);
        assert_eq!((i, d), (1, f64::INFINITY));
        let (i, d) = worst_abs_diff(&[f32::NAN; 4], &[f32::NAN; 4]);
        assert_eq!((i, d), (0, f64::INFINITY));
        assert_eq!(worst_abs_diff(&[1.0f64, 2.0], &[1.25, 2.0]), (0, 0.25));
    }

    #[test]
    fn a_required_path_fails_and_an_optional_one_skips() {
        const VAR: &str = "GAGAVATAR_TESTKIT_SELF_TEST";
        std::env::remove_var(VAR);
        assert!(optional_path("t", true, "n/a", VAR));
        assert!(!optional_path("t", false, "absent", VAR));
        std::env::set_var(VAR, "0");
        assert!(!optional_path("t", false, "absent", VAR));
        std::env::set_var(VAR, "1");
        let r = std::panic::catch_unwind(|| optional_path("t", false, "absent", VAR));
        std::env::remove_var(VAR);
        let msg = r.expect_err("a required path must fail");
        let msg = msg.downcast_ref::<String>().cloned().unwrap_or_default();
        assert!(msg.contains("absent") && msg.contains(VAR), "{msg}");
    }
}
