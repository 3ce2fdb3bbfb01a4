//! Runs every face pipeline over a folder of frames (sorted by name) and writes the results
//! for `tools/reference/face_reference.py parity`, which runs MediaPipe on the same frames and
//! compares:
//!
//!     cargo run --release -p gagavatar-face --example parity_frames -- FRAMES OUT_DIR
//!
//! `OUT_DIR/rust.json`: per frame, short- and full-range detections, the static FaceMesh face
//! (up to 4) and the tracking-mode face (frames in order as one video), all normalised as
//! MediaPipe reports them; `OUT_DIR/mattes/<frame>.png`: the matte, 16-bit grey.

use std::path::PathBuf;

use gagavatar_face::{
    Detection, DetectorModel, FaceDetector, FaceMesh, FaceTracker, SelfieSegmenter,
};
use serde_json::{json, Value};

fn det_json(d: &Detection) -> Value {
    json!({"score": d.score, "box": [d.xmin, d.ymin, d.width, d.height], "keypoints": d.keypoints})
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() != 3 {
        return Err("usage: parity_frames FRAMES OUT_DIR".into());
    }
    let out = PathBuf::from(&args[2]);
    std::fs::create_dir_all(out.join("mattes"))?;
    let mut files: Vec<PathBuf> = std::fs::read_dir(&args[1])?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    files.sort();
    let mesh = FaceMesh::new()?;
    let full = FaceDetector::new(DetectorModel::FullRange)?;
    let seg = SelfieSegmenter::new()?;
    let mut tracker = FaceTracker::new()?;
    let mut frames = Vec::new();
    for f in &files {
        let img = image::open(f)?.into_rgb8();
        let name = f
            .file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned();
        let short = mesh.detector.detect(&img)?;
        let far = full.detect(&img)?;
        let faces = mesh.process(&img, 4)?;
        let was = tracker.is_tracking();
        let tracked = tracker.process(&img)?;
        let m = seg.matte(&img)?;
        let grey =
            image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(m.width, m.height, |x, y| {
                image::Luma([(m.at(x, y).clamp(0.0, 1.0) * 65535.0).round() as u16])
            });
        grey.save(out.join("mattes").join(format!("{name}.png")))?;
        frames.push(json!({
            "name": name,
            "short_range": short.iter().map(det_json).collect::<Vec<_>>(),
            "full_range": far.iter().map(det_json).collect::<Vec<_>>(),
            "mesh": faces.iter().map(|f| &f.landmarks).collect::<Vec<_>>(),
            "tracked": tracked.as_ref().map(|f| &f.landmarks),
            "tracking": was,
        }));
    }
    std::fs::write(
        out.join("rust.json"),
        serde_json::to_string(&json!({"frames": frames}))?,
    )?;
    println!("{} frames -> {}", files.len(), out.display());
    Ok(())
}
