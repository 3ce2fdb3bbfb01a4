//! Bilinear resizes of the network's sizes: dense interpolation matrices (candle matmuls) vs
//! the sparse-tap kernel. `RAYON_NUM_THREADS=2 cargo bench -p gagavatar-ops --bench resample`.

use candle_core::{Device, Tensor};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use gagavatar_ops::resample::{resize, resize_dense, ResizeMode};
use std::time::Duration;

fn bench(c: &mut Criterion) {
    let cases = [
        (
            "up_64x256_to_512_halfpixel",
            [1usize, 64, 256, 256],
            512usize,
            ResizeMode::HalfPixel,
        ),
        (
            "down_64x512_to_256_halfpixel",
            [1, 64, 512, 512],
            256,
            ResizeMode::HalfPixel,
        ),
        (
            "up_256x148_to_296_aligncorners",
            [1, 256, 148, 148],
            296,
            ResizeMode::AlignCorners,
        ),
        (
            "aa_3x512_to_518",
            [1, 3, 512, 512],
            518,
            ResizeMode::Antialias,
        ),
        (
            "aa_3x512_to_148",
            [1, 3, 512, 512],
            148,
            ResizeMode::Antialias,
        ),
    ];
    for (name, shape, out, mode) in cases {
        let x = Tensor::randn(0f32, 1.0, &shape[..], &Device::Cpu).unwrap();
        let mut group = c.benchmark_group(format!("resize/{name}"));
        group
            .sample_size(10)
            .warm_up_time(Duration::from_millis(300))
            .measurement_time(Duration::from_secs(2));
        group.bench_function(BenchmarkId::from_parameter("dense"), |b| {
            b.iter(|| resize_dense(&x, out, out, mode).unwrap())
        });
        group.bench_function(BenchmarkId::from_parameter("taps"), |b| {
            b.iter(|| resize(&x, out, out, mode).unwrap())
        });
        group.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
