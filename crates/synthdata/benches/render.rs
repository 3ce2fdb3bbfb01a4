//! Time to render one synthetic frame (FLAME block share, rasterize, shade, PNG) by size.

use criterion::{criterion_group, criterion_main, Criterion};
use gagavatar_flame::synthesize;
use gagavatar_synthdata::{Generator, SynthConfig};

fn render(c: &mut Criterion) {
    let asset = synthesize(0);
    let mut group = c.benchmark_group("synth_frame");
    group.sample_size(10);
    for size in [64, 128, 512] {
        let g = Generator::new(&asset, SynthConfig::new(1, 16, size, 0)).unwrap();
        let (s, verts) = g.frame_vertices(0, 3).unwrap();
        let app = g.appearance(0);
        group.bench_function(format!("shade_{size}"), |b| {
            b.iter(|| g.shade(&app, &s.transform, &verts).unwrap())
        });
        group.bench_function(format!("encode_png_{size}"), |b| {
            let img = g.shade(&app, &s.transform, &verts).unwrap();
            b.iter(|| gagavatar_data::encode_png(&img).unwrap())
        });
    }
    let g = Generator::new(&asset, SynthConfig::new(1, 16, 64, 0)).unwrap();
    group.bench_function("flame_block_16", |b| {
        b.iter(|| g.frame_vertices(0, 0).unwrap())
    });
    group.finish();
}

criterion_group!(benches, render);
criterion_main!(benches);
