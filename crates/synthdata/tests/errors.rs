//! Bad settings and unusable output folders are clear errors that write nothing.

mod common;

use gagavatar_flame::synthesize;
use gagavatar_synthdata::{Generator, NoProgress, Progress, SynthConfig, SynthError, WriteOptions};

fn config_error(config: SynthConfig) -> (&'static str, String) {
    match Generator::new(&synthesize(0), config) {
        Err(SynthError::Config { field, reason }) => (field, reason),
        Err(other) => panic!("expected a config error, got {other}"),
        Ok(_) => panic!("expected a config error, got a generator"),
    }
}

#[test]
fn bad_settings_name_the_setting() {
    let base = SynthConfig::new(4, 2, 64, 0);
    let cases: Vec<(SynthConfig, &str)> = vec![
        (
            SynthConfig {
                identities: 0,
                ..base.clone()
            },
            "identities",
        ),
        (
            SynthConfig {
                frames: 0,
                ..base.clone()
            },
            "frames",
        ),
        (
            SynthConfig {
                size: 0,
                ..base.clone()
            },
            "size",
        ),
        (
            SynthConfig {
                size: 4097,
                ..base.clone()
            },
            "size",
        ),
        (
            SynthConfig {
                holdout: Some(4),
                ..base.clone()
            },
            "holdout",
        ),
        (
            SynthConfig {
                supersample: Some(0),
                ..base.clone()
            },
            "supersample",
        ),
        (
            SynthConfig {
                supersample: Some(9),
                ..base.clone()
            },
            "supersample",
        ),
        (
            SynthConfig {
                identities: 1,
                holdout: Some(1),
                ..base.clone()
            },
            "holdout",
        ),
    ];
    for (config, field) in cases {
        let (got, reason) = config_error(config);
        assert_eq!(got, field, "{reason}");
        let msg = SynthError::Config { field: got, reason }.to_string();
        assert!(msg.contains(field), "{msg}");
    }
    let mut s = base.clone();
    s.sampling.shape_components = 301;
    assert_eq!(config_error(s).0, "shape_components");
    let mut s = base.clone();
    s.sampling.exp_sigma = f64::NAN;
    assert_eq!(config_error(s).0, "exp_sigma");
    let mut s = base;
    s.sampling.distance = (9.0, 8.0);
    assert_eq!(config_error(s).0, "distance");
    // One identity trains alone by default (no held-out set).
    let g = Generator::new(&synthesize(0), SynthConfig::new(1, 2, 16, 0)).unwrap();
    assert!(g.splits().val.is_empty() && g.splits().train.len() == 2);
    // Ten identities hold one out by default, used for both val and test.
    let g = Generator::new(&synthesize(0), SynthConfig::new(10, 2, 16, 0)).unwrap();
    let s = g.splits();
    assert_eq!(s.train.len(), 18);
    assert_eq!(s.val, ["id0009_0", "id0009_1"]);
    assert_eq!(s.test, s.val);
}

#[test]
fn unusable_output_folders_are_errors_and_nothing_is_written() {
    let g = Generator::new(&synthesize(0), SynthConfig::new(2, 2, 16, 0)).unwrap();
    let root = common::scratch("errors");
    std::fs::create_dir_all(&root).unwrap();
    let listing = || {
        let mut v: Vec<String> = std::fs::read_dir(&root)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    };

    // Under a regular file: the folder cannot be created.
    let file = root.join("a-file");
    std::fs::write(&file, b"keep").unwrap();
    let err = g
        .write_dataset(&file.join("out"), WriteOptions::default(), &NoProgress)
        .unwrap_err();
    assert!(matches!(err, SynthError::Output { .. }), "{err}");
    assert!(err.to_string().contains("a-file"), "{err}");
    assert_eq!(std::fs::read(&file).unwrap(), b"keep");

    // The output path is a file.
    let err = g
        .write_dataset(&file, WriteOptions::default(), &NoProgress)
        .unwrap_err();
    assert!(err.to_string().contains("not a folder"), "{err}");

    // A non-empty folder is kept unless overwriting is allowed.
    let full = root.join("full");
    std::fs::create_dir(&full).unwrap();
    std::fs::write(full.join("mine.txt"), b"precious").unwrap();
    let err = g
        .write_dataset(&full, WriteOptions::default(), &NoProgress)
        .unwrap_err();
    assert!(err.to_string().contains("not empty"), "{err}");
    assert_eq!(std::fs::read(full.join("mine.txt")).unwrap(), b"precious");
    assert_eq!(listing(), ["a-file", "full"]);

    // Cancelled before the end: no output, no temporaries.
    struct Cancel;
    impl Progress for Cancel {
        fn cancelled(&self) -> bool {
            true
        }
    }
    let out = root.join("cancelled");
    let err = g
        .write_dataset(&out, WriteOptions::default(), &Cancel)
        .unwrap_err();
    assert!(matches!(err, SynthError::Interrupted), "{err}");
    assert_eq!(listing(), ["a-file", "full"]);

    // Overwriting replaces the folder as a whole.
    g.write_dataset(&full, WriteOptions { overwrite: true }, &NoProgress)
        .unwrap();
    assert!(!full.join("mine.txt").exists());
    assert!(full.join("optim.pkl").is_file());
    // An empty existing folder is fine without overwriting.
    let empty = root.join("empty");
    std::fs::create_dir(&empty).unwrap();
    g.write_dataset(&empty, WriteOptions::default(), &NoProgress)
        .unwrap();
    assert_eq!(listing(), ["a-file", "empty", "full"]);
    std::fs::remove_dir_all(&root).unwrap();
}

/// A cancellation that arrives while images are being rendered also leaves nothing behind.
#[test]
fn cancellation_mid_run_leaves_nothing() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    struct After(AtomicUsize);
    impl Progress for After {
        fn cancelled(&self) -> bool {
            // The first check is before the records; let one chunk render, then stop.
            self.0.fetch_add(1, Ordering::Relaxed) >= 2
        }
    }
    // 40 identities = 40 FLAME blocks = 3 chunks of 16.
    let g = Generator::new(&synthesize(0), SynthConfig::new(40, 1, 16, 0)).unwrap();
    let root = common::scratch("cancel-mid");
    std::fs::create_dir_all(&root).unwrap();
    let err = g
        .write_dataset(
            &root.join("out"),
            WriteOptions::default(),
            &After(AtomicUsize::new(0)),
        )
        .unwrap_err();
    assert!(matches!(err, SynthError::Interrupted), "{err}");
    assert_eq!(std::fs::read_dir(&root).unwrap().count(), 0);
    std::fs::remove_dir_all(&root).unwrap();
}
