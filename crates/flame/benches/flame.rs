//! FLAME forward on the CPU (f32, full 300 + 100 components): one frame, and 100 frames batched,
//! through the full forward and through the driving path (identity cached once per shape code,
//! `forward_with_identity` per frame). Thread count follows candle's defaults (all cores; set
//! RAYON_NUM_THREADS to pin it).

use candle_core::{DType, Device, Tensor};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use gagavatar_flame::{synthesize, FlameConfig, FlameModel, FlameParams};

fn params(model: &FlameModel, batch: usize) -> FlameParams {
    let dev = &model.device;
    let r = |n: usize, s: f64| (Tensor::randn(0f32, 1f32, (batch, n), dev).unwrap() * s).unwrap();
    FlameParams {
        shape: r(300, 1.0),
        expression: r(100, 1.0),
        pose: r(6, 0.1),
        eye: r(6, 0.1),
    }
}

fn bench(c: &mut Criterion) {
    let asset = synthesize(0);
    let model = FlameModel::new(&asset, FlameConfig::default(), &Device::Cpu, DType::F32).unwrap();
    let mut g = c.benchmark_group("flame_forward");
    for batch in [1usize, 100] {
        let p = params(&model, batch);
        g.throughput(Throughput::Elements(batch as u64));
        g.bench_function(format!("batch_{batch}"), |b| {
            b.iter(|| model.forward(&p).unwrap())
        });
    }
    // Driving: one source shape for every frame, so its identity part is built once, outside
    // the timed loop.
    let identity = model.identity(&params(&model, 1).shape).unwrap();
    for batch in [1usize, 100] {
        let p = params(&model, batch);
        g.throughput(Throughput::Elements(batch as u64));
        g.bench_function(format!("cached_identity_batch_{batch}"), |b| {
            b.iter(|| {
                model
                    .forward_with_identity(&identity, &p.expression, &p.pose, &p.eye)
                    .unwrap()
            })
        });
    }
    g.throughput(Throughput::Elements(1));
    let p = params(&model, 1);
    g.bench_function("batch_1_with_landmarks", |b| {
        b.iter(|| {
            let out = model.forward(&p).unwrap();
            model.landmarks(&out.vertices, &p.pose).unwrap()
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
