//! The identity pipeline on the astronaut test picture: 5-point landmarks, the 150x150 chip
//! (plain and through dlib's image pyramid), the ResNet descriptor, and all of it together.
//! Run with `RAYON_NUM_THREADS=2 cargo bench -p gagavatar-metrics --bench identity`.

use std::path::Path;
use std::time::Duration;

use candle_core::{Device, Tensor};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use gagavatar_metrics::{
    default_asset_dir, extract_image_chip, face_chip_details, FaceRect, IdentityNet, CHIP_PADDING,
    CHIP_SIZE,
};
use gagavatar_ops::{conv2d_with_algo, Conv2dSpec, ConvAlgo};
use image::RgbImage;

fn astronaut() -> RgbImage {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden/astronaut_head.png");
    image::open(p).expect("test picture").to_rgb8()
}

/// 4x nearest-neighbour upscale (a face of about 360 pixels: the chip goes through the pyramid).
fn upscale4(img: &RgbImage) -> RgbImage {
    RgbImage::from_fn(img.width() * 4, img.height() * 4, |x, y| {
        *img.get_pixel(x / 4, y / 4)
    })
}

fn bench(c: &mut Criterion) {
    let net = IdentityNet::load(&default_asset_dir()).expect("identity models");
    let img = astronaut();
    let big = upscale4(&img);
    let rect = FaceRect::new(86, 76, 175, 166).unwrap();
    let big_rect = FaceRect::new(344, 304, 703, 667).unwrap();
    let lm = net.predictor().predict(&img, rect).unwrap();
    let lm_big = net.predictor().predict(&big, big_rect).unwrap();
    let det = face_chip_details(&lm, CHIP_SIZE, CHIP_PADDING).unwrap();
    let det_big = face_chip_details(&lm_big, CHIP_SIZE, CHIP_PADDING).unwrap();
    let chip = extract_image_chip(&img, &det).unwrap();

    let mut g = c.benchmark_group("identity");
    g.sample_size(20)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(4));
    g.bench_function("landmarks_5", |b| {
        b.iter(|| net.predictor().predict(&img, rect).unwrap())
    });
    g.bench_function("chip_256px_image", |b| {
        b.iter(|| extract_image_chip(&img, &det).unwrap())
    });
    g.bench_function("chip_1024px_image_pyramid", |b| {
        b.iter(|| extract_image_chip(&big, &det_big).unwrap())
    });
    g.bench_function("resnet_1_chip", |b| {
        b.iter(|| net.embed_chip(&chip).unwrap())
    });
    g.bench_function("resnet_batch_2_chips", |b| {
        b.iter(|| net.embed_chips(&[&chip, &chip]).unwrap())
    });
    g.bench_function("embed_end_to_end", |b| {
        b.iter(|| net.embed(&img, rect).unwrap())
    });
    g.finish();
}

/// The network's convolution shapes: (name, cin, cout, kernel, stride, input side).
const CONVS: &[(&str, usize, usize, usize, usize, usize)] = &[
    ("stem_7x7s2_3to32_150", 3, 32, 7, 2, 150),
    ("3x3_32_35", 32, 32, 3, 1, 35),
    ("3x3s2_32to64_35", 32, 64, 3, 2, 35),
    ("3x3_64_17", 64, 64, 3, 1, 17),
    ("3x3_128_8", 128, 128, 3, 1, 8),
    ("3x3_256_3", 256, 256, 3, 1, 3),
];

/// Which convolution kernel suits these small maps: the automatic choice (Winograd for 3x3
/// stride 1) against the banded GEMM.
fn convs(c: &mut Criterion) {
    let dev = Device::Cpu;
    for &(name, cin, cout, k, stride, side) in CONVS {
        let x = Tensor::randn(0f32, 1.0, (1, cin, side, side), &dev).unwrap();
        let w = Tensor::randn(0f32, 0.05, (cout, cin, k, k), &dev).unwrap();
        let b = Tensor::randn(0f32, 1.0, cout, &dev).unwrap();
        let spec = Conv2dSpec {
            stride,
            padding: if stride == 1 { k / 2 } else { 0 },
        };
        let mut g = c.benchmark_group(format!("identity_convs/{name}"));
        g.sample_size(20)
            .warm_up_time(Duration::from_millis(300))
            .measurement_time(Duration::from_secs(2));
        for algo in [ConvAlgo::Auto, ConvAlgo::Gemm] {
            g.bench_function(BenchmarkId::from_parameter(format!("{algo:?}")), |bch| {
                bch.iter(|| conv2d_with_algo(&x, &w, Some(&b), spec, algo).unwrap())
            });
        }
        g.finish();
    }
}

criterion_group!(benches, bench, convs);
criterion_main!(benches);
