//! Shared helpers of the golden tests: the files written by `tools/reference/face_reference.py`.

#![allow(dead_code)]

use std::path::PathBuf;

use gagavatar_face::warp::RotatedRect;
use image::RgbImage;
use serde_json::Value;

pub fn golden_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden")
}

pub fn json(name: &str) -> Value {
    let p = golden_dir().join(name);
    let s = std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    serde_json::from_str(&s).unwrap()
}

pub fn png(rel: &str) -> RgbImage {
    let p = golden_dir().join(rel);
    image::open(&p)
        .unwrap_or_else(|e| panic!("{}: {e}", p.display()))
        .into_rgb8()
}

pub fn picture(name: &str) -> RgbImage {
    png(&format!("images/{name}.png"))
}

pub fn floats(v: &Value) -> Vec<f32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap() as f32)
        .collect()
}

pub fn f(v: &Value) -> f32 {
    v.as_f64().unwrap() as f32
}

/// A MediaPipe normalised rect as pixels of a `w x h` image (`GetRoi`, in f32).
pub fn roi_pixels(r: &Value, w: u32, h: u32) -> RotatedRect {
    RotatedRect {
        cx: f(&r["cx"]) * w as f32,
        cy: f(&r["cy"]) * h as f32,
        w: f(&r["w"]) * w as f32,
        h: f(&r["h"]) * h as f32,
        rotation: f(&r["rotation"]),
    }
}

/// Worst absolute difference and where.
pub fn worst(a: &[f32], b: &[f32]) -> (usize, f32) {
    assert_eq!(a.len(), b.len(), "lengths");
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .enumerate()
        .fold(
            (0, 0.0),
            |m, (i, d)| if d > m.1 || d.is_nan() { (i, d) } else { m },
        )
}
