//! A `kill -9` while a tracked folder is being written leaves no partial folder: the folder is
//! built under a hidden temporary sibling and moved into place whole, so after SIGKILL the target
//! is either absent or the previous complete folder (only hidden temporaries may remain).
//!
//! The writer runs in a child process (this test binary re-run with [`CHILD_DIR`] set), fed
//! crops slowly as a real video decode would, and is killed once its temporary folder exists.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::*;
use gagavatar_data::records::read_records;
use gagavatar_data::LmdbReader;
use gagavatar_track::output::{write_video, IMAGES_DIR, OPTIM_FILE};
use gagavatar_track::pipeline::{track_video, TrackOptions};
use gagavatar_track::{Observation, TrackedVideo};
use image::RgbImage;

/// Set in the child: the folder to write.
const CHILD_DIR: &str = "GAGAVATAR_TRACK_KILL_DIR";
/// Set in the child: the frame count (the crop source sleeps per frame).
const CHILD_FRAMES: &str = "GAGAVATAR_TRACK_KILL_FRAMES";
/// How long the child's crop source takes per frame: long enough that the kill lands mid-write.
const CROP_DELAY: Duration = Duration::from_millis(150);
/// The child must reach its write within this (tracking a few synthetic frames takes < 1 s).
const START_TIMEOUT: Duration = Duration::from_secs(120);

fn video(n: usize) -> TrackedVideo {
    let rig = rig();
    let obs: Vec<Observation> = (0..n)
        .map(|i| {
            let (shape, st) = truth(&rig, 1, i + 1);
            let pts = exact_points(&rig, &shape, &st).map(|p| [p[0] * 1.2 + 40.0, p[1] * 1.2]);
            observation(&pts, 700, 640)
        })
        .collect();
    track_video(obs, &rig, &TrackOptions::default(), "v", |_, _| {}).unwrap()
}

/// The child's work: track, then write with a slow crop source (or a fast one for the first,
/// complete folder).
fn write_folder(dir: &Path, frames: usize, slow: bool) {
    let v = video(frames);
    let crops = (0..frames).map(move |i| {
        if slow {
            std::thread::sleep(CROP_DELAY);
        }
        Ok(RgbImage::from_pixel(
            512,
            512,
            image::Rgb([i as u8, 90, 200]),
        ))
    });
    write_video(dir, "clip", &v, crops).unwrap();
}

/// Hidden entries beside `dir` named after it (the writer's temporaries).
fn temporaries(dir: &Path) -> Vec<PathBuf> {
    let prefix = format!(".{}.", dir.file_name().unwrap().to_string_lossy());
    std::fs::read_dir(dir.parent().unwrap())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
        .map(|e| e.path())
        .collect()
}

/// Runs the writer in a child process and kills it (SIGKILL) a little after its temporary
/// folder has its first entry. Returns whether the kill landed before the child finished.
fn kill_mid_write(dir: &Path, frames: usize) -> bool {
    let exe = std::env::current_exe().unwrap();
    let mut child = Command::new(exe)
        .args([
            "--exact",
            "kill_9_while_writing_a_tracked_folder",
            "--nocapture",
        ])
        .env(CHILD_DIR, dir)
        .env(CHILD_FRAMES, frames.to_string())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(status.success(), "the writer failed: {status}");
            return false;
        }
        // The temporary folder has its (temporary) LMDB folder: crops are being written, the
        // pickles and JSON are not yet.
        if temporaries(dir)
            .iter()
            .any(|t| std::fs::read_dir(t).is_ok_and(|mut entries| entries.next().is_some()))
        {
            std::thread::sleep(2 * CROP_DELAY);
            break;
        }
        assert!(
            t0.elapsed() < START_TIMEOUT,
            "the writer did not start writing"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    // `Child::kill` is SIGKILL on Unix.
    child.kill().unwrap();
    child.wait().unwrap();
    true
}

#[test]
fn kill_9_while_writing_a_tracked_folder() {
    if let Some(dir) = std::env::var_os(CHILD_DIR) {
        let frames = std::env::var(CHILD_FRAMES).unwrap().parse().unwrap();
        write_folder(Path::new(&dir), frames, true);
        return;
    }
    let t = TempDir::new("kill");

    // A new folder: after the kill it does not exist.
    let fresh = t.0.join("fresh");
    assert!(
        kill_mid_write(&fresh, 12),
        "the write finished before the kill"
    );
    assert!(!fresh.exists(), "a partial folder exists after kill -9");
    let left = temporaries(&fresh);
    assert!(!left.is_empty(), "no temporary folder was seen");

    // The leftover temporary does not stop the next run.
    write_folder(&fresh, 3, false);
    assert_eq!(read_records(&fresh.join(OPTIM_FILE)).unwrap().len(), 3);

    // Rewriting a complete folder: after the kill the old folder is still there, whole.
    assert!(
        kill_mid_write(&fresh, 12),
        "the rewrite finished before the kill"
    );
    assert_eq!(read_records(&fresh.join(OPTIM_FILE)).unwrap().len(), 3);
    assert_eq!(
        LmdbReader::open(&fresh.join(IMAGES_DIR)).unwrap().len(),
        3,
        "the previous folder's images changed"
    );
    for p in temporaries(&fresh) {
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        assert!(name.starts_with('.'), "visible leftover {name}");
    }
}
