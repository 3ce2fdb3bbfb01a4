//! Driving sequences (tracked folders, pickles, JSON) and source records.

// The same fixtures as the formats crate's tests (temporary folders, pickles, LMDBs).
#[path = "../../formats/tests/common/mod.rs"]
mod common;

use std::path::Path;

use common::{copy_dir, data, f32s, hex, TempDir};
use gagavatar_data::driver::DEFAULT_FPS;
use gagavatar_data::{read_source_record, DataError, DriverSequence};

/// See `images.rs`: the one JPEG frame of `release_small` against the pixels before encoding
/// (PIL measured 4 levels of JPEG loss on it; one more for decoder rounding).
const JPEG_TOLERANCE: i32 = 5;

const NATURAL: [&str; 6] = [
    "spk_a_0",
    "spk_a_1",
    "spk_a_2",
    "spk_a_10",
    "spk_b_x_0",
    "spk_b_x_3",
];

fn assert_pixels(img: &image::RgbImage, want_hex: &str, tol: i32, what: &str) {
    let want = hex(want_hex);
    assert_eq!(img.as_raw().len(), want.len(), "{what}");
    for (i, (g, w)) in img.as_raw().iter().zip(&want).enumerate() {
        let d = (i32::from(*g) - i32::from(*w)).abs();
        assert!(d <= tol, "{what}: byte {i}: expected {w}, actual {g}");
    }
}

#[test]
fn tracked_folder_in_natural_order_with_images() {
    let exp = common::read_json("release_small/expected.json");
    let seq = DriverSequence::open(&data("release_small")).unwrap();
    assert_eq!(seq.fps, DEFAULT_FPS);
    let names: Vec<&str> = seq.frames.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, NATURAL);
    assert!(seq.has_images());
    for (i, f) in seq.frames.iter().enumerate() {
        let want = f32s(exp["records"][&f.name]["expcode"]["hex"].as_str().unwrap());
        assert_eq!(
            f.record.expcode,
            want.iter().map(|&x| f64::from(x)).collect::<Vec<_>>(),
            "{}",
            f.name
        );
        let img = seq.image(i).unwrap().unwrap();
        let tol = if f.name == exp["jpeg_frame"] {
            JPEG_TOLERANCE
        } else {
            0
        };
        assert_pixels(&img, exp["pixels"][&f.name].as_str().unwrap(), tol, &f.name);
    }
    assert!(seq.image(6).is_err());
    // The pickle named directly also finds the folder's img_lmdb.
    let seq = DriverSequence::open(&data("release_small/optim.pkl")).unwrap();
    assert!(seq.has_images() && seq.len() == 6);
}

#[test]
fn smoothed_is_preferred_and_images_are_optional() {
    let dir = TempDir::new("driver");
    std::fs::copy(data("records_p4.pkl"), dir.path().join("smoothed.pkl")).unwrap();
    std::fs::copy(
        data("release_small/optim.pkl"),
        dir.path().join("optim.pkl"),
    )
    .unwrap();
    let seq = DriverSequence::open(dir.path()).unwrap();
    let names: Vec<&str> = seq.frames.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, ["id_01_clip_0", "id_01_clip_2", "id_01_clip_10"]);
    assert!(!seq.has_images());
    assert!(seq.image(0).unwrap().is_none());
    // A frame missing from img_lmdb is an error naming it.
    copy_dir(
        &data("release_small/img_lmdb"),
        &dir.path().join("img_lmdb"),
    );
    let seq = DriverSequence::open(dir.path()).unwrap();
    let e = seq.image(0).unwrap_err().to_string();
    assert!(
        e.contains("id_01_clip_0") && e.contains("no such entry"),
        "{e}"
    );
}

#[test]
fn a_tracked_folder_keeps_the_rate_its_track_json_records() {
    let dir = TempDir::new("driver-fps");
    std::fs::copy(data("records_p4.pkl"), dir.path().join("optim.pkl")).unwrap();
    let track = dir.path().join("track.json");
    // No track.json (a release folder), or one without a rate (a photo): 25 fps.
    assert_eq!(DriverSequence::open(dir.path()).unwrap().fps, 25.0);
    std::fs::write(&track, r#"{"kind": "photo"}"#).unwrap();
    assert_eq!(DriverSequence::open(dir.path()).unwrap().fps, 25.0);
    std::fs::write(&track, r#"{"kind": "video", "fps": 29.97002997002997}"#).unwrap();
    assert_eq!(
        DriverSequence::open(dir.path()).unwrap().fps,
        30000.0 / 1001.0
    );
    for bad in [
        r#"{"fps": 0}"#,
        r#"{"fps": -5}"#,
        r#"{"fps": "fast"}"#,
        "not json",
    ] {
        std::fs::write(&track, bad).unwrap();
        let e = DriverSequence::open(dir.path()).unwrap_err().to_string();
        assert!(e.contains("track.json"), "{bad}: {e}");
    }
}

fn record_json(k: usize, with_image: bool, name: Option<&str>) -> serde_json::Value {
    let mut v = serde_json::json!({
        "shapecode": vec![0.01 * k as f64; 300],
        "expcode": vec![0.1; 100],
        "posecode": [0, 0, 0, 0.1, 0, 0],
        "eyecode": [0, 0, 0, 0, 0, 0],
        "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 9]],
    });
    if with_image {
        v["image"] = serde_json::json!(format!("frames/{k}.png"));
    }
    if let Some(n) = name {
        v["name"] = serde_json::json!(n);
    }
    v
}

fn write_json(dir: &Path, doc: &serde_json::Value) -> std::path::PathBuf {
    let p = dir.join("drive.json");
    std::fs::write(&p, serde_json::to_string(doc).unwrap()).unwrap();
    p
}

#[test]
fn json_sequences() {
    let dir = TempDir::new("driver-json");
    std::fs::create_dir_all(dir.path().join("frames")).unwrap();
    for k in 0..3 {
        std::fs::copy(
            data("img_rgb.png"),
            dir.path().join(format!("frames/{k}.png")),
        )
        .unwrap();
    }
    let doc = serde_json::json!({
        "fps": 30,
        "frames": [record_json(0, true, Some("b_10")), record_json(1, true, None), record_json(2, true, Some("a_1"))],
    });
    let seq = DriverSequence::open(&write_json(dir.path(), &doc)).unwrap();
    assert_eq!(seq.fps, 30.0);
    // File order is kept; unnamed frames get their index.
    let names: Vec<&str> = seq.frames.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, ["b_10", "000001", "a_1"]);
    assert_eq!(seq.frames[2].record.shapecode[0], 0.02);
    assert!(seq.has_images());
    let img = seq.image(1).unwrap().unwrap();
    assert_eq!((img.width(), img.height()), (7, 5));

    // Without images and fps.
    let doc = serde_json::json!({ "frames": [record_json(0, false, None)] });
    let seq = DriverSequence::open(&write_json(dir.path(), &doc)).unwrap();
    assert_eq!(seq.fps, DEFAULT_FPS);
    assert!(!seq.has_images() && seq.image(0).unwrap().is_none());
}

#[test]
fn broken_json_sequences_name_frame_and_field() {
    let dir = TempDir::new("driver-bad");
    let good = |k| record_json(k, false, None);
    let drop_field = |k: usize, field: &str| {
        let mut v = good(k);
        v.as_object_mut().unwrap().remove(field);
        v
    };
    let with = |k: usize, field: &str, value: serde_json::Value| {
        let mut v = good(k);
        v[field] = value;
        v
    };
    let cases: Vec<(serde_json::Value, &str, &str, &str)> = vec![
        (
            serde_json::json!({"frames": [good(0), drop_field(1, "expcode")]}),
            "#1",
            "expcode",
            "is missing",
        ),
        (
            serde_json::json!({"frames": [good(0), good(1), drop_field(2, "transform_matrix")]}),
            "#2",
            "transform_matrix",
            "is missing",
        ),
        (
            serde_json::json!({"frames": [with(0, "posecode", serde_json::json!("x"))]}),
            "#0",
            "posecode",
            "not an array",
        ),
        (
            serde_json::json!({"frames": [with(0, "transform_matrix", serde_json::json!([[1, 0, 0], [0, 1, 0], [0, 0, 1]]))]}),
            "#0",
            "transform_matrix",
            "row 0 has 3 values",
        ),
        (
            serde_json::json!({"frames": [with(0, "name", serde_json::json!("vid_3")), with(1, "eyecode", serde_json::json!([0, "a"]))]}),
            "#1",
            "eyecode",
            "element 1",
        ),
        (
            serde_json::json!({"frames": [record_json(0, true, None), good(1)]}),
            "#1",
            "image",
            "all or none",
        ),
    ];
    for (doc, frame, field, needle) in cases {
        let p = write_json(dir.path(), &doc);
        let e = DriverSequence::open(&p).unwrap_err();
        let text = e.to_string();
        match &e {
            DataError::Record {
                frame: f,
                field: fi,
                reason,
                ..
            } => {
                assert_eq!(f, frame, "{text}");
                assert_eq!(fi, field, "{text}");
                assert!(reason.contains(needle), "{text}");
            }
            other => panic!("{other}"),
        }
        assert!(
            text.contains("drive.json") && !text.contains('\n'),
            "{text}"
        );
    }
    for (doc, needle) in [
        (serde_json::json!({"fps": -1, "frames": [good(0)]}), "`fps`"),
        (serde_json::json!({"frames": []}), "`frames` is empty"),
        (serde_json::json!({"fps": 25}), "`frames` is missing"),
        (serde_json::json!([1, 2]), "top level"),
    ] {
        let e = DriverSequence::open(&write_json(dir.path(), &doc))
            .unwrap_err()
            .to_string();
        assert!(e.contains(needle), "{e}");
    }
    std::fs::write(dir.path().join("drive.json"), "{\"frames\": [").unwrap();
    let e = DriverSequence::open(&dir.path().join("drive.json"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("invalid JSON"), "{e}");
    let e = DriverSequence::open(&dir.path().join("missing.json"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("missing.json"), "{e}");
    let e = DriverSequence::open(dir.path()).unwrap_err().to_string();
    assert!(e.contains("neither smoothed.pkl nor optim.pkl"), "{e}");
    // A JSON frame image that does not exist fails when read, naming the file.
    let doc = serde_json::json!({"frames": [record_json(0, true, None)]});
    let seq = DriverSequence::open(&write_json(dir.path(), &doc)).unwrap();
    let e = seq.image(0).unwrap_err().to_string();
    assert!(e.contains("0.png"), "{e}");
}

#[test]
fn source_records() {
    let exp = common::read_json("records_expected.json");
    let r = read_source_record(&data("records_p4.pkl"), Some("id_01_clip_2")).unwrap();
    let want = f32s(exp["id_01_clip_2"]["shapecode"]["hex"].as_str().unwrap());
    assert_eq!(
        r.shapecode,
        want.iter().map(|&x| f64::from(x)).collect::<Vec<_>>()
    );
    // A folder: optim.pkl.
    let r = read_source_record(&data("release_small"), Some("spk_b_x_3")).unwrap();
    assert!(r.transform_matrix.is_some());

    let e = read_source_record(&data("records_p4.pkl"), Some("nope"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("no entry `nope`") && e.contains("id_01_clip_0, id_01_clip_2, id_01_clip_10"),
        "{e}"
    );
    let e = read_source_record(&data("release_small/optim.pkl"), None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("--source-key") && e.contains("6 frames") && e.contains("spk_a_0, spk_a_1"),
        "{e}"
    );

    let dir = TempDir::new("source");
    let p = dir.path().join("src.json");
    std::fs::write(
        &p,
        serde_json::to_string(&record_json(4, false, None)).unwrap(),
    )
    .unwrap();
    let r = read_source_record(&p, None).unwrap();
    assert_eq!(r.shapecode[0], 0.04);
    std::fs::write(&p, r#"{"shapecode": [1], "expcode": [], "posecode": []}"#).unwrap();
    let e = read_source_record(&p, None).unwrap_err().to_string();
    assert!(
        e.contains("src.json") && e.contains("eyecode") && e.contains("is missing"),
        "{e}"
    );
    let e = read_source_record(&dir.path().join("absent.json"), None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("absent.json") && e.contains("cannot read"),
        "{e}"
    );
}
