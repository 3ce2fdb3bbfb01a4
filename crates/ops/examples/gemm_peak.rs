//! How close the ViT's f32 products run to this CPU's limit: the register-only AVX-512 FMA
//! peak (1 and 2 threads) beside the `gemm` crate's rate on the DINOv2 ViT-B/14 linear layers
//! (1370 tokens). The ViT's time is bounded below by its 302 GFLOP at that peak.
//!
//!     cargo run --release -p gagavatar-ops --example gemm_peak

use std::time::Instant;

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn fma_chain(n: usize) -> f32 {
    use std::arch::x86_64::*;
    // 12 independent accumulators hide the FMA latency; nothing touches memory.
    let mut acc = [_mm512_set1_ps(1.0); 12];
    let b = _mm512_set1_ps(0.999_999);
    let c = _mm512_set1_ps(1e-7);
    for _ in 0..n {
        for a in acc.iter_mut() {
            *a = _mm512_fmadd_ps(*a, b, c);
        }
    }
    let mut out = [0f32; 16];
    let mut s = 0.0;
    for a in acc {
        _mm512_storeu_ps(out.as_mut_ptr(), a);
        s += out[0];
    }
    s
}

fn peak(threads: usize) -> Option<f64> {
    #[cfg(target_arch = "x86_64")]
    {
        if !std::arch::is_x86_feature_detected!("avx512f") {
            return None;
        }
        let n = 100_000_000usize;
        let t = Instant::now();
        let handles: Vec<_> = (0..threads)
            // SAFETY: AVX-512F was detected above.
            .map(|_| std::thread::spawn(move || unsafe { fma_chain(n) }))
            .collect();
        for h in handles {
            std::hint::black_box(h.join().ok()?);
        }
        Some((threads * n * 12 * 32) as f64 / t.elapsed().as_secs_f64() / 1e9)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = threads;
        None
    }
}

fn main() {
    for threads in [1, 2] {
        match peak(threads) {
            Some(gf) => println!("FMA peak, {threads} thread(s): {gf:.0} GFLOP/s"),
            None => println!("no AVX-512F: no FMA peak figure"),
        }
    }
    let shapes = [
        ("qkv", 1370, 768, 2304),
        ("proj", 1370, 768, 768),
        ("fc1", 1370, 768, 3072),
        ("fc2", 1370, 3072, 768),
    ];
    let reps = 10;
    for (name, m, k, n) in shapes {
        let a: Vec<f32> = (0..m * k)
            .map(|i| (i % 1000) as f32 / 1000.0 - 0.5)
            .collect();
        let b: Vec<f32> = (0..k * n).map(|i| (i % 997) as f32 / 997.0 - 0.5).collect();
        let mut c = vec![0f32; m * n];
        let mut run = || {
            // SAFETY: a, b and c hold m x k, k x n and m x n values, row-major, not aliased.
            unsafe {
                gemm::gemm(
                    m,
                    n,
                    k,
                    c.as_mut_ptr(),
                    1,
                    n as isize,
                    false,
                    a.as_ptr(),
                    1,
                    k as isize,
                    b.as_ptr(),
                    1,
                    n as isize,
                    0.0,
                    1.0,
                    false,
                    false,
                    false,
                    gemm::Parallelism::Rayon(0),
                )
            }
        };
        run();
        let t = Instant::now();
        for _ in 0..reps {
            run();
        }
        let gf = 2.0 * (m * n * k * reps) as f64 / t.elapsed().as_secs_f64() / 1e9;
        println!("gemm {name} {m}x{k}x{n}: {gf:.0} GFLOP/s");
    }
}
