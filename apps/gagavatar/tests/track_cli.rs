//! `gagavatar track` and inline tracking, end to end on the shipped public-domain photo
//! (`assets/demo/astronaut.jpg`): the release layout with its keys and float32 dtypes, the
//! overlay, a photo without a face (one error line, non-zero exit, nothing written), and
//! `reenact` / `export-ply` from a raw photo and a raw video, tracked once and then found in the
//! cache. Seeded `tiny` weights and the built-in synthetic FLAME keep it to seconds.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use gagavatar_formats::numpy::DType;
use gagavatar_formats::pickle::{read_pickle, DictKey, PyValue};

fn key_str(k: &DictKey) -> String {
    match k {
        DictKey::Str(s) => s.clone(),
        DictKey::Int(i) => i.to_string(),
    }
}

const BIN: &str = env!("CARGO_BIN_EXE_gagavatar");

fn astronaut() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo/astronaut.jpg")
}

/// A fresh folder per test, with its own tracking cache.
struct Scratch(PathBuf);

impl Scratch {
    fn new(tag: &str) -> Self {
        let d = std::env::temp_dir().join(format!("gagavatar_track_{tag}_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        Scratch(d)
    }
    fn p(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }
    fn s(&self, name: &str) -> String {
        self.p(name).display().to_string()
    }
    fn run(&self, args: &[&str]) -> Output {
        Command::new(BIN)
            .args(args)
            .env("GAGAVATAR_CACHE", self.p("cache"))
            .output()
            .expect("running the gagavatar binary")
    }
    fn ok(&self, args: &[&str]) -> String {
        let out = self.run(args);
        let log = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(out.status.success(), "gagavatar {args:?} failed:\n{log}");
        log
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

const RECORD_SHAPES: [(&str, &[usize]); 6] = [
    ("bbox", &[4]),
    ("shapecode", &[300]),
    ("expcode", &[100]),
    ("posecode", &[6]),
    ("eyecode", &[6]),
    ("transform_matrix", &[3, 4]),
];

/// Every frame of a release pickle: its keys and the six float32 arrays of the release.
fn check_pickle(path: &Path, keys: &[String]) {
    let PyValue::Dict(frames) = read_pickle(path).unwrap() else {
        panic!("{} is not a dict", path.display());
    };
    let names: Vec<String> = frames.iter().map(|(k, _)| key_str(k)).collect();
    let mut sorted = names.clone();
    sorted.sort();
    let mut want = keys.to_vec();
    want.sort();
    assert_eq!(sorted, want, "{}", path.display());
    for (k, v) in &frames {
        let PyValue::Dict(fields) = v else {
            panic!("frame {k} of {} is not a dict", path.display());
        };
        assert_eq!(fields.len(), 6, "frame {k}: {} fields", fields.len());
        for (name, shape) in RECORD_SHAPES {
            let (_, val) = fields
                .iter()
                .find(|(f, _)| key_str(f) == name)
                .unwrap_or_else(|| panic!("frame {k} lacks {name}"));
            let PyValue::Array(a) = val else {
                panic!("frame {k}: {name} is not an array");
            };
            assert_eq!(a.dtype(), DType::F32, "frame {k}: {name}");
            assert_eq!(a.shape, shape, "frame {k}: {name}");
        }
    }
}

fn lmdb_keys(dir: &Path) -> Vec<String> {
    let db = gagavatar_data::LmdbReader::open(&dir.join("img_lmdb")).unwrap();
    let mut keys: Vec<String> = db
        .keys()
        .unwrap()
        .into_iter()
        .map(|k| String::from_utf8(k).unwrap())
        .collect();
    keys.sort();
    for k in &keys {
        let bytes = db.get(k.as_bytes()).unwrap().unwrap();
        let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::Jpeg).unwrap();
        assert_eq!((img.width(), img.height()), (512, 512), "crop {k}");
    }
    keys
}

#[test]
fn track_a_photo_writes_the_release_layout_and_an_overlay() {
    let s = Scratch::new("photo");
    let out = s.s("astro");
    let overlay = s.s("astro_fit.png");
    let photo = astronaut().display().to_string();
    s.ok(&["track", &photo, "-o", &out, "--overlay", &overlay]);

    let dir = s.p("astro");
    let mut entries: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    entries.sort();
    assert_eq!(entries, ["img_lmdb", "optim.pkl", "track.json"]);
    let keys = vec!["astronaut_0".to_string()];
    assert_eq!(lmdb_keys(&dir), keys);
    check_pickle(&dir.join("optim.pkl"), &keys);

    let t: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("track.json")).unwrap()).unwrap();
    assert_eq!(t["kind"], "photo");
    let f = &t["frames"][0];
    assert_eq!(f["key"], "astronaut_0");
    assert_eq!(f["face_found"], true);
    assert_eq!(f["image_size"], serde_json::json!([512, 512]));
    let detected = f["landmarks_detected"].as_array().unwrap();
    let fitted = f["landmarks_fitted"].as_array().unwrap();
    assert_eq!((detected.len(), fitted.len()), (70, 70));
    // The window holds the face: every detected landmark lies inside it.
    let w: Vec<f64> = f["window"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    for (k, p) in detected.iter().enumerate() {
        let (x, y) = (p[0].as_f64().unwrap(), p[1].as_f64().unwrap());
        assert!(
            x > w[0] && x < w[2] && y > w[1] && y < w[3],
            "landmark {k} ({x}, {y}) outside the window {w:?}"
        );
    }

    let pic = image::open(&overlay).unwrap();
    assert_eq!((pic.width(), pic.height()), (512, 512));
    let orig = image::open(astronaut()).unwrap().to_rgb8();
    let changed = pic
        .to_rgb8()
        .pixels()
        .zip(orig.pixels())
        .filter(|(a, b)| a != b)
        .count();
    assert!(changed > 2000, "the overlay drew on only {changed} pixels");

    // Tracking again replaces the folder (it holds only what tracking writes).
    s.ok(&["track", &photo, "-o", &out]);
    assert!(dir.join("track.json").is_file());
}

/// A photo with no face: a smooth gradient.
fn no_face_png(path: &Path) {
    image::RgbImage::from_fn(160, 120, |x, y| image::Rgb([x as u8, y as u8, 128]))
        .save(path)
        .unwrap();
}

fn assert_no_face_error(out: &Output, photo: &Path) {
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "succeeded:\n{log}");
    let lines: Vec<&str> = log.lines().collect();
    assert_eq!(
        lines,
        [format!("error: no face found in {}", photo.display())],
        "expected exactly one error line"
    );
}

#[test]
fn a_photo_without_a_face_fails_and_writes_nothing() {
    let s = Scratch::new("noface");
    let photo = s.p("wall.png");
    no_face_png(&photo);
    let out = s.run(&[
        "track",
        &photo.display().to_string(),
        "-o",
        &s.s("out"),
        "--overlay",
        &s.s("fit.png"),
    ]);
    assert_no_face_error(&out, &photo);
    assert!(!s.p("out").exists(), "the output folder was created");
    assert!(!s.p("fit.png").exists(), "the overlay was written");

    // The same photo as a reenact source.
    let ckpt = s.s("tiny.safetensors");
    s.ok(&[
        "init-weights",
        "--preset",
        "tiny",
        "--seed",
        "3",
        "-o",
        &ckpt,
    ]);
    let out = s.run(&[
        "reenact",
        "--ckpt",
        &ckpt,
        "--flame",
        "synthetic",
        "--source",
        &photo.display().to_string(),
        "--driver",
        &astronaut().display().to_string(),
        "-o",
        &s.s("out.mp4"),
    ]);
    assert_no_face_error(&out, &photo);
    assert!(!s.p("out.mp4").exists());
    let leftovers: Vec<_> = std::fs::read_dir(&s.0)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n != "wall.png" && n != "tiny.safetensors")
        .collect();
    assert!(leftovers.is_empty(), "left behind: {leftovers:?}");
}

/// A 6-frame 256x256 driving video: the astronaut's face through a window drifting sideways.
fn driving_video(path: &Path) {
    let photo = image::open(astronaut()).unwrap().to_rgb8();
    let mut w = gagavatar_video::VideoWriter::create(
        path,
        256,
        256,
        gagavatar_video::VideoOptions {
            fps: 10.0,
            watermark: false,
        },
    )
    .unwrap();
    for i in 0..6u32 {
        let view = image::imageops::crop_imm(&photo, 90 + 4 * i, 0, 280, 280).to_image();
        let frame = image::imageops::resize(&view, 256, 256, image::imageops::FilterType::Triangle);
        w.push_rgb(frame.as_raw()).unwrap();
    }
    w.finish().unwrap();
}

#[test]
fn reenact_and_export_from_a_raw_photo_and_video_use_the_cache_the_second_time() {
    let s = Scratch::new("inline");
    let ckpt = s.s("tiny.safetensors");
    s.ok(&[
        "init-weights",
        "--preset",
        "tiny",
        "--seed",
        "4",
        "-o",
        &ckpt,
    ]);
    let video = s.p("drive.mp4");
    driving_video(&video);
    let photo = astronaut().display().to_string();
    let out = s.s("out.mp4");
    let args = [
        "reenact",
        "--ckpt",
        &ckpt,
        "--flame",
        "synthetic",
        "--source",
        &photo,
        "--driver",
        &video.display().to_string(),
        "--side-by-side",
        "-o",
        &out,
    ];
    let first = s.ok(&args);
    assert!(
        first.contains("source: tracked") && first.contains("driver: tracked"),
        "first run:\n{first}"
    );
    let info = gagavatar_video::mp4::read_mp4_info(Path::new(&out)).unwrap();
    // The tiny preset renders 64x64; side by side doubles the width.
    assert_eq!((info.frames, info.width, info.height), (6, 128, 64));

    let second = s.ok(&args);
    assert!(
        second.contains("source: using the cached tracking")
            && second.contains("driver: using the cached tracking"),
        "second run:\n{second}"
    );
    assert!(
        !second.contains("tracked"),
        "second run tracked again:\n{second}"
    );

    // The cache holds two tracked folders in the release layout, with their metadata.
    let cache = s.p("cache").join("track");
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(&cache)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_dir())
        .collect();
    dirs.sort();
    assert_eq!(dirs.len(), 2, "{dirs:?}");
    for d in &dirs {
        assert!(
            d.with_extension("json").is_file(),
            "{} has no metadata",
            d.display()
        );
    }
    let video_dir = dirs
        .iter()
        .find(|d| d.join("smoothed.pkl").is_file())
        .expect("the driver's folder");
    let keys: Vec<String> = (0..6).map(|i| format!("drive_{i}")).collect();
    let mut sorted_keys = keys.clone();
    sorted_keys.sort();
    assert_eq!(lmdb_keys(video_dir), sorted_keys);
    check_pickle(&video_dir.join("optim.pkl"), &keys);
    check_pickle(&video_dir.join("smoothed.pkl"), &keys);

    // export-ply takes the raw photo too, from the cache.
    let ply = s.s("astro.ply");
    let log = s.ok(&[
        "export-ply",
        "--ckpt",
        &ckpt,
        "--flame",
        "synthetic",
        "--source",
        &photo,
        "-o",
        &ply,
    ]);
    assert!(log.contains("source: using the cached tracking"), "{log}");
    assert!(Path::new(&ply).is_file());

    // A tracked folder is a source as well.
    let tracked = s.s("tracked_astro");
    s.ok(&["track", &photo, "-o", &tracked]);
    let ply2 = s.s("astro2.ply");
    s.ok(&[
        "export-ply",
        "--ckpt",
        &ckpt,
        "--flame",
        "synthetic",
        "--source",
        &tracked,
        "-o",
        &ply2,
    ]);
    assert!(Path::new(&ply2).is_file());
}
