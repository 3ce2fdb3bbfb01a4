//! Helpers of the training-run tests: scratch folders, synthetic datasets, tiny configurations.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::sync::Once;

use gagavatar_synthdata::{Generator, NoProgress, SynthConfig, WriteOptions};
use gagavatar_train::TrainConfig;

/// candle's element-wise pool spin-waits between ops by default; on a shared 2-core machine
/// that made tiny steps 4x slower. Set once, before any test touches candle.
pub fn init() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        if std::env::var_os("CANDLE_BARRIER_POOL_SPIN_LIMIT").is_none() {
            std::env::set_var("CANDLE_BARRIER_POOL_SPIN_LIMIT", "0");
        }
    });
}

/// An empty scratch folder for one test.
pub fn scratch(name: &str) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("train_{name}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A synthetic dataset (release layout) of `ids` identities x `frames` frames at `size` px,
/// with the built-in FLAME asset; the last identity is held out for val/test.
pub fn synth_dataset(dir: &Path, ids: usize, frames: usize, size: usize, seed: u64) -> PathBuf {
    let out = dir.join("data");
    let mut cfg = SynthConfig::new(ids, frames, size, seed);
    cfg.holdout = Some(1);
    let generator = Generator::new(&gagavatar_flame::synthesize(0), cfg).unwrap();
    generator
        .write_dataset(&out, WriteOptions { overwrite: true }, &NoProgress)
        .unwrap();
    out
}

/// The tiny preset on `data`, with test-sized loop settings.
pub fn tiny_config(data: &Path, steps: u64) -> TrainConfig {
    let mut cfg = TrainConfig::preset("tiny").unwrap();
    cfg.data.dir = Some(data.to_path_buf());
    cfg.train.steps = steps;
    cfg.train.checkpoint_every = 0;
    cfg.val.every = 0;
    cfg.log.every_step_until = 1_000_000;
    cfg
}

/// `(step, loss)` of every line of a run's metrics.jsonl.
pub fn losses(run: &Path) -> Vec<(u64, f64)> {
    let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    text.lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            (
                v["step"].as_u64().unwrap(),
                v["loss"].as_f64().unwrap_or(f64::NAN),
            )
        })
        .collect()
}
