//! The tracked folder: written in the release layout, read back by the data crate (the
//! project's release-format reader, whose own tests check it against Python), all-or-nothing.

mod common;

use common::*;
use gagavatar_data::records::read_records;
use gagavatar_data::{DriverSequence, LmdbReader};
use gagavatar_track::crop::crop_image;
use gagavatar_track::output::{
    read_track_json, sanitize_name, video_track_json, write_photo, write_video, IMAGES_DIR,
    OPTIM_FILE, SMOOTHED_FILE, TRACK_JSON,
};
use gagavatar_track::pipeline::{track_photo, track_video, TrackOptions};
use gagavatar_track::{Observation, TrackError, TrackedPhoto, TrackedVideo};
use image::RgbImage;

fn photo() -> TrackedPhoto {
    let rig = rig();
    let (shape, st) = truth(&rig, 1, 1);
    let pts = exact_points(&rig, &shape, &st).map(|p| [p[0] * 1.2 + 40.0, p[1] * 1.2 + 10.0]);
    track_photo(
        &observation(&pts, 700, 640),
        &rig,
        &TrackOptions::default(),
        "p",
    )
    .unwrap()
}

fn video(n: usize) -> TrackedVideo {
    let rig = rig();
    let obs: Vec<Observation> = (0..n)
        .map(|i| {
            if i == 2 {
                return Observation::no_face(700, 640).unwrap();
            }
            let (shape, st) = truth(&rig, 1, i + 1);
            let pts = exact_points(&rig, &shape, &st).map(|p| [p[0] * 1.2 + 40.0, p[1] * 1.2]);
            observation(&pts, 700, 640)
        })
        .collect();
    track_video(obs, &rig, &TrackOptions::default(), "v", |_, _| {}).unwrap()
}

fn frame_image() -> RgbImage {
    RgbImage::from_fn(700, 640, |x, y| {
        image::Rgb([(x % 256) as u8, (y % 256) as u8, 128])
    })
}

fn same_record(a: &gagavatar_flame::TrackedFrame, b: &gagavatar_flame::TrackedFrame) {
    let pad = |v: &[f64], n: usize| {
        let mut v = v.to_vec();
        v.resize(n, 0.0);
        v
    };
    let close = |x: &[f64], y: &[f64], what: &str| {
        assert_eq!(x.len(), y.len(), "{what}");
        for (i, (p, q)) in x.iter().zip(y).enumerate() {
            // float32 storage.
            assert!(
                (p - q).abs() <= 1e-6 * (1.0 + p.abs()),
                "{what}[{i}]: {p} vs {q}"
            );
        }
    };
    close(&pad(&a.shapecode, 300), &b.shapecode, "shapecode");
    close(&pad(&a.expcode, 100), &b.expcode, "expcode");
    close(&a.posecode, &b.posecode, "posecode");
    close(&a.eyecode, &b.eyecode, "eyecode");
    close(&a.bbox.unwrap(), &b.bbox.unwrap(), "bbox");
    let f = |m: [[f64; 4]; 3]| m.iter().flatten().copied().collect::<Vec<_>>();
    close(
        &f(a.transform_matrix.unwrap()),
        &f(b.transform_matrix.unwrap()),
        "transform",
    );
}

/// Where the folders these tests wrote and checked are copied for
/// `tools/reference/track_loader_check.py` (`photo/` and `video/`), when set.
const SAMPLE_DIR_ENV: &str = "GAGAVATAR_TRACK_SAMPLE_DIR";

/// Copies the checked folder `dir` to `$GAGAVATAR_TRACK_SAMPLE_DIR/<name>` when that is set.
fn keep_sample(dir: &std::path::Path, name: &str) {
    fn copy(from: &std::path::Path, to: &std::path::Path) {
        std::fs::create_dir_all(to).unwrap();
        for e in std::fs::read_dir(from).unwrap() {
            let e = e.unwrap();
            let target = to.join(e.file_name());
            if e.file_type().unwrap().is_dir() {
                copy(&e.path(), &target);
            } else {
                std::fs::copy(e.path(), target).unwrap();
            }
        }
    }
    if let Some(root) = std::env::var_os(SAMPLE_DIR_ENV) {
        let to = std::path::Path::new(&root).join(name);
        let _ = std::fs::remove_dir_all(&to);
        copy(dir, &to);
    }
}

#[test]
fn photo_folder_reads_back() {
    let t = TempDir::new("photo");
    let dir = t.0.join("out");
    let p = photo();
    let crop = crop_image(&frame_image(), &p.frame.window).unwrap();
    write_photo(&dir, "my photo_1", &p, &crop).unwrap();
    let key = "my-photo-1_0";
    let recs = read_records(&dir.join(OPTIM_FILE)).unwrap();
    assert_eq!(recs.keys().collect::<Vec<_>>(), vec![key]);
    same_record(&p.frame.record, &recs[key]);
    let lmdb = LmdbReader::open(&dir.join(IMAGES_DIR)).unwrap();
    let jpeg = lmdb.get(key.as_bytes()).unwrap().unwrap();
    let img = image::load_from_memory(&jpeg).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (512, 512));
    let tj = read_track_json(&dir.join(TRACK_JSON)).unwrap();
    assert_eq!((tj.kind.as_str(), tj.frames.len()), ("photo", 1));
    assert_eq!(tj.frames[0].window, p.frame.window.as_array());
    assert_eq!(tj.frames[0].landmarks_fitted.len(), 70);
    same_record(&p.frame.record, &tj.frames[0].record.to_record());
    assert!(!dir.join(SMOOTHED_FILE).exists());
    // The project's own driver reader opens it as a tracked folder.
    let d = DriverSequence::open(&dir).unwrap();
    assert_eq!(d.frames.len(), 1);
    assert!(d.has_images());
    // A photo has no rate: the release's default.
    assert_eq!((tj.fps, d.fps), (None, gagavatar_data::driver::DEFAULT_FPS));
    keep_sample(&dir, "photo");
}

#[test]
fn video_folder_reads_back_and_is_all_or_nothing() {
    let t = TempDir::new("video");
    let dir = t.0.join("clip");
    let mut v = video(5);
    // An NTSC clip: the exact rate survives the folder (not the release's 25 fps default).
    let ntsc = 30000.0 / 1001.0;
    v.fps = Some(ntsc);
    let img = frame_image();
    let crops = v.frames.iter().map(|f| crop_image(&img, &f.window));
    write_video(&dir, "clip", &v, crops).unwrap();
    let optim = read_records(&dir.join(OPTIM_FILE)).unwrap();
    let smoothed = read_records(&dir.join(SMOOTHED_FILE)).unwrap();
    assert_eq!(optim.len(), 5);
    assert_eq!(smoothed.len(), 5);
    for i in 0..5 {
        let k = format!("clip_{i}");
        same_record(&v.raw_records[i], &optim[&k]);
        same_record(&v.frames[i].record, &smoothed[&k]);
    }
    let lmdb = LmdbReader::open(&dir.join(IMAGES_DIR)).unwrap();
    assert_eq!(lmdb.len(), 5);
    let tj = read_track_json(&dir.join(TRACK_JSON)).unwrap();
    assert_eq!(tj.frames.len(), 5);
    // The frame-by-frame writer writes what the whole `TrackJson` value writes, byte for byte.
    let text = std::fs::read_to_string(dir.join(TRACK_JSON)).unwrap();
    let whole = serde_json::to_string(&video_track_json("clip", &v).unwrap()).unwrap();
    assert!(text == whole, "track.json differs from the TrackJson value");
    assert!(!tj.frames[2].face_found && tj.frames[2].landmarks_detected.is_none());
    let d = DriverSequence::open(&dir).unwrap();
    assert_eq!(d.frames.len(), 5);
    assert_eq!(d.fps, ntsc);
    assert_eq!(tj.fps, Some(ntsc));

    // Rewriting over our own folder is allowed; a failing crop source leaves the old one.
    let bad = (0..5).map(|i| {
        if i == 3 {
            Err(TrackError::Input {
                what: "decoder",
                reason: "broken frame".into(),
            })
        } else {
            Ok(RgbImage::new(512, 512))
        }
    });
    let e = write_video(&dir, "clip", &v, bad).unwrap_err();
    assert!(e.to_string().contains("broken frame"), "{e}");
    assert_eq!(LmdbReader::open(&dir.join(IMAGES_DIR)).unwrap().len(), 5);
    // Too few crops, or a wrong size: refused, nothing written.
    let fresh = t.0.join("fresh");
    let few = (0..4).map(|_| Ok(RgbImage::new(512, 512)));
    assert!(write_video(&fresh, "clip", &v, few).is_err());
    let small = (0..5).map(|_| Ok(RgbImage::new(256, 256)));
    assert!(write_video(&fresh, "clip", &v, small).is_err());
    assert!(!fresh.exists());
    // Only leftovers are the finished folders.
    let names: Vec<String> = std::fs::read_dir(&t.0)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, vec!["clip".to_string()], "{names:?}");
    keep_sample(&dir, "video");
}

#[test]
fn a_folder_with_other_files_is_not_replaced() {
    let t = TempDir::new("refuse");
    std::fs::write(t.0.join("notes.txt"), b"mine").unwrap();
    let p = photo();
    let e = write_photo(&t.0, "p", &p, &RgbImage::new(512, 512)).unwrap_err();
    assert!(e.to_string().contains("notes.txt"), "{e}");
    assert_eq!(std::fs::read(t.0.join("notes.txt")).unwrap(), b"mine");
}

#[test]
fn names_are_safe_for_the_release_loaders() {
    assert_eq!(sanitize_name("obama"), "obama");
    assert_eq!(sanitize_name("my_video 2.mp4"), "my-video-2-mp4");
    assert_eq!(sanitize_name("été"), "-t-");
    assert_eq!(sanitize_name(""), "track");
}
