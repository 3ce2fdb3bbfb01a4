//! Evaluation of a model on a split (spec section 11's validation): for each pair (the first
//! frame of a video driving each other frame), PSNR and SSIM of
//! - `fine`: the neural renderer's output (what the release validates and reports),
//! - `coarse`: the splatted image's RGB channels alone (what the "without neural renderer"
//!   ablation outputs),
//! - `source`: the source image itself as the prediction, a floor any model should beat.
//!
//! PSNR is [`crate::metrics::psnr`] and SSIM [`crate::metrics::ssim_gray`] (11x11 Gaussian
//! window on luma, reflect padding: the release's validation SSIM), both on images clamped to
//! [0, 1] at the model's resolution, averaged over pairs. The renderer uses its fixed noise
//! buffers, so an evaluation is deterministic.
//!
//! With LPIPS weights ([`evaluate_with`]), each score also has LPIPS ([`Lpips`], AlexNet, on
//! the same clamped images; lower is better); without them the report is unchanged.

use std::path::Path;

use candle_core::{Device, Tensor};
use gagavatar_net::model::{Avatar, GagAvatar};
use gagavatar_net::style_unet::Noise;
use serde::Serialize;

use crate::lpips::Lpips;
use crate::metrics::{psnr, ssim_gray};
use crate::pairs::{Pair, SampleSource};
use crate::run_error::{ckpt_err, RunResult};

#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Scores {
    pub psnr: f64,
    pub ssim: f64,
    /// LPIPS (lower is better), when the evaluation had its weights.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f64>,
}

/// The scores of one pair.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PairScores {
    pub source: String,
    pub target: String,
    pub fine: Scores,
    pub coarse: Scores,
    /// The source image as the prediction.
    pub copy_source: Scores,
}

/// Per-pair scores of a split.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EvalReport {
    pub split: String,
    pub pairs: Vec<PairScores>,
}

/// One row of the validation grid: target, coarse RGB, fine, each `[3, S, S]` in [0, 1].
#[derive(Debug, Clone)]
pub struct GridRow {
    pub target: Vec<f32>,
    pub coarse: Vec<f32>,
    pub fine: Vec<f32>,
}

impl EvalReport {
    fn mean_of(&self, f: impl Fn(&PairScores) -> Scores) -> Scores {
        let n = self.pairs.len().max(1) as f64;
        let (p, s) = self
            .pairs
            .iter()
            .map(&f)
            .fold((0.0, 0.0), |(p, s), x| (p + x.psnr, s + x.ssim));
        // A mean only when every pair has the score (an evaluation has it for all or none).
        let lpips = self
            .pairs
            .iter()
            .map(|x| f(x).lpips)
            .sum::<Option<f64>>()
            .filter(|_| !self.pairs.is_empty())
            .map(|l| l / n);
        Scores {
            psnr: p / n,
            ssim: s / n,
            lpips,
        }
    }

    pub fn fine(&self) -> Scores {
        self.mean_of(|p| p.fine)
    }

    pub fn coarse(&self) -> Scores {
        self.mean_of(|p| p.coarse)
    }

    pub fn copy_source(&self) -> Scores {
        self.mean_of(|p| p.copy_source)
    }

    /// A small text table of the means.
    pub fn table(&self) -> String {
        let mut s = format!(
            "split `{}`, {} pairs (first frame of each video as source)\n",
            self.split,
            self.pairs.len()
        );
        let rows = [
            ("fine (neural renderer)", self.fine()),
            ("coarse (splatted RGB)", self.coarse()),
            ("copy the source image", self.copy_source()),
        ];
        if rows.iter().all(|r| r.1.lpips.is_some()) {
            s += &format!(
                "{:<26} {:>8} {:>8} {:>8}   (LPIPS: lower is better)\n",
                "prediction", "PSNR", "SSIM", "LPIPS"
            );
            for (name, sc) in rows {
                let l = sc.lpips.unwrap_or(f64::NAN);
                s += &format!("{name:<26} {:>8.3} {:>8.4} {l:>8.4}\n", sc.psnr, sc.ssim);
            }
            return s;
        }
        s += &format!("{:<26} {:>8} {:>8}\n", "prediction", "PSNR", "SSIM");
        for (name, sc) in rows {
            s += &format!("{name:<26} {:>8.3} {:>8.4}\n", sc.psnr, sc.ssim);
        }
        s
    }

    /// Means and per-pair scores as JSON.
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "split": self.split,
            "n_pairs": self.pairs.len(),
            "fine": self.fine(),
            "coarse": self.coarse(),
            "copy_source": self.copy_source(),
            "pairs": self.pairs,
        })
    }
}

fn scores(pred: &Tensor, target: &Tensor, lpips: Option<&Lpips>) -> RunResult<Scores> {
    let lpips = match lpips {
        // Clamped like the images PSNR and SSIM see.
        Some(net) => {
            let d = net.distances(&pred.clamp(0f32, 1f32)?, &target.clamp(0f32, 1f32)?)?;
            Some(d.iter().sum::<f64>() / d.len().max(1) as f64)
        }
        None => None,
    };
    Ok(Scores {
        psnr: psnr(pred, target)?,
        ssim: ssim_gray(pred, target)?,
        lpips,
    })
}

fn host(t: &Tensor) -> RunResult<Vec<f32>> {
    Ok(t.clamp(0f32, 1f32)?
        .to_dtype(candle_core::DType::F32)?
        .flatten_all()?
        .to_vec1()?)
}

/// Evaluates `pairs` (see the module docs), reconstructing each source once for consecutive
/// pairs that share it. Keeps the images of the first `grid_rows` pairs. `progress(done,
/// total)` is called after each pair; returning `false` stops early (the report then holds the
/// pairs done).
pub fn evaluate(
    model: &GagAvatar,
    source: &SampleSource,
    split: &str,
    pairs: &[Pair],
    grid_rows: usize,
    progress: &mut dyn FnMut(usize, usize) -> bool,
) -> RunResult<(EvalReport, Vec<GridRow>)> {
    evaluate_with(model, source, split, pairs, grid_rows, None, progress)
}

/// [`evaluate`], with LPIPS in every score when `lpips` is given.
pub fn evaluate_with(
    model: &GagAvatar,
    source: &SampleSource,
    split: &str,
    pairs: &[Pair],
    grid_rows: usize,
    lpips: Option<&Lpips>,
    progress: &mut dyn FnMut(usize, usize) -> bool,
) -> RunResult<(EvalReport, Vec<GridRow>)> {
    let dev = model.head_base.device().clone();
    let s = source.image_size;
    let mut out = Vec::with_capacity(pairs.len());
    let mut grid = Vec::new();
    let mut current: Option<(String, Avatar, Tensor)> = None;
    for (i, pair) in pairs.iter().enumerate() {
        let sample = source.load(pair)?;
        let batch = crate::pairs::HostBatch {
            step: 0,
            samples: vec![sample],
            image_size: s,
            n_vertices: source.flame.n_vertices,
        }
        .to_tensors(&dev)?;
        // Consecutive pairs of one video share the source: reconstruct it once.
        let (avatar, source_image) = match current.take() {
            Some((name, avatar, image)) if name == pair.source => (avatar, image),
            _ => (
                model.reconstruct(&batch.source_image, &batch.source_transform)?,
                batch.source_image.clone(),
            ),
        };
        let frame = model.drive(
            &avatar,
            &batch.target_vertices,
            &batch.target_transform,
            Noise::Fixed,
        )?;
        let coarse = frame.coarse.narrow(1, 0, 3)?;
        let gt = &batch.target_image;
        out.push(PairScores {
            source: pair.source.clone(),
            target: pair.target.clone(),
            fine: scores(&frame.fine, gt, lpips)?,
            coarse: scores(&coarse, gt, lpips)?,
            copy_source: scores(&source_image, gt, lpips)?,
        });
        if grid.len() < grid_rows {
            grid.push(GridRow {
                target: host(gt)?,
                coarse: host(&coarse)?,
                fine: host(&frame.fine)?,
            });
        }
        current = Some((pair.source.clone(), avatar, source_image));
        if !progress(i + 1, pairs.len()) {
            break;
        }
    }
    Ok((
        EvalReport {
            split: split.to_string(),
            pairs: out,
        },
        grid,
    ))
}

/// The grid image: one row per pair, target | coarse | fine.
pub fn grid_image(rows: &[GridRow], size: usize) -> image::RgbImage {
    let mut img = image::RgbImage::new((3 * size) as u32, (rows.len() * size).max(1) as u32);
    for (r, row) in rows.iter().enumerate() {
        for (c, chw) in [&row.target, &row.coarse, &row.fine]
            .into_iter()
            .enumerate()
        {
            for y in 0..size {
                for x in 0..size {
                    let px = |ch: usize| {
                        let v = chw
                            .get(ch * size * size + y * size + x)
                            .copied()
                            .unwrap_or(0.0);
                        (v.clamp(0.0, 1.0) * 255.0).round() as u8
                    };
                    img.put_pixel(
                        (c * size + x) as u32,
                        (r * size + y) as u32,
                        image::Rgb([px(0), px(1), px(2)]),
                    );
                }
            }
        }
    }
    img
}

/// Writes the grid as a PNG, atomically.
pub fn write_grid(path: &Path, rows: &[GridRow], size: usize) -> RunResult<()> {
    let png = gagavatar_data::encode_png(&grid_image(rows, size))?;
    gagavatar_formats::atomic::write_atomic(path, &png).map_err(|e| ckpt_err(path, e.detail()))
}

/// The device a model's weights live on.
pub fn model_device(model: &GagAvatar) -> Device {
    model.head_base.device().clone()
}
