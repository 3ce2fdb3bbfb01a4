//! Helpers shared by the CLI tests: running the binary, a fixture folder with tiny seeded
//! weights and the synthetic FLAME asset, and killing a command in the middle of its output.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

pub const BIN: &str = env!("CARGO_BIN_EXE_gagavatar");
/// The tiny preset renders 64x64 frames.
pub const SIZE: u32 = 64;

pub fn run(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .output()
        .expect("running the gagavatar binary")
}

pub fn ok(args: &[&str]) -> Output {
    let out = run(args);
    assert!(
        out.status.success(),
        "gagavatar {args:?} failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Runs a command that must fail; returns its last stderr line (the error), checking it is one
/// clean `error:` line and not a panic.
pub fn fails(args: &[&str]) -> String {
    let log = fails_log(args);
    log.lines().last().unwrap_or("").to_string()
}

/// Like [`fails`], but returns all of stderr.
pub fn fails_log(args: &[&str]) -> String {
    let out = run(args);
    let log = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "{args:?} succeeded:\n{log}");
    assert!(!log.contains("panicked"), "{args:?} panicked:\n{log}");
    let last = log.lines().last().unwrap_or("");
    assert!(
        last.starts_with("error: "),
        "{args:?}: no error line:\n{log}"
    );
    log
}

/// A tracked-frame record as JSON, facing the camera.
pub fn record(exp: f64) -> serde_json::Value {
    record_turned(exp, 0.0)
}

/// A tracked-frame record as JSON with the head turned by `yaw` radians.
pub fn record_turned(exp: f64, yaw: f64) -> serde_json::Value {
    let (s, c) = yaw.sin_cos();
    serde_json::json!({
        "shapecode": [0.2, -0.1, 0.3],
        "expcode": (0..10).map(|k| exp * ((k as f64) + 1.0).sin()).collect::<Vec<_>>(),
        "posecode": [0, 0, 0, 0.05, 0, 0],
        "eyecode": [0, 0, 0, 0, 0, 0],
        "transform_matrix": [[-c, 0.0, s, 0.0], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, -c, 9.0]],
    })
}

/// A folder with `flame.safetensors` (the synthetic asset), `tiny.safetensors` (seeded tiny
/// weights), `src.png` (64x64) and `src.json`.
pub struct Fixture {
    pub dir: PathBuf,
}

impl Fixture {
    pub fn new(tag: &str) -> Self {
        Self::with_seed(tag, 4)
    }

    /// The same folder with the tiny weights drawn from `seed`.
    pub fn with_seed(tag: &str, seed: u64) -> Self {
        let dir = std::env::temp_dir().join(format!("gagavatar_{tag}_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let f = Fixture { dir };
        ok(&["flame", "synth", "-o", &f.s("flame.safetensors")]);
        ok(&[
            "init-weights",
            "--preset",
            "tiny",
            "--seed",
            &seed.to_string(),
            "-o",
            &f.s("tiny.safetensors"),
        ]);
        let img = image::RgbImage::from_fn(SIZE, SIZE, |x, y| {
            image::Rgb([(x * 4) as u8, (y * 4) as u8, ((x + y) * 2) as u8])
        });
        img.save(f.path("src.png")).unwrap();
        std::fs::write(f.path("src.json"), record(0.0).to_string()).unwrap();
        f
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }

    pub fn s(&self, name: &str) -> String {
        self.path(name).display().to_string()
    }

    /// `gagavatar <sub> --ckpt .. --flame .. --source .. --source-record ..` plus `extra`, with
    /// any of the four replaced through `with`.
    pub fn avatar_args(&self, sub: &str, with: &[(&str, String)], extra: &[&str]) -> Vec<String> {
        let mut v = vec![sub.to_string()];
        for (k, name) in [
            ("--ckpt", "tiny.safetensors"),
            ("--flame", "flame.safetensors"),
            ("--source", "src.png"),
            ("--source-record", "src.json"),
        ] {
            v.push(k.into());
            match with.iter().find(|(f, _)| *f == k) {
                Some((_, value)) => v.push(value.clone()),
                None => v.push(self.s(name)),
            }
        }
        v.extend(extra.iter().map(|s| s.to_string()));
        v
    }
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

pub fn strs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

/// The hidden temporary siblings of `output` (`.NAME.tmpPID.N`, `.NAME.mdat.tmpPID.N`, ...) and
/// their sizes.
pub fn temp_siblings(output: &Path) -> Vec<(PathBuf, u64)> {
    let dir = output.parent().unwrap();
    let prefix = format!(".{}.", output.file_name().unwrap().to_string_lossy());
    let Ok(rd) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    rd.filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
        .map(|e| {
            let len = e.metadata().map(|m| m.len()).unwrap_or(0);
            (e.path(), len)
        })
        .collect()
}

/// What happened to a command killed with SIGKILL while writing `output`.
#[derive(Debug)]
pub struct Killed {
    /// The kill landed while the output was being written (a temp sibling held at least the
    /// requested bytes); `false` when the command finished first.
    pub mid_write: bool,
    /// Temp siblings left behind (allowed: hidden, never at the output path).
    pub leftovers: Vec<PathBuf>,
}

/// How long the child holds a finished temporary before renaming it (see
/// `gagavatar_formats::atomic::PAUSE_BEFORE_RENAME_ENV`): far longer than the polling below
/// needs to see it, so the kill always lands inside the write, whatever the machine's speed.
const PAUSE_BEFORE_RENAME_MS: &str = "60000";

/// Starts `gagavatar args`, waits until a temp sibling of `output` holds at least `min_bytes`,
/// kills the process with SIGKILL (no handler runs, nothing is cleaned up) and reaps it. The
/// caller checks that `output` does not exist. Reusable for every command that writes through
/// the atomic temp-and-rename mechanism (reenact, orbit, export-ply, track, ...). The child
/// pauses before each rename, so a finished temporary waits for the kill.
pub fn kill_mid_write(args: &[String], output: &Path, min_bytes: u64) -> Killed {
    let mut child = Command::new(BIN)
        .args(args)
        .env(
            gagavatar_formats::atomic::PAUSE_BEFORE_RENAME_ENV,
            PAUSE_BEFORE_RENAME_MS,
        )
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("starting gagavatar");
    let t0 = Instant::now();
    let mut mid_write = false;
    while t0.elapsed() < Duration::from_secs(120) {
        if temp_siblings(output).iter().any(|(_, n)| *n >= min_bytes) {
            let _ = child.kill();
            mid_write = true;
            break;
        }
        if child.try_wait().unwrap().is_some() {
            break;
        }
        std::thread::sleep(Duration::from_micros(200));
    }
    if !mid_write {
        let _ = child.kill();
    }
    let _ = child.wait();
    Killed {
        mid_write,
        leftovers: temp_siblings(output).into_iter().map(|(p, _)| p).collect(),
    }
}
