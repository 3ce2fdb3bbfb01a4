//! Step time of the training loop on a synthetic batch (no dataset): the built-in FLAME head
//! at rest seen from two cameras, smooth random images. Measures exactly what
//! [`TrainState::train_step`] does (forward of both phases, every loss term, backward, the
//! NaN-guard check, Adam), not the data loading, which runs on other threads.

use std::time::Instant;

use candle_core::{Device, Tensor};
use gagavatar_splat::Camera;

use crate::config::TrainConfig;
use crate::pairs::BatchTensors;
use crate::perceptual::PerceptualLoss;
use crate::run_error::RunResult;
use crate::trainer::{load_flame, TrainState};

/// Timings of [`time_steps`].
#[derive(Debug, Clone)]
pub struct StepTiming {
    /// Building the model and the optimiser.
    pub build_s: f64,
    /// Each timed step, in seconds (after one untimed warm-up step).
    pub steps_s: Vec<f64>,
    /// Values the optimiser trains.
    pub trained_values: usize,
    pub backbone_frozen: bool,
    pub percep: bool,
    pub losses: Vec<f64>,
    /// Per timed step, where a split step's time went (`--device gpu`).
    pub splits: Vec<crate::trainer::SplitTiming>,
}

impl StepTiming {
    pub fn median_s(&self) -> f64 {
        median(self.steps_s.clone())
    }

    /// Medians of the split steps' parts: reconstruction forward, device, host, backward.
    pub fn split_medians(&self) -> Option<[f64; 4]> {
        if self.splits.is_empty() {
            return None;
        }
        let part = |f: fn(&crate::trainer::SplitTiming) -> f64| {
            median(self.splits.iter().map(f).collect())
        };
        Some([
            part(|t| t.reconstruct_s),
            part(|t| t.device_s),
            part(|t| t.host_s),
            part(|t| t.backward_s),
        ])
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// A synthetic batch of `batch` pairs at the configuration's sizes.
pub fn synthetic_batch(
    cfg: &TrainConfig,
    batch: usize,
    device: &Device,
) -> RunResult<BatchTensors> {
    let s = cfg.model.image_size;
    let flame = load_flame(None)?;
    let params = gagavatar_flame::FlameParams::zeros(&flame, 1)?;
    let verts = flame.forward(&params)?.vertices; // [1, V, 3]
    let verts = Tensor::cat(&vec![verts; batch], 0)?.to_device(device)?;
    let cam = |yaw: f64| -> RunResult<Tensor> {
        let m = Camera::look_at_origin_matrix(9.0, yaw, 0.1);
        let flat: Vec<f32> = m.iter().flatten().map(|&v| v as f32).collect();
        let one = Tensor::from_vec(flat, (1, 3, 4), device)?;
        Ok(Tensor::cat(&vec![one; batch], 0)?)
    };
    // Smooth images: a few low-frequency waves per channel, values in [0.1, 0.9].
    let img = |phase: f32| -> RunResult<Tensor> {
        let mut v = vec![0f32; batch * 3 * s * s];
        for (i, x) in v.iter_mut().enumerate() {
            let (c, y, xx) = ((i / (s * s)) % 3, (i / s) % s, i % s);
            let (fy, fx) = (y as f32 / s as f32, xx as f32 / s as f32);
            *x = 0.5 + 0.4 * (6.0 * fx + 4.0 * fy + c as f32 + phase).sin() * (3.0 * fy).cos();
        }
        Ok(Tensor::from_vec(v, (batch, 3, s, s), device)?)
    };
    let bbox = Tensor::from_vec([0.3f32, 0.25, 0.7, 0.75].repeat(batch), (batch, 4), device)?;
    Ok(BatchTensors {
        source_image: img(0.0)?,
        source_transform: cam(0.3)?,
        target_image: img(1.0)?,
        target_transform: cam(-0.2)?,
        target_vertices: verts,
        bbox,
    })
}

/// Builds the model of `cfg` (seeded weights) and times `runs` steps at batch `batch`.
pub fn time_steps(
    cfg: &TrainConfig,
    percep: Option<PerceptualLoss>,
    batch: usize,
    runs: usize,
    device: &Device,
) -> RunResult<StepTiming> {
    time_steps_with(cfg, percep, batch, runs, device, |_| Ok(()))
}

/// [`time_steps`] with `setup` applied to the state before the first step (e.g. a
/// [`crate::RenderHalf`] on a GPU; its setup counts in `build_s`).
pub fn time_steps_with(
    cfg: &TrainConfig,
    percep: Option<PerceptualLoss>,
    batch: usize,
    runs: usize,
    device: &Device,
    setup: impl FnOnce(&mut TrainState) -> RunResult<()>,
) -> RunResult<StepTiming> {
    let t0 = Instant::now();
    let has_percep = percep.is_some();
    let mut state = TrainState::new(cfg.clone(), None, percep, device)?;
    setup(&mut state)?;
    let trained_values = state.vars()?.iter().map(|(_, v)| v.elem_count()).sum();
    let build_s = t0.elapsed().as_secs_f64();
    let b = synthetic_batch(cfg, batch, device)?;
    let mut steps_s = Vec::new();
    let mut losses = Vec::new();
    let mut splits = Vec::new();
    for i in 0..=runs {
        let t = Instant::now();
        let r = state.train_step(&b)?;
        if i > 0 {
            steps_s.push(t.elapsed().as_secs_f64());
            splits.extend(state.last_split());
        }
        losses.push(r.loss);
    }
    Ok(StepTiming {
        build_s,
        steps_s,
        trained_values,
        backbone_frozen: cfg.model.backbone_frozen(),
        percep: has_percep,
        losses,
        splits,
    })
}
