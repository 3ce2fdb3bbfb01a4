//! Speed of the training building blocks at release sizes:
//! `RAYON_NUM_THREADS=2 cargo bench -p gagavatar-train --bench train [-- FILTER]`.
//!
//! - `metrics/512`: PSNR + per-channel SSIM + luma SSIM of one 512x512 RGB pair;
//! - `nearest/*`: k-d tree over 2 x 296^2 = 175,232 lifted-like points (two jittered planes),
//!   5,023 head-like queries: build, query, and the whole `lifting_loss` (host copy, search,
//!   `index_select`, distance) plus its backward;
//! - `perceptual/512_fwd_bwd`: both networks on one 512x512 prediction (tracked) and its
//!   target, the distance, and the backward pass to the input (seeded weights).

use std::time::Duration;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarBuilder;
use criterion::{criterion_group, criterion_main, Criterion};
use gagavatar_splat::rng::Rng;
use gagavatar_train::metrics::{psnr, ssim, ssim_gray};
use gagavatar_train::nearest::{lifting_loss, KdTree};
use gagavatar_train::perceptual::{seeded_weights, PerceptualLoss};

fn lifted_like(rng: &mut Rng) -> Vec<[f32; 3]> {
    let s = 296;
    let mut pts = Vec::with_capacity(2 * s * s);
    for sign in [1.0f64, -1.0] {
        for i in 0..s {
            for j in 0..s {
                let u = 1.0 - 2.0 * j as f64 / (s - 1) as f64;
                let v = 1.0 - 2.0 * i as f64 / (s - 1) as f64;
                // Rays of the point plane at depth ~5 (FLAME scale 5), lifted by a sigmoid.
                let d = sign * rng.uniform();
                let z = 5.0 + d;
                pts.push([(u / 12.0 * z) as f32, (v / 12.0 * z) as f32, z as f32]);
            }
        }
    }
    pts
}

fn head_like(rng: &mut Rng, n: usize) -> Vec<[f32; 3]> {
    (0..n)
        .map(|_| {
            let t = rng.uniform() * std::f64::consts::PI;
            let p = rng.uniform() * 2.0 * std::f64::consts::PI;
            [
                (0.4 * t.sin() * p.cos()) as f32,
                (0.5 * t.cos()) as f32,
                (5.0 + 0.4 * t.sin() * p.sin()) as f32,
            ]
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let dev = Device::Cpu;
    let mut rng = Rng::from_state(1);

    {
        let a = Tensor::rand(0f32, 1.0, (1, 3, 512, 512), &dev).unwrap();
        let b = (a.affine(0.9, 0.05).unwrap()
            + Tensor::randn(0f32, 0.02, (1, 3, 512, 512), &dev).unwrap())
        .unwrap();
        let mut g = c.benchmark_group("metrics");
        g.sample_size(20).warm_up_time(Duration::from_millis(500));
        g.bench_function("512_psnr_ssim_luma", |bch| {
            bch.iter(|| {
                (
                    psnr(&b, &a).unwrap(),
                    ssim(&b, &a).unwrap(),
                    ssim_gray(&b, &a).unwrap(),
                )
            })
        });
        g.bench_function("512_ssim_per_channel", |bch| {
            bch.iter(|| ssim(&b, &a).unwrap())
        });
        g.finish();
    }

    {
        let pts = lifted_like(&mut rng);
        let qs = head_like(&mut rng, 5023);
        let tree = KdTree::new(&pts).unwrap();
        let mut g = c.benchmark_group("nearest");
        g.sample_size(20).warm_up_time(Duration::from_millis(500));
        g.bench_function("build_175k", |bch| bch.iter(|| KdTree::new(&pts).unwrap()));
        g.bench_function("query_5023", |bch| {
            bch.iter(|| tree.nearest_all(&qs).unwrap())
        });
        let flat: Vec<f32> = pts.iter().flatten().copied().collect();
        let lifted =
            Var::from_tensor(&Tensor::from_vec(flat, (1, pts.len(), 3), &dev).unwrap()).unwrap();
        let tflat: Vec<f32> = qs.iter().flatten().copied().collect();
        let targets = Tensor::from_vec(tflat, (1, qs.len(), 3), &dev).unwrap();
        g.bench_function("lifting_loss_fwd_bwd_175k_x_5023", |bch| {
            bch.iter(|| {
                lifting_loss(lifted.as_tensor(), &targets)
                    .unwrap()
                    .backward()
                    .unwrap()
            })
        });
        g.finish();
    }

    {
        let w = seeded_weights(7).unwrap();
        let p = PerceptualLoss::new(VarBuilder::from_tensors(w, DType::F32, &dev)).unwrap();
        let x =
            Var::from_tensor(&Tensor::rand(0f32, 1.0, (1, 3, 512, 512), &dev).unwrap()).unwrap();
        let y = Tensor::rand(0f32, 1.0, (1, 3, 512, 512), &dev).unwrap();
        let mut g = c.benchmark_group("perceptual");
        g.sample_size(10)
            .warm_up_time(Duration::from_millis(100))
            .measurement_time(Duration::from_secs(20));
        g.bench_function("512_fwd_bwd", |bch| {
            bch.iter(|| p.loss(x.as_tensor(), &y).unwrap().backward().unwrap())
        });
        g.bench_function("512_fwd_only", |bch| {
            bch.iter(|| p.loss(&x.as_tensor().detach(), &y).unwrap())
        });
        g.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
