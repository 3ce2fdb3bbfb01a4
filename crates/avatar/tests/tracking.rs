//! Tracking in-process through the library, on the real public-domain photo the repository ships
//! (`assets/demo/astronaut.jpg`) and a short clip made from it: what a call returns is what its
//! folder holds, the cache gives back the same numbers and pixels as the run that filled it, a
//! video streams through the stages the monitor reports, and cancellation or a photo without a
//! face leaves nothing behind.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use gagavatar_avatar::cache::{read_tracked, read_tracked_frame};
use gagavatar_avatar::{
    AvatarError, CancelToken, Drive, Engine, EngineConfig, InputKind, Monitor, NoMonitor, TrackTo,
};
use gagavatar_flame::TrackedFrame;

fn demo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo")
}

fn engine() -> Engine {
    Engine::open(&EngineConfig::new(demo().join("weights.safetensors"))).unwrap()
}

/// A fresh folder under the target directory, removed when dropped.
struct Scratch(PathBuf);
impl Scratch {
    fn new(tag: &str) -> Self {
        let p = std::env::temp_dir().join(format!(
            "gagavatar_avatar_tracking_{tag}_{}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap();
        Scratch(p)
    }
    fn entries(&self) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(&self.0)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }
}
impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Six 256x256 frames, as a folder of PNGs (a video input that needs no decoder): the
/// astronaut's face through a window drifting sideways.
fn clip(dir: &Path) -> PathBuf {
    let photo = image::open(demo().join("astronaut.jpg")).unwrap().to_rgb8();
    let out = dir.join("clip");
    std::fs::create_dir_all(&out).unwrap();
    for i in 0..6u32 {
        let view = image::imageops::crop_imm(&photo, 90 + 4 * i, 0, 280, 280).to_image();
        let frame = image::imageops::resize(&view, 256, 256, image::imageops::FilterType::Triangle);
        frame.save(out.join(format!("f{i:03}.png"))).unwrap();
    }
    out
}

fn assert_records_equal(a: &[TrackedFrame], b: &[TrackedFrame], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: frame count");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert_eq!(x, y, "{what}: frame {i} differs");
    }
}

#[test]
fn a_photo_tracked_in_memory_and_into_a_folder_gives_the_same_record_and_crop() {
    let s = Scratch::new("photo");
    let e = engine();
    let photo = image::open(demo().join("astronaut.jpg")).unwrap().to_rgb8();
    let mem = e.track_photo(&photo, "astronaut").unwrap();
    assert_eq!(mem.crop.dimensions(), (512, 512));
    let rms = mem.photo.frame.fit_rms_px.unwrap();
    assert!(rms < 10.0, "landmark RMS {rms} px at 512");

    let dir = s.0.join("astro");
    let t = e
        .track(
            &demo().join("astronaut.jpg"),
            &TrackTo::Folder(dir.clone()),
            &NoMonitor,
        )
        .unwrap();
    assert_eq!(t.kind, InputKind::Photo);
    assert!(!t.cached);
    assert_eq!(t.names, ["astronaut_0"]);
    // The file is decoded by the same reader as the array above: one result.
    assert_eq!(t.crop.as_ref().unwrap(), &mem.crop);
    // What the call returned is what the folder holds, bit for bit.
    let (crop, record, _) = read_tracked_frame(&dir, None).unwrap();
    assert_eq!(&crop, t.crop.as_ref().unwrap());
    assert_records_equal(
        &t.records,
        std::slice::from_ref(&record),
        "returned vs optim.pkl",
    );
    // And it reconstructs and renders.
    let av = e.avatar(&crop, &record).unwrap();
    let codes = av.codes(&record, "the tracked record").unwrap();
    let frame = av
        .cpu_drive()
        .render(&codes, &av.source_camera().unwrap())
        .unwrap();
    assert_eq!(frame.len(), 64 * 64 * 3);
}

/// Counts what a run reports.
#[derive(Default)]
struct Log {
    stages: Mutex<Vec<(String, Option<u64>, u64)>>,
    finished: AtomicU64,
    cancel_after: Option<u64>,
    steps: AtomicU64,
}
impl Monitor for Log {
    fn stage(&self, name: &str, total: Option<u64>) {
        self.stages
            .lock()
            .unwrap()
            .push((name.to_string(), total, 0));
    }
    fn advance(&self, steps: u64) {
        self.steps.fetch_add(steps, Ordering::SeqCst);
        if let Some(last) = self.stages.lock().unwrap().last_mut() {
            last.2 += steps;
        }
    }
    fn finish(&self) {
        self.finished.fetch_add(1, Ordering::SeqCst);
    }
    fn cancelled(&self) -> bool {
        self.cancel_after
            .is_some_and(|k| self.steps.load(Ordering::SeqCst) >= k)
    }
}

#[test]
fn a_video_streams_through_its_stages_and_the_cache_gives_back_the_same_numbers() {
    let s = Scratch::new("video");
    let input = clip(&s.0);
    let cache = s.0.join("cache");
    // The only test in this binary that reads the variable.
    std::env::set_var("GAGAVATAR_CACHE", &cache);
    let e = engine();

    let log = Log::default();
    let first = e.track(&input, &TrackTo::Cache, &log).unwrap();
    assert_eq!(first.kind, InputKind::Video);
    assert!(!first.cached);
    assert_eq!(first.records.len(), 6);
    assert_eq!(
        first.names,
        (0..6).map(|i| format!("clip_{i}")).collect::<Vec<_>>()
    );
    assert!(first.crop.is_none());
    let summary = first.video.as_ref().unwrap();
    assert_eq!((summary.frames, summary.no_face), (6, 0));
    let stages = log.stages.lock().unwrap().clone();
    let names: Vec<&str> = stages.iter().map(|s| s.0.as_str()).collect();
    assert_eq!(
        names,
        ["landmarks", "fit | crop, matte, JPEG"],
        "{stages:?}"
    );
    // Every frame once through the landmarks, twice (fit, crop) through the second stage.
    assert_eq!(stages[0].2, 6, "{stages:?}");
    assert_eq!((stages[1].1, stages[1].2), (Some(12), 12), "{stages:?}");
    assert_eq!(log.finished.load(Ordering::SeqCst), 1);
    assert!(first.dir.starts_with(&cache));

    // The folder holds what was returned.
    let back = read_tracked(&first.dir, InputKind::Video).unwrap();
    assert_eq!(back.names, first.names);
    assert_records_equal(&back.records, &first.records, "returned vs smoothed.pkl");

    // The second call finds it: same folder, same records, nothing reported but the end.
    let log2 = Log::default();
    let second = e.track(&input, &TrackTo::Cache, &log2).unwrap();
    assert!(second.cached);
    assert_eq!(second.dir, first.dir);
    assert_eq!(second.fps, first.fps);
    assert_records_equal(&second.records, &first.records, "cached vs fresh");
    assert!(log2.stages.lock().unwrap().is_empty());

    // A photo from the cache reconstructs from the same pixels as the run that filled it.
    let astro = demo().join("astronaut.jpg");
    let p1 = e.track(&astro, &TrackTo::Cache, &NoMonitor).unwrap();
    let p2 = e.track(&astro, &TrackTo::Cache, &NoMonitor).unwrap();
    assert!(!p1.cached && p2.cached);
    assert_eq!(p1.crop, p2.crop);
    assert_records_equal(&p1.records, &p2.records, "cached photo vs fresh");
}

#[test]
fn cancelling_a_video_leaves_nothing_behind() {
    let s = Scratch::new("cancel");
    let input = clip(&s.0);
    let e = engine();
    for cancel_after in [0, 3, 8] {
        let out = s.0.join(format!("out_{cancel_after}"));
        let log = Log {
            cancel_after: Some(cancel_after),
            ..Log::default()
        };
        let err = e
            .track(&input, &TrackTo::Folder(out.clone()), &log)
            .unwrap_err();
        assert!(
            matches!(err, AvatarError::Cancelled),
            "after {cancel_after} steps: {err}"
        );
        assert_eq!(log.finished.load(Ordering::SeqCst), 1);
    }
    // Only the input: no output folder, no temporary sibling.
    assert_eq!(s.entries(), ["clip"]);

    // A token cancelled from elsewhere stops the call before any work.
    let token = CancelToken::new();
    token.cancel();
    let err = e
        .track(&input, &TrackTo::Folder(s.0.join("t")), &token)
        .unwrap_err();
    assert!(matches!(err, AvatarError::Cancelled), "{err}");
    assert_eq!(s.entries(), ["clip"]);
}

#[test]
fn a_photo_without_a_face_is_a_typed_error_and_writes_nothing() {
    let s = Scratch::new("noface");
    let e = engine();
    let wall = image::RgbImage::from_fn(200, 160, |x, y| {
        image::Rgb([(x % 256) as u8, (y % 256) as u8, 128])
    });
    let err = e.track_photo(&wall, "wall.png").unwrap_err();
    assert_eq!(err.to_string(), "no face found in wall.png");
    let path = s.0.join("wall.png");
    wall.save(&path).unwrap();
    let err = e
        .track(&path, &TrackTo::Folder(s.0.join("out")), &NoMonitor)
        .unwrap_err();
    assert!(
        err.to_string()
            .contains(&format!("no face found in {}", path.display())),
        "{err}"
    );
    assert_eq!(s.entries(), ["wall.png"]);
    // A source must be a photo.
    let err = e
        .track_as(&s.0, &TrackTo::Cache, "source", true, &NoMonitor)
        .unwrap_err();
    assert!(err.to_string().contains("is not a photo"), "{err}");
    let tiny = image::RgbImage::new(8, 8);
    let err = e.track_photo(&tiny, "tiny").unwrap_err();
    assert!(err.to_string().contains("at least 16"), "{err}");
}
