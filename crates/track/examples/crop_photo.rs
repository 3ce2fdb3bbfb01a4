//! The release-rule crop of a real photo with the calibrated head box, so the framing
//! statistics of that crop can be measured again (`tools/reference/framing_measure.py`).
//!
//!     cargo run -p gagavatar-track --example crop_photo -- FACE.json
//!
//! `FACE.json` is `{"image": path, "landmarks": [[x, y]; 478]}` (MediaPipe's points in pixels);
//! the crop is written to `<image>.crop.png` and its window printed.

use gagavatar_track::crop::{crop_image, CropWindow, FramingCalibration};
use gagavatar_track::observation::FaceLandmarks;

type Error = Box<dyn std::error::Error>;

fn main() -> Result<(), Error> {
    let Some(path) = std::env::args().nth(1) else {
        return Err("usage: crop_photo FACE.json".into());
    };
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path)?)?;
    let image_path = v["image"]
        .as_str()
        .ok_or_else(|| format!("{path}: no \"image\" string"))?;
    let pts: Vec<[f64; 2]> = serde_json::from_value(v["landmarks"].clone())?;
    let lm = FaceLandmarks::new(pts)?;
    let img = image::open(image_path)?.to_rgb8();
    let b = FramingCalibration::default().head_box(&lm)?;
    let w = CropWindow::from_head_box(&b)?;
    let out = format!("{image_path}.crop.png");
    crop_image(&img, &w)?.save(&out)?;
    println!("window {:?}; wrote {out}", w.as_array());
    Ok(())
}
