//! Tracks a folder of video frames, split into consecutive clips, into one release-layout
//! dataset for `gagavatar eval` (each clip a "video": frames `clipK_<i>`, all in the test
//! split). Landmarks: `crates/face` in video mode; fits: `crates/track`'s `track_video` with
//! the built-in synthetic FLAME asset (or `--flame F`); crops: the release's 512 rule.
//!
//! ```text
//! ffmpeg -i obama.mp4 /tmp/frames/%06d.png
//! cargo run --release -p gagavatar-metrics --example track_clips -- /tmp/frames 4 /tmp/obama_eval [FLAME.pt]
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use gagavatar_data::dataset::{write_release_dataset, DatasetSplits};
use gagavatar_face::face_mesh::FaceTracker;
use gagavatar_flame::{synthesize, FlameAsset, LoadOptions, TrackedFrame};
use gagavatar_track::crop::crop_image;
use gagavatar_track::observation::{FaceLandmarks, Observation};
use gagavatar_track::pipeline::{track_video, TrackOptions};
use gagavatar_track::rig::LandmarkRig;

type AnyResult<T> = Result<T, Box<dyn std::error::Error>>;

fn main() -> AnyResult<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 3 {
        return Err("usage: track_clips FRAMES_DIR CLIPS OUT_DIR [FLAME]".into());
    }
    let frames_dir = PathBuf::from(&args[0]);
    let clips: usize = args[1].parse()?;
    let out = PathBuf::from(&args[2]);
    let asset = match args.get(3) {
        Some(p) => FlameAsset::load(Path::new(p), &LoadOptions::default())?,
        None => synthesize(0),
    };
    let rig = LandmarkRig::for_tracking(&asset)?;
    let mut files: Vec<PathBuf> = std::fs::read_dir(&frames_dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "png" || x == "jpg"))
        .collect();
    files.sort();
    if clips == 0 || files.len() < 2 * clips {
        return Err(format!("{} frames cannot make {clips} clips", files.len()).into());
    }
    let per = files.len() / clips;
    let opts = TrackOptions::default();
    let mut records: BTreeMap<String, TrackedFrame> = BTreeMap::new();
    let mut images: Vec<(String, Vec<u8>)> = Vec::new();
    for k in 0..clips {
        let part = &files[k * per..(k + 1) * per];
        let frames: Vec<image::RgbImage> = part
            .iter()
            .map(|p| Ok(image::open(p)?.to_rgb8()))
            .collect::<AnyResult<_>>()?;
        let mut tracker = FaceTracker::new()?;
        let mut obs = Vec::with_capacity(frames.len());
        for f in &frames {
            let (w, h) = f.dimensions();
            let lm = match tracker.process(f)? {
                Some(face) => {
                    let pts: Vec<[f64; 2]> = face
                        .landmarks_pixels(w, h)
                        .iter()
                        .map(|p| [p[0] as f64, p[1] as f64])
                        .collect();
                    Some(FaceLandmarks::new(pts)?)
                }
                None => None,
            };
            obs.push(Observation::new(w, h, lm)?);
        }
        let name = format!("clip{k}");
        let video = track_video(obs, &rig, &opts, &name, |_, _| {})?;
        let rms: Vec<f64> = video.frames.iter().filter_map(|f| f.fit_rms_px).collect();
        eprintln!(
            "{name}: {} frames, {} with a face, mean fit RMS {:.2} px",
            frames.len(),
            rms.len(),
            rms.iter().sum::<f64>() / rms.len().max(1) as f64
        );
        for (i, (f, t)) in frames.iter().zip(&video.frames).enumerate() {
            let key = format!("{name}_{i}");
            let crop = crop_image(f, &t.window)?;
            images.push((key.clone(), gagavatar_data::encode_png(&crop)?));
            records.insert(key, video.raw_records[i].clone());
        }
    }
    let names: Vec<String> = images.iter().map(|(k, _)| k.clone()).collect();
    let splits = DatasetSplits {
        train: Vec::new(),
        val: Vec::new(),
        test: names,
    };
    write_release_dataset(&out, &records, images, &splits)?;
    eprintln!("wrote {}", out.display());
    Ok(())
}
