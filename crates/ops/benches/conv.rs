//! Convolution shapes of the network (DPT head, Gaussian generators, StyleUNet renderer):
//! candle's conv2d vs our GEMM and Winograd paths and the automatic choice, f32, batch 1.
//! Run with `RAYON_NUM_THREADS=2 cargo bench -p gagavatar-ops --bench conv [-- filter]`;
//! `benches/conv_torch.py` times PyTorch on the same shapes.

use candle_core::{DType, Device, Tensor, Var};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use gagavatar_ops::{conv2d_with_algo, Conv2dSpec, ConvAlgo};
use std::time::Duration;

/// (name, cin, cout, k, stride, padding, h, w); keep in sync with conv_torch.py.
/// (name, cin, cout, k, stride, padding, h, w)
type ConvShape = (
    &'static str,
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
);

const SHAPES: &[ConvShape] = &[
    ("k3_64to32_512", 64, 32, 3, 1, 1, 512, 512),
    ("k3_16to16_512", 16, 16, 3, 1, 1, 512, 512),
    ("k3_32to32_512", 32, 32, 3, 1, 1, 512, 512),
    ("k3_128to128_296", 128, 128, 3, 1, 1, 296, 296),
    ("k3_283to128_296", 283, 128, 3, 1, 1, 296, 296),
    ("k3_256to256_148", 256, 256, 3, 1, 1, 148, 148),
    ("k3_1027to256_19", 1027, 256, 3, 1, 1, 19, 19),
    ("k1_128to41_296", 128, 41, 1, 1, 0, 296, 296),
    ("k3s2_256to256_37", 256, 256, 3, 2, 1, 37, 37),
];

fn inputs(cin: usize, cout: usize, k: usize, h: usize, w: usize) -> (Tensor, Tensor, Tensor) {
    let dev = Device::Cpu;
    let x = Tensor::randn(0f32, 1.0, (1, cin, h, w), &dev).unwrap();
    let wt = (Tensor::randn(0f32, 1.0, (cout, cin, k, k), &dev).unwrap() * 0.05).unwrap();
    let b = Tensor::randn(0f32, 1.0, cout, &dev).unwrap();
    (x, wt, b)
}

fn forward(c: &mut Criterion) {
    for &(name, cin, cout, k, stride, padding, h, w) in SHAPES {
        let (x, wt, b) = inputs(cin, cout, k, h, w);
        let spec = Conv2dSpec { stride, padding };
        let mut group = c.benchmark_group(format!("conv/{name}"));
        group
            .sample_size(10)
            .warm_up_time(Duration::from_millis(500))
            .measurement_time(Duration::from_secs(3));
        let mut algos = vec![ConvAlgo::Candle, ConvAlgo::Gemm];
        if k == 3 && stride == 1 {
            algos.push(ConvAlgo::Winograd);
        }
        algos.push(ConvAlgo::Auto);
        for algo in algos {
            group.bench_function(BenchmarkId::from_parameter(format!("{algo:?}")), |bench| {
                bench.iter(|| conv2d_with_algo(&x, &wt, Some(&b), spec, algo).unwrap())
            });
        }
        group.finish();
    }
}

/// Gradients wrt input, weight and bias of the 296x296 128->128 layer (the Gaussian
/// generator's), forward excluded: the graph is built once and `backward` run repeatedly.
fn backward(c: &mut Criterion) {
    let (x, wt, b) = inputs(128, 128, 3, 296, 296);
    let spec = Conv2dSpec {
        stride: 1,
        padding: 1,
    };
    let r = Tensor::randn(0f32, 1.0, (1, 128, 296, 296), &Device::Cpu).unwrap();
    let mut group = c.benchmark_group("conv_backward/k3_128to128_296");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(5));
    for algo in [ConvAlgo::Candle, ConvAlgo::Auto] {
        let vars = [&x, &wt, &b].map(|t| Var::from_tensor(t).unwrap());
        let y = conv2d_with_algo(
            vars[0].as_tensor(),
            vars[1].as_tensor(),
            Some(vars[2].as_tensor()),
            spec,
            algo,
        )
        .unwrap();
        let loss = (y * &r)
            .unwrap()
            .sum_all()
            .unwrap()
            .to_dtype(DType::F32)
            .unwrap();
        group.bench_function(BenchmarkId::from_parameter(format!("{algo:?}")), |bench| {
            bench.iter(|| loss.backward().unwrap())
        });
    }
    group.finish();
}

criterion_group!(benches, forward, backward);
criterion_main!(benches);
