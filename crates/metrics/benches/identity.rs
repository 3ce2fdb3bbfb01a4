//! The identity pipeline on the astronaut test picture: 5-point landmarks, the 150x150 chip
//! (plain and through dlib's image pyramid), the ResNet descriptor, and all of it together.
//! Run with `RAYON_NUM_THREADS=2 cargo bench -p gagavatar-metrics --bench identity`.

use std::path::Path;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use gagavatar_metrics::{
    default_asset_dir, extract_image_chip, face_chip_details, FaceRect, IdentityNet, CHIP_PADDING,
    CHIP_SIZE,
};
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

criterion_group!(benches, bench);
criterion_main!(benches);
