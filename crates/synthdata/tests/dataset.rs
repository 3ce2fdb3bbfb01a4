//! The written dataset: determinism (seed -> bytes, whatever the thread count), the release
//! layout read back through `gagavatar_data::Dataset`, exact float32 records, splits by
//! identity.

mod common;

use gagavatar_data::Dataset;
use gagavatar_flame::synthesize;
use gagavatar_synthdata::{frame_name, Generator, NoProgress, SynthConfig, WriteOptions};

fn write(dir: &std::path::Path, config: SynthConfig, threads: usize) {
    let asset = synthesize(0);
    let g = Generator::new(&asset, config).unwrap();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| g.write_dataset(dir, WriteOptions::default(), &NoProgress))
        .unwrap();
}

#[test]
fn same_seed_gives_the_same_bytes_on_one_or_two_threads() {
    // 20 frames: a full FLAME block of 16 and a partial one.
    let config = SynthConfig::new(3, 20, 32, 5);
    let (a, b, c) = (
        common::scratch("det-a"),
        common::scratch("det-b"),
        common::scratch("det-c"),
    );
    write(&a, config.clone(), 1);
    write(&b, config.clone(), 2);
    let fa = common::files(&a);
    let fb = common::files(&b);
    let names: Vec<&str> = fa.iter().map(|f| f.0.as_str()).collect();
    assert_eq!(names, ["dataset.json", "img_lmdb/data.mdb", "optim.pkl"]);
    for (x, y) in fa.iter().zip(&fb) {
        assert_eq!(x.0, y.0);
        assert!(x.1 == y.1, "{} differs between 1 and 2 threads", x.0);
    }
    let mut other = config;
    other.seed = 6;
    write(&c, other, 2);
    let fc = common::files(&c);
    for (x, y) in fa.iter().zip(&fc) {
        if x.0 != "dataset.json" {
            assert!(x.1 != y.1, "{} is the same for seeds 5 and 6", x.0);
        }
    }
    for d in [a, b, c] {
        std::fs::remove_dir_all(d).unwrap();
    }
}

#[test]
fn dataset_reads_back_with_exact_records_and_identity_splits() {
    let mut config = SynthConfig::new(5, 3, 32, 9);
    config.holdout = Some(2);
    let dir = common::scratch("roundtrip");
    let asset = synthesize(0);
    let g = Generator::new(&asset, config).unwrap();
    let summary = g
        .write_dataset(&dir, WriteOptions::default(), &NoProgress)
        .unwrap();
    assert_eq!(summary.frames, 15);
    let ds = Dataset::open(&dir).unwrap();
    assert!(matches!(ds, Dataset::Release(_)));
    let names = |ids: &[usize]| -> Vec<String> {
        ids.iter()
            .flat_map(|&i| (0..3).map(move |f| frame_name(i, f)))
            .collect()
    };
    let s = ds.splits();
    assert_eq!(s.train, names(&[0, 1, 2]));
    assert_eq!(s.val, names(&[3]));
    assert_eq!(s.test, names(&[4]));
    let videos = ds.videos();
    assert_eq!(videos.len(), 5);
    for (v, frames) in &videos {
        assert_eq!(frames.len(), 3, "video {v}");
    }
    assert_eq!(ds.records().len(), 15);
    for i in 0..5 {
        for f in 0..3 {
            let want = g.render(i, f).unwrap();
            let got = ds.record(&want.name).unwrap();
            // Float32 in the pickle, and the generator's values are float32 already: equal.
            assert_eq!(got, &want.record, "record {}", want.name);
            assert_eq!(got.shapecode.len(), 300);
            assert_eq!(got.expcode.len(), 100);
            let tm = got.transform_matrix.unwrap();
            let all = got
                .shapecode
                .iter()
                .chain(&got.expcode)
                .chain(&got.posecode)
                .chain(&got.eyecode)
                .chain(tm.iter().flatten())
                .chain(got.bbox.as_ref().unwrap());
            for (k, &x) in all.enumerate() {
                assert_eq!(x, x as f32 as f64, "{} value {k} is not float32", want.name);
            }
            assert_eq!(got.posecode[..3], [0.0; 3], "{}: global pose", want.name);
            let img = ds.image(&want.name).unwrap();
            assert!(
                img == want.image,
                "image {} differs from a fresh render",
                want.name
            );
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
