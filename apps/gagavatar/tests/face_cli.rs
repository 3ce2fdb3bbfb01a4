//! `gagavatar face` end to end: JSON, overlay and matte for a photo with a face and one
//! without; bad inputs refused with one clear line and a non-zero exit; `bench face` runs.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const BIN: &str = env!("CARGO_BIN_EXE_gagavatar");

fn run(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .output()
        .expect("running the gagavatar binary")
}

fn golden(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../crates/face/tests/golden/images")
        .join(name)
        .display()
        .to_string()
}

fn dir() -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("cli_face");
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn face_json_overlay_and_matte() {
    let d = dir();
    let (json, overlay, matte) = (d.join("a.json"), d.join("a.png"), d.join("a_matte.png"));
    let o = run(&[
        "face",
        &golden("astronaut_384.png"),
        "--json",
        &json.display().to_string(),
        "-o",
        &overlay.display().to_string(),
        "--matte",
        &matte.display().to_string(),
    ]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{out}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(out.contains("face 0: score"), "{out}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(
        (v["width"].as_u64(), v["height"].as_u64()),
        (Some(384), Some(384))
    );
    let f = &v["faces"][0];
    assert_eq!(f["landmarks"].as_array().unwrap().len(), 478);
    assert_eq!(f["keypoints"].as_array().unwrap().len(), 6);
    let b: Vec<f64> = f["box"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect();
    // The face is in the upper middle of the picture.
    assert!(
        b[0] > 100.0 && b[2] < 240.0 && b[1] > 30.0 && b[3] < 160.0,
        "{b:?}"
    );
    let ov = image::open(&overlay).unwrap();
    assert_eq!((ov.width(), ov.height()), (384, 384));
    let m = image::open(&matte).unwrap().into_luma8();
    assert_eq!(m.dimensions(), (384, 384));
    // Person in the middle, sky-blue wall at the top-left corner.
    assert!(m.get_pixel(192, 300)[0] > 200 && m.get_pixel(5, 5)[0] < 50);
}

#[test]
fn no_face_is_not_an_error() {
    let json = dir().join("cat.json");
    let o = run(&[
        "face",
        &golden("chelsea_cat.png"),
        "--json",
        &json.display().to_string(),
    ]);
    assert!(o.status.success());
    assert!(String::from_utf8_lossy(&o.stdout).contains("no face found"));
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(v["faces"].as_array().unwrap().len(), 0);
}

#[test]
fn bad_inputs_fail_with_one_line() {
    let d = dir();
    let empty = d.join("empty.png");
    std::fs::write(&empty, b"").unwrap();
    let tiny = d.join("one.png");
    image::RgbImage::new(1, 1).save(&tiny).unwrap();
    let trunc = d.join("trunc.png");
    let bytes = std::fs::read(golden("astronaut_384.png")).unwrap();
    std::fs::write(&trunc, &bytes[..bytes.len() / 2]).unwrap();
    let text = d.join("text.jpg");
    std::fs::write(&text, b"not an image at all").unwrap();
    // A PNG header claiming 20000x20000 pixels.
    let huge = d.join("huge.png");
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = b"IHDR".to_vec();
    ihdr.extend(20000u32.to_be_bytes());
    ihdr.extend(20000u32.to_be_bytes());
    ihdr.extend([8, 2, 0, 0, 0]);
    png.extend(13u32.to_be_bytes());
    png.extend(&ihdr);
    png.extend(crc32(&ihdr).to_be_bytes());
    std::fs::write(&huge, &png).unwrap();
    for (p, needle) in [
        (&empty, "empty"),
        (&tiny, "1x1"),
        (&trunc, "truncated"),
        (&text, "not an image"),
        (&huge, "too large"),
        (&d.join("missing.png"), "cannot read"),
    ] {
        let o = run(&["face", &p.display().to_string()]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{}: succeeded", p.display());
        assert!(err.contains(needle), "{}: {err}", p.display());
        assert_eq!(err.trim().lines().count(), 1, "{}: {err}", p.display());
        assert!(!err.contains("panicked"), "{err}");
    }
}

#[test]
fn bench_face_runs() {
    let o = run(&[
        "bench",
        "face",
        &golden("astronaut_flip.png"),
        &golden("astronaut_384.png"),
        "--runs",
        "2",
        "--threads",
        "1",
    ]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{out}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(
        out.contains("tracking frame") && out.contains("matte 256x256"),
        "{out}"
    );
}

fn crc32(data: &[u8]) -> u32 {
    let mut c = 0xffff_ffffu32;
    for &b in data {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xedb8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}
