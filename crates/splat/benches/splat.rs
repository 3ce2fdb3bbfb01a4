//! Criterion benchmark of the avatar-like scene (the same scene as `gagavatar bench splat`):
//! 2 x 296x296 lifted plane points + 5023 head points, 512x512, 32 channels.
//! Run with `cargo bench -p gagavatar-splat` (RAYON_NUM_THREADS sets the thread count).

use candle_core::{DType, Device, Tensor, Var};
use criterion::{criterion_group, criterion_main, Criterion};
use gagavatar_splat::testscene::{avatar_scene, Regime};
use gagavatar_splat::{splat, Gaussians};

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("splat_avatar_512");
    group.sample_size(10);
    for regime in [Regime::Small, Regime::Large] {
        let (scene, cam) = avatar_scene(296, 5023, 32, regime, 1);
        let dev = Device::Cpu;
        let tensors = scene.to_tensors(&dev).expect("scene tensors");
        let vars: Vec<Var> = tensors
            .iter()
            .map(|t| Var::from_tensor(t).expect("var"))
            .collect();
        let bg = Tensor::zeros(32, DType::F32, &dev).expect("background");
        let gaussians =
            |v: &[Var]| -> [Tensor; 5] { [0, 1, 2, 3, 4].map(|i| v[i].as_tensor().clone()) };
        group.bench_function(format!("{regime:?}/forward"), |b| {
            b.iter(|| {
                splat(
                    &Gaussians::from_tensors(&tensors),
                    &bg,
                    std::slice::from_ref(&cam),
                )
                .expect("splat")
            })
        });
        group.bench_function(format!("{regime:?}/forward+backward"), |b| {
            b.iter(|| {
                let var_tensors = gaussians(&vars);
                let out = splat(
                    &Gaussians::from_tensors(&var_tensors),
                    &bg,
                    std::slice::from_ref(&cam),
                )
                .expect("splat");
                out.image
                    .mean_all()
                    .and_then(|l| l.backward())
                    .expect("backward")
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
