//! Shared by the kernels' tests: one device per test binary and the comparison helpers.

use std::collections::HashMap;
use std::sync::{Arc, OnceLock};

use candle_core::{Device, Tensor};
use gagavatar_net::checkpoint::{build_model, init_weights};
use gagavatar_net::model::GagAvatar;
use gagavatar_net::ModelConfig;

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

/// The tests' device where it runs the tensor-core kernels ([`Gpu::mma_f16`]), or `None` with
/// a printed reason (lavapipe has no cooperative matrices: those kernels are checked by the
/// device run, see tools/device).
pub fn mma_gpu() -> Option<&'static Gpu> {
    let g = gpu()?;
    if !g.mma_f16 {
        eprintln!(
            "skipping: {} has no 16x16x16 f16 cooperative matrices",
            g.describe()
        );
        return None;
    }
    Some(g)
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

/// Asserts `max |want - got| <= rtol * max |want|` (gradients and images whose scale the
/// test does not know beforehand), naming the worst index and both values.
pub fn assert_close_rel(what: &str, want: &[f32], got: &[f32], rtol: f64) {
    let scale = want
        .iter()
        .fold(0f64, |m, v| m.max(v.abs() as f64))
        .max(1e-12);
    let (d, i, w, g) = max_diff(want, got);
    eprintln!("{what}: max abs difference {d:e} of the largest value {scale:e}");
    assert!(
        d <= rtol * scale,
        "{what}: max abs difference {d:e} > {:e} at index {i}: expected {w}, got {g}",
        rtol * scale
    );
}

/// Splatting is discontinuous: a Gaussian whose alpha at a pixel lies within rounding of 1/255
/// is taken on one side and skipped on the other, and a GPU may round its projection
/// differently from the CPU (a driver may fuse multiply-adds: SPIR-V allows it unless told
/// otherwise, and naga does not tell it). Such a flip moves that pixel by up to
/// ~2 alpha max|feature| in every channel. So a splatted `[C, H, W]` image is compared with
/// `tol` everywhere except at a few pixels, at most `max_pixels`, which may differ by up to
/// `flip_tol`. Prints the measured figures either way.
pub fn assert_close_but_flips(
    what: &str,
    want: &[f32],
    got: &[f32],
    plane: usize,
    tol: f64,
    flip_tol: f64,
    max_pixels: usize,
) {
    let (d, i, w, g) = max_diff(want, got);
    let mut flipped = std::collections::BTreeSet::new();
    let mut values = 0usize;
    for (k, (&a, &b)) in want.iter().zip(got).enumerate() {
        let e = (a as f64 - b as f64).abs();
        if e > tol || e.is_nan() {
            values += 1;
            flipped.insert(k % plane);
        }
    }
    eprintln!(
        "{what}: max abs difference {d:e} at index {i}; {values} values in {} of {plane} pixels \
         over {tol:e} (allowed: {max_pixels} pixels up to {flip_tol:e})",
        flipped.len()
    );
    assert!(
        d <= flip_tol,
        "{what}: max abs difference {d:e} > {flip_tol:e} (more than a flipped Gaussian can \
         move a pixel) at index {i}: expected {w}, got {g}"
    );
    assert!(
        flipped.len() <= max_pixels,
        "{what}: {} pixels differ by more than {tol:e}, at most {max_pixels} allowed \
         (first: {:?}); worst at index {i}: expected {w}, got {g}",
        flipped.len(),
        flipped.iter().take(8).collect::<Vec<_>>()
    );
}

/// The tests' device as an `Arc` (the drive and reconstruct keep one), shared.
pub fn shared_gpu() -> Option<Arc<Gpu>> {
    static GPU: std::sync::OnceLock<Option<Arc<Gpu>>> = std::sync::OnceLock::new();
    GPU.get_or_init(|| {
        // `gpu()` skips (or fails, when a device is required) where there is none; once one
        // was opened, failing to open it again is a real failure, never a skip.
        gpu()?;
        match Gpu::new(AdapterPolicy::AllowCpu) {
            Ok(g) => Some(Arc::new(g)),
            Err(e) => panic!("a second device on the adapter the tests opened: {e}"),
        }
    })
    .clone()
}

/// The model of `cfg` with seeded weights.
/// A tensor's values as f32, flattened.
pub fn flat(t: &candle_core::Tensor) -> Vec<f32> {
    t.flatten_all()
        .unwrap()
        .to_dtype(candle_core::DType::F32)
        .unwrap()
        .to_vec1()
        .unwrap()
}

/// `n` values in [-1, 1) from a xorshift stream of `seed` (reproducible test inputs).
pub fn seeded(n: usize, seed: u64) -> Vec<f32> {
    let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..n)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            ((x >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        })
        .collect()
}

pub fn seeded_model(cfg: &ModelConfig, seed: u64) -> GagAvatar {
    let map: HashMap<String, Tensor> = init_weights(cfg, seed)
        .unwrap()
        .into_iter()
        .map(|(k, (s, v))| (k, Tensor::from_vec(v, s, &Device::Cpu).unwrap()))
        .collect();
    build_model(cfg, map, &Device::Cpu).unwrap()
}
