//! Shared by the kernels' tests: one device per test binary and the comparison helpers.

use std::sync::OnceLock;

use crate::device::{AdapterPolicy, Gpu};

/// Set (by `.ci/run`) to make a missing Vulkan device a test failure instead of a skip.
pub const REQUIRE_ENV: &str = "GAGAVATAR_REQUIRE_GPU_TESTS";

/// The device for the tests (any adapter, a CPU-emulated one included), or `None` with a
/// printed reason when there is none and the environment does not require one.
pub fn gpu() -> Option<&'static Gpu> {
    static GPU: OnceLock<Result<Gpu, String>> = OnceLock::new();
    let opened = GPU.get_or_init(|| {
        let g = Gpu::new(AdapterPolicy::AllowCpu).map_err(|e| e.to_string());
        if let Ok(g) = &g {
            // Once per test binary: the log says which device the GPU tests covered.
            eprintln!("GPU tests on {}", g.describe());
        }
        g
    });
    match opened {
        Ok(g) => Some(g),
        Err(e) => {
            if std::env::var(REQUIRE_ENV).is_ok_and(|v| v != "0") {
                panic!("{REQUIRE_ENV} is set but there is no GPU device: {e}");
            }
            eprintln!("skipping GPU test: {e}");
            None
        }
    }
}

/// Largest absolute difference, with its index, expected and actual values (NaN counts as
/// an infinite difference).
pub fn max_diff(want: &[f32], got: &[f32]) -> (f64, usize, f32, f32) {
    assert_eq!(want.len(), got.len(), "lengths differ");
    let mut worst = (0.0f64, 0usize, 0f32, 0f32);
    for (i, (&w, &g)) in want.iter().zip(got).enumerate() {
        let d = (w as f64 - g as f64).abs();
        let d = if d.is_nan() { f64::INFINITY } else { d };
        if d > worst.0 {
            worst = (d, i, w, g);
        }
    }
    worst
}

/// Asserts `max |want - got| <= tol`, naming the worst index and both values.
pub fn assert_close(what: &str, want: &[f32], got: &[f32], tol: f64) {
    let (d, i, w, g) = max_diff(want, got);
    assert!(
        d <= tol,
        "{what}: max abs difference {d:e} > {tol:e} at index {i}: expected {w}, got {g}"
    );
    eprintln!("{what}: max abs difference {d:e} (tolerance {tol:e})");
}
