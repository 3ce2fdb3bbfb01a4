//! The training loop (spec section 11): a [`TrainState`] (model, optimiser, loss) that takes
//! one step on a batch, and a [`Run`] that owns a run folder and drives the state with pairs
//! from a dataset, validation, logging and checkpoints.
//!
//! - Step: both phases in one graph ([`GagAvatar::train_forward`]), the release's loss
//!   ([`TrainLosses`]), backward, then Adam. The renderer's noise is
//!   [`Noise::Seeded`] from `(seed, step)`. With a [`RenderHalf`] (`--device gpu`) the
//!   splatting, renderer and image terms of each sample (and the lifting generators and the
//!   DPT head, when it runs them) run there, forward and backward, and the Gaussians' (or the
//!   expression Gaussians' and `F_local`'s, or the expression Gaussians' alone) gradients come
//!   back into one backward of the reconstruction (the same gradients: see
//!   [`TrainState::set_render_half`]).
//! - NaN guard: a step whose loss or any gradient is NaN or infinite changes nothing (no
//!   update, the optimiser and its schedule stay where they were); it is reported, logged with
//!   `"skipped"` in `metrics.jsonl` and counted.
//! - Frozen parts: what the configuration freezes (the DINOv2 backbone in the release) is not a
//!   variable at all (see `gagavatar_net::train`), so neither gradient nor update can reach it.
//! - Run folder: `config.toml` (the effective configuration), `metrics.jsonl` (one JSON object
//!   per logged step: every step up to `log.every_step_until`, then every `log.every`, and
//!   every validation, checkpoint or skipped step), `val/step_NNNNNNN.png` (target | coarse |
//!   fine per validation pair), `checkpoint.safetensors` and `weights.safetensors` (see
//!   [`crate::ckpt`]). Every file is replaced atomically.
//! - Resume: [`Run::resume`] restores weights, optimiser state, step and configuration from the
//!   checkpoint; pairs and noise are functions of `(seed, step)`, so the resumed run computes
//!   what the uninterrupted run computes.
//! - Errors: a dataset that cannot be opened (LMDB, pickle, splits) or whose first batch cannot
//!   be loaded fails before the run folder is touched; a frame that fails later stops the run
//!   with an error naming it, and the last checkpoint (if any) is left as it was.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarMap;
use gagavatar_data::Dataset;
use gagavatar_flame::{synthesize, FlameAsset, FlameModel, LoadOptions};
use gagavatar_net::checkpoint::{read_weights, write_tensors_with_metadata, FLAME_METADATA_KEY};
use gagavatar_net::model::{cameras, coarse_gaussians, GagAvatar};
use gagavatar_net::style_unet::{noise_resolution, seeded_noise_from, Noise};
use gagavatar_net::train::{export_weights, trainable_model};
use gagavatar_net::ModelConfig;
use serde_json::json;

use crate::adam::Adam;
use crate::ckpt::{
    read_checkpoint, write_checkpoint, TrainMeta, CHECKPOINT_FILE, CHECKPOINT_FORMAT, CONFIG_FILE,
    METRICS_FILE, VAL_DIR, WEIGHTS_FILE,
};
use crate::collective::{Collective, Single};
use crate::config::TrainConfig;
use crate::eval::{evaluate, write_grid, EvalReport};
use crate::head_box::{crop_resize, head_boxes};
use crate::losses::{LossInputs, TrainLosses};
use crate::nearest::lifting_loss;
use crate::pairs::{eval_pairs, mix, BatchTensors, Loader, Pair, PairSampler, SampleSource};
use crate::perceptual::{PerceptualLoss, PERCEP_PREFIX};
use crate::render_half::{LiftSample, LiftedGaussians, RenderHalf, RenderSample};
use crate::run_error::{ckpt_err, config_err, io_err, RunError, RunResult};

/// Salt of the renderer-noise stream.
const SALT_NOISE: u64 = 0x4E01_5E00;

/// What a run reports while it works. Every method has a do-nothing default.
pub trait Monitor {
    /// Something the user should know (a term switched off, a skipped step, ...).
    fn warn(&self, _msg: &str) {}
    /// Training starts at 0-based step `first` and stops at `until`.
    fn started(&self, _first: u64, _until: u64) {}
    fn step(&self, _report: &StepReport) {}
    fn validation(&self, _step: u64, _report: &EvalReport) {}
    fn checkpoint(&self, _step: u64, _path: &Path) {}
    /// Polled before each step: `true` ends the run after writing a checkpoint.
    fn stop_requested(&self) -> bool {
        false
    }
}

/// A [`Monitor`] that ignores everything.
#[derive(Debug, Default, Clone, Copy)]
pub struct NoMonitor;
impl Monitor for NoMonitor {}

/// The outcome of one step.
#[derive(Debug, Clone, PartialEq)]
pub struct StepReport {
    /// 1-based number of the step (the release's `iter_idx`).
    pub step: u64,
    pub loss: f64,
    pub img: f64,
    pub box_l1: f64,
    pub percep: Option<f64>,
    pub point: Option<f64>,
    /// The base learning rate the step used (groups scale it).
    pub lr: f64,
    /// L2 norm of all gradients (NaN when the step was skipped before backward).
    pub grad_norm: f64,
    /// Why the NaN guard skipped the step.
    pub skipped: Option<String>,
    /// Trainable parameters that got no gradient.
    pub no_grad: Vec<String>,
    pub seconds: f64,
}

/// Parameters that get no gradient by construction, in the release too: the ViT's mask token
/// (used only for masked inputs), the first DPT fusion block's first residual unit (its input
/// is never added), the StyleUNet's `toRGB` skip outputs (the release discards them), and what
/// an ablation switches off.
pub fn gets_no_gradient(cfg: &ModelConfig, key: &str) -> bool {
    key == "base_model.dino_model.mask_token"
        || key.starts_with("base_model.refinenet.0.resConfUnit1.")
        || key.starts_with("upsampler.toRGB.")
        || (cfg.one_plane && key.starts_with("gs_generator_l1."))
        || (cfg.no_neural_renderer && key.starts_with("upsampler."))
}

/// Model, optimiser and loss: one step at a time, no files.
pub struct TrainState {
    pub cfg: TrainConfig,
    pub model: GagAvatar,
    pub varmap: VarMap,
    pub adam: Adam,
    pub losses: TrainLosses,
    /// Steps completed (skipped ones included): the next step's 0-based index.
    pub step: u64,
    /// Steps the NaN guard skipped.
    pub skipped_steps: u64,
    poisoned: BTreeSet<u64>,
    /// The ranks this state trains with (one: [`Single`]).
    collective: Arc<dyn Collective>,
    /// Where the rendering half of each step runs when not in the candle graph (a GPU).
    render_half: Option<Box<dyn RenderHalf>>,
    /// The last split step's timing.
    last_split: Option<SplitTiming>,
}

/// Where a split step's time went (wall seconds; see [`TrainState::last_split`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SplitTiming {
    /// The reconstruction's forward in candle (a backbone on the device included).
    pub reconstruct_s: f64,
    /// Inside the rendering half's calls (weights, forward, backward; waits included).
    pub device_s: f64,
    /// The host work around them: copies, the perceptual term when it runs here.
    pub host_s: f64,
    /// The reconstruction's backward in candle (and the lifting term, unless the device
    /// computed it).
    pub backward_s: f64,
}

/// The perceptual networks' host weights (by key without `percep_loss.`) and the term's factor.
pub type PercepWeights = (HashMap<String, Vec<f32>>, f64);

/// The loss terms' values of a step (this rank's batch).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepTerms {
    pub loss: f64,
    pub img: f64,
    pub box_l1: f64,
    pub percep: Option<f64>,
    pub point: Option<f64>,
}

impl std::fmt::Debug for TrainState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TrainState")
            .field("model", &self.cfg.model.name)
            .field("step", &self.step)
            .field("skipped_steps", &self.skipped_steps)
            .finish()
    }
}

/// The values of the variables whose key starts with `prefix`, flattened, by key (without the
/// prefix when `strip`).
fn host_weights(
    vars: &HashMap<String, Var>,
    prefix: &str,
    strip: bool,
) -> RunResult<HashMap<String, Vec<f32>>> {
    let mut out = HashMap::new();
    for (k, v) in vars {
        if let Some(rest) = k.strip_prefix(prefix) {
            let t = v.as_tensor().flatten_all()?.to_dtype(DType::F32)?;
            let key = if strip { rest } else { k.as_str() };
            out.insert(key.to_string(), t.to_vec1::<f32>()?);
        }
    }
    Ok(out)
}

/// Both lifting generators' values by checkpoint key.
fn lifting_host_weights(vars: &HashMap<String, Var>) -> RunResult<HashMap<String, Vec<f32>>> {
    let mut w = host_weights(vars, "gs_generator_l0.", false)?;
    w.extend(host_weights(vars, "gs_generator_l1.", false)?);
    Ok(w)
}

/// The DPT head's values by checkpoint key (`base_model.` outside the backbone).
fn dpt_host_weights(vars: &HashMap<String, Var>) -> RunResult<HashMap<String, Vec<f32>>> {
    let mut w = host_weights(vars, "base_model.", false)?;
    w.retain(|k, _| !k.starts_with("base_model.dino_model."));
    Ok(w)
}

/// The reconstruction's candle graph in a split step: all of it, with the Gaussians the
/// device splats, or (lifting generators on the device) up to `F_local` and the expression
/// Gaussians, or (the DPT head there too) the expression Gaussians alone.
enum Graph {
    Whole {
        avatar: gagavatar_net::model::Avatar,
        g: gagavatar_net::model::CoarseGaussians,
    },
    Lift {
        expr: gagavatar_net::gs_generator::GaussianAttributes,
        trace: gagavatar_net::model::ReconstructTrace,
    },
}

fn named_vars(varmap: &VarMap) -> RunResult<Vec<(String, Var)>> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| config_err(None, "the VarMap lock is poisoned"))?;
    Ok(data.iter().map(|(k, v)| (k.clone(), v.clone())).collect())
}

impl TrainState {
    /// A fresh state: weights from `init` (a checkpoint's tensors; `percep_loss.*` are ignored)
    /// or seeded from `cfg.train.seed`; Adam with the configuration's groups and schedule.
    pub fn new(
        cfg: TrainConfig,
        init: Option<HashMap<String, Tensor>>,
        percep: Option<PerceptualLoss>,
        device: &Device,
    ) -> RunResult<Self> {
        let (model, varmap) = trainable_model(&cfg.model, init, cfg.train.seed, device)?;
        let adam = Adam::new(named_vars(&varmap)?, cfg.adam())?;
        let losses = TrainLosses::new(cfg.losses(), percep);
        Ok(Self {
            cfg,
            model,
            varmap,
            adam,
            losses,
            step: 0,
            skipped_steps: 0,
            poisoned: BTreeSet::new(),
            collective: Arc::new(Single),
            render_half: None,
            last_split: None,
        })
    }

    /// Trains as one rank of a data-parallel run: each step's batch is this rank's share, and
    /// gradients and loss terms are averaged over the ranks before the (identical) Adam step.
    pub fn set_collective(&mut self, collective: Arc<dyn Collective>) {
        self.collective = collective;
    }

    /// Runs the rendering half of every step on `rh` (a GPU): see
    /// [`crate::render_half`]. The model's ablations without a neural renderer keep the CPU.
    pub fn set_render_half(&mut self, rh: Box<dyn RenderHalf>) -> RunResult<()> {
        if self.cfg.model.no_neural_renderer {
            return Err(config_err(
                None,
                "the no_neural_renderer ablation trains on the CPU only (--device cpu)",
            ));
        }
        self.render_half = Some(rh);
        Ok(())
    }

    /// The renderer's trained weights, by key relative to `upsampler.`, flattened f32 (what a
    /// [`RenderHalf`] is built with and receives each step).
    pub fn renderer_weights(&self) -> RunResult<HashMap<String, Vec<f32>>> {
        host_weights(&self.vars()?.into_iter().collect(), "upsampler.", true)
    }

    /// The lifting generators' weights by checkpoint key (what a [`RenderHalf`] that runs
    /// them is built with and receives each step).
    pub fn lifting_weights(&self) -> RunResult<HashMap<String, Vec<f32>>> {
        lifting_host_weights(&self.vars()?.into_iter().collect())
    }

    /// The DPT head's values by checkpoint key (`base_model.projects.0.weight`, ...): what a
    /// [`RenderHalf`] that runs the head is built with.
    pub fn dpt_weights(&self) -> RunResult<HashMap<String, Vec<f32>>> {
        dpt_host_weights(&self.vars()?.into_iter().collect())
    }

    /// The perceptual networks' weights (by key without `percep_loss.`) and the term's factor,
    /// when the term is on: what a [`RenderHalf`] that computes the term is built with.
    pub fn percep_weights(&self) -> RunResult<Option<PercepWeights>> {
        match self.losses.percep() {
            Some(p) => Ok(Some((p.host_weights()?, self.losses.cfg.percep_weight))),
            None => Ok(None),
        }
    }

    /// Where the last step's time went, when its rendering half ran on a device.
    pub fn last_split(&self) -> Option<SplitTiming> {
        self.last_split
    }

    /// The device of the rendering half, when it is not the CPU.
    pub fn render_device(&self) -> Option<String> {
        self.render_half.as_ref().map(|r| r.describe())
    }

    /// The step's forward and backward with the rendering half on `rh`: reconstruction in the
    /// candle graph (without the lifting generators when `rh` runs them), each sample's
    /// splatting, renderer and image terms (forward and backward) on `rh`, the perceptual
    /// distance of the crops `rh` returns and the lifting term here (unless `rh` computes
    /// them); then one backward of the
    /// reconstruction from the Gaussians' gradients (or, with the lifting generators on `rh`,
    /// from the expression Gaussians' and `F_local`'s; with the DPT head there too, from the
    /// expression Gaussians' alone, the head's weight gradients coming from `rh`). Every term
    /// is a mean over the batch, so each sample's gradients count `1 / B`.
    fn split_forward_backward(
        &self,
        rh: &mut dyn RenderHalf,
        batch: &BatchTensors,
        seed: u64,
        first: usize,
    ) -> RunResult<(StepTerms, Option<GradStore>, SplitTiming)> {
        let t_start = Instant::now();
        let mut timing = SplitTiming::default();
        let name = rh.describe();
        let device = |err| RunError::Render {
            device: name.clone(),
            err,
        };
        let cfg = &self.cfg.model;
        let mut host_tokens: Option<[Vec<f32>; 4]> = None;
        let backbone = if cfg.backbone_frozen() && rh.has_backbone() {
            let images = batch
                .source_image
                .to_dtype(DType::F32)?
                .flatten_from(1)?
                .to_vec2::<f32>()?;
            let cams = batch
                .source_transform
                .to_dtype(DType::F32)?
                .flatten_from(1)?
                .to_vec2::<f32>()?;
            let g2 = cfg.grid() * cfg.grid();
            let mut outs: [Vec<f32>; 4] = Default::default();
            for (im, cam) in images.iter().zip(&cams) {
                for (o, v) in outs.iter_mut().zip(rh.backbone(im, cam).map_err(device)?) {
                    if v.len() != g2 * cfg.vit_dim {
                        return Err(device(
                            format!("{} backbone values, expected {}", v.len(), g2 * cfg.vit_dim)
                                .into(),
                        ));
                    }
                    o.extend(v);
                }
            }
            let b = images.len();
            // The device's DPT head reads them again, sample by sample.
            if rh.has_dpt() && rh.has_lifting() {
                host_tokens = Some(outs.clone());
            }
            let [o0, o1, o2, o3] =
                outs.map(|v| Tensor::from_vec(v, (b, g2, cfg.vit_dim), &Device::Cpu));
            Some([o0?, o1?, o2?, o3?])
        } else {
            None
        };
        let rows = |t: &Tensor| -> RunResult<Vec<Vec<f32>>> {
            Ok(t.flatten_from(1)?.to_dtype(DType::F32)?.to_vec2::<f32>()?)
        };
        let (img_src, cam_src) = (&batch.source_image, &batch.source_transform);
        // What the device splats, per sample: either every Gaussian (host rows of the candle
        // graph's attributes), or the expression Gaussians here and the lifted ones from the
        // device, sample by sample.
        // With the DPT head on the device too, the graph stops at the expression Gaussians.
        let dpt_here = host_tokens.is_some();
        let graph = if rh.has_lifting() {
            let (expr, trace) = match backbone {
                Some(outs) if dpt_here => {
                    self.model.reconstruct_expression(img_src, cam_src, outs)?
                }
                backbone => self
                    .model
                    .reconstruct_features(img_src, cam_src, backbone)?,
            };
            Graph::Lift { expr, trace }
        } else {
            let avatar = match backbone {
                Some(outs) => self
                    .model
                    .reconstruct_with_backbone(img_src, cam_src, outs)?,
                None => self.model.reconstruct(img_src, cam_src)?,
            };
            let g = coarse_gaussians(
                cfg,
                &avatar,
                &batch.target_vertices,
                &batch.target_transform,
            )?;
            Graph::Whole { avatar, g }
        };
        timing.reconstruct_s = t_start.elapsed().as_secs_f64();
        let cameras = cameras(&batch.target_transform, cfg.image_size)?;
        // The graph's tensors whose gradients the device returns, in RenderSample's order
        // (means, features, opacities, scales, rotations); with the lifting generators on the
        // device the means are the target's vertices (no gradient) and `F_local` follows.
        let attrs: Vec<Option<&Tensor>> = match &graph {
            Graph::Whole { g, .. } => {
                [&g.means, &g.features, &g.opacities, &g.scales, &g.rotations]
                    .into_iter()
                    .map(Some)
                    .collect()
            }
            Graph::Lift { expr, trace } => vec![
                None,
                Some(&expr.colors),
                Some(&expr.opacities),
                Some(&expr.scales),
                Some(&expr.rotations),
                (!dpt_here).then_some(&trace.f_local),
            ],
        };
        let vars: HashMap<String, Var> = self.vars()?.into_iter().collect();
        let t = Instant::now();
        rh.set_renderer_weights(&host_weights(&vars, "upsampler.", true)?)
            .map_err(device)?;
        if let Graph::Lift { .. } = graph {
            rh.set_lifting_weights(&lifting_host_weights(&vars)?)
                .map_err(device)?;
            if dpt_here {
                rh.set_dpt_weights(&dpt_host_weights(&vars)?)
                    .map_err(device)?;
            }
        }
        timing.device_s += t.elapsed().as_secs_f64();

        let host: Vec<Vec<Vec<f32>>> = match &graph {
            Graph::Whole { g, .. } => {
                [&g.means, &g.features, &g.opacities, &g.scales, &g.rotations]
                    .iter()
                    .map(|t| rows(t))
                    .collect::<RunResult<_>>()?
            }
            Graph::Lift { expr, trace } => vec![
                rows(&batch.target_vertices)?,
                rows(&expr.colors)?,
                rows(&expr.opacities)?,
                rows(&expr.scales)?,
                rows(&expr.rotations)?,
                rows(&trace.f_local)?,
            ],
        };
        let lift_inputs = match &graph {
            Graph::Lift { trace, .. } => Some([
                rows(&trace.dir_encoding)?,
                rows(&trace.plane_points)?,
                rows(&trace.plane_dir)?,
            ]),
            Graph::Whole { .. } => None,
        };
        // The DPT head's other input, per sample, when it runs on the device.
        let dino_inputs = match (&graph, dpt_here) {
            (Graph::Lift { trace, .. }, true) => Some(rows(&trace.input_518)?),
            _ => None,
        };
        let percep = self.losses.percep();
        let nan = StepTerms {
            loss: f64::NAN,
            img: f64::NAN,
            box_l1: f64::NAN,
            percep: percep.map(|_| f64::NAN),
            point: self.losses.cfg.lifting.then_some(f64::NAN),
        };
        // As on the CPU, a blown-up reconstruction makes the loss NaN and the step is skipped
        // (the device would refuse such Gaussians).
        if host.iter().flatten().flatten().any(|v| !v.is_finite()) {
            return Ok((nan, None, timing));
        }
        let targets = rows(&batch.target_image)?;
        let (b, _, h, w) = batch.target_image.dims4()?;
        let boxes = head_boxes(&batch.bbox, h, w)?;
        let box_size = self.losses.cfg.box_size;
        if percep.is_none() && rh.has_percep() {
            return Err(device(
                "computes a perceptual term the run has switched off".into(),
            ));
        }
        // The perceptual term here when the device does not compute it.
        let cpu_percep = percep.filter(|_| !rh.has_percep());
        let gt_crops = match cpu_percep {
            Some(_) => Some(crop_resize(
                &batch.target_image.to_dtype(DType::F32)?,
                &boxes,
                box_size,
            )?),
            None => None,
        };
        let like = Tensor::zeros(1, DType::F32, &Device::Cpu)?;
        let n_noise = 2 * cfg.renderer_levels() + 1;
        let inv_b = 1.0 / b as f32;
        let mut acc: Vec<Vec<f32>> = host
            .iter()
            .map(|a| vec![0f32; a.len() * a[0].len()])
            .collect();
        let (mut img, mut box_l1, mut percep_sum, mut point_sum) = (0.0, 0.0, 0.0, 0.0);
        for i in 0..b {
            // With the lifting generators on the device: this sample's lifted Gaussians after
            // the expression Gaussians.
            let lifted = match &lift_inputs {
                Some([enc, points, dir]) => {
                    let t = Instant::now();
                    if let (Some(tokens), Some(images)) = (&host_tokens, &dino_inputs) {
                        let per = tokens[0].len() / b;
                        let sample = tokens.each_ref().map(|t| &t[i * per..(i + 1) * per]);
                        rh.dpt_forward(sample, &images[i]).map_err(device)?;
                    }
                    let l = rh
                        .lift_forward(&LiftSample {
                            f_local: (!dpt_here).then_some(host[5][i].as_slice()),
                            // The expression Gaussians' means are the target's vertices.
                            targets: self.losses.cfg.lifting.then_some(host[0][i].as_slice()),
                            term_scale: inv_b,
                            encoding: &enc[i],
                            plane_points: &points[i],
                            plane_dir: &dir[i],
                        })
                        .map_err(device)?;
                    timing.device_s += t.elapsed().as_secs_f64();
                    let all = [&l.means, &l.features, &l.opacities, &l.scales, &l.rotations];
                    if all.iter().any(|v| v.iter().any(|x| !x.is_finite())) {
                        return Ok((nan, None, timing));
                    }
                    Some(l)
                }
                None => None,
            };
            let joined: Option<[Vec<f32>; 5]> = lifted.as_ref().map(|l| {
                let cat = |a: &[f32], b: &[f32]| [a, b].concat();
                [
                    cat(&host[0][i], &l.means),
                    cat(&host[1][i], &l.features),
                    cat(&host[2][i], &l.opacities),
                    cat(&host[3][i], &l.scales),
                    cat(&host[4][i], &l.rotations),
                ]
            });
            let at = |k: usize| -> &[f32] {
                match &joined {
                    Some(j) => &j[k],
                    None => &host[k][i],
                }
            };
            let noise = (0..n_noise)
                .map(|j| {
                    let r = noise_resolution(j);
                    let t = seeded_noise_from(seed, j, first + i, 1, r, &like)?;
                    Ok(t.flatten_all()?.to_vec1::<f32>()?)
                })
                .collect::<RunResult<Vec<_>>>()?;
            let sample = RenderSample {
                means: at(0),
                features: at(1),
                channels: cfg.color_dim,
                opacities: at(2),
                scales: at(3),
                rotations: at(4),
                camera: &cameras[i],
                target: &targets[i],
                head_box: boxes[i],
                noise: &noise,
            };
            let t = Instant::now();
            let fwd = rh
                .forward(&sample, box_size, cpu_percep.is_some())
                .map_err(device)?;
            timing.device_s += t.elapsed().as_secs_f64();
            img += fwd.img;
            box_l1 += fwd.box_l1;
            if let Some(v) = fwd.percep {
                percep_sum += v;
            }
            let crop_grads = match (cpu_percep, &gt_crops, fwd.crops) {
                (Some(p), Some(gt), Some([cc, fc])) => {
                    let shape = (1, 3, box_size, box_size);
                    let vc = Var::from_vec(cc, shape, &Device::Cpu)?;
                    let vf = Var::from_vec(fc, shape, &Device::Cpu)?;
                    let target = p.features(&gt.narrow(0, i, 1)?)?;
                    let pred = p.features(&Tensor::cat(&[vc.as_tensor(), vf.as_tensor()], 0)?)?;
                    let d = (PerceptualLoss::distance(&pred, &target)?
                        * self.losses.cfg.percep_weight)?;
                    percep_sum += d.to_dtype(DType::F64)?.to_scalar::<f64>()?;
                    let gs = d.backward()?;
                    let flat = |v: &Var| -> RunResult<Vec<f32>> {
                        Ok(match gs.get(v.as_tensor()) {
                            Some(t) => t.flatten_all()?.to_vec1::<f32>()?,
                            None => vec![0f32; v.as_tensor().elem_count()],
                        })
                    };
                    Some([flat(&vc)?, flat(&vf)?])
                }
                _ => None,
            };
            let t = Instant::now();
            let gr = rh
                .backward(
                    crop_grads
                        .as_ref()
                        .map(|[c, f]| [c.as_slice(), f.as_slice()]),
                    inv_b,
                )
                .map_err(device)?;
            timing.device_s += t.elapsed().as_secs_f64();
            let mut lifted_grads = LiftedGaussians::default();
            let outs = [
                &mut lifted_grads.means,
                &mut lifted_grads.features,
                &mut lifted_grads.opacities,
                &mut lifted_grads.scales,
                &mut lifted_grads.rotations,
            ];
            for ((k, src), out) in [gr.means, gr.features, gr.opacities, gr.scales, gr.rotations]
                .iter()
                .enumerate()
                .zip(outs)
            {
                let total = at(k).len();
                if src.len() != total {
                    return Err(device(
                        format!("{} gradient values for {total} of attribute {k}", src.len())
                            .into(),
                    ));
                }
                // Graph values first (all of them, or the expression Gaussians'), then the
                // lifted Gaussians' for the device's own backward.
                let per = host[k][i].len();
                for (a, v) in acc[k][i * per..(i + 1) * per].iter_mut().zip(src) {
                    *a = v * inv_b;
                }
                if lifted.is_some() {
                    out.extend(src[per..].iter().map(|v| v * inv_b));
                }
            }
            if let Some(l) = &lifted {
                if let Some(p) = l.point {
                    // The device computed the term; its gradient joins in lift_backward.
                    point_sum += p;
                } else if self.losses.cfg.lifting {
                    // The lifting term of this sample (the batch's is the samples' mean).
                    let n = l.means.len() / 3;
                    let xyz = Var::from_slice(&l.means, (1, n, 3), &Device::Cpu)?;
                    let p = lifting_loss(xyz.as_tensor(), &batch.target_vertices.narrow(0, i, 1)?)?;
                    point_sum += p.to_dtype(DType::F64)?.to_scalar::<f64>()?;
                    let gs = (p.to_dtype(DType::F32)? * f64::from(inv_b))?.backward()?;
                    if let Some(g) = gs.get(xyz.as_tensor()) {
                        let g = g.flatten_all()?.to_dtype(DType::F32)?.to_vec1::<f32>()?;
                        for (a, v) in lifted_grads.means.iter_mut().zip(g) {
                            *a += v;
                        }
                    }
                }
                let t = Instant::now();
                let df = rh.lift_backward(&lifted_grads).map_err(device)?;
                timing.device_s += t.elapsed().as_secs_f64();
                let per = host[5][i].len();
                if df.len() != per {
                    return Err(device(
                        format!("{} F_local gradient values, expected {per}", df.len()).into(),
                    ));
                }
                acc[5][i * per..(i + 1) * per].copy_from_slice(&df);
            }
        }
        // The batch's mean, summed on the device.
        let t = Instant::now();
        let mut device_grads = rh.renderer_grads().map_err(device)?;
        for (k, _) in &mut device_grads {
            *k = format!("upsampler.{k}");
        }
        if let Graph::Lift { .. } = graph {
            device_grads.extend(rh.lifting_grads().map_err(device)?);
            if dpt_here {
                device_grads.extend(rh.dpt_grads().map_err(device)?);
            }
        }
        timing.device_s += t.elapsed().as_secs_f64();

        // The reconstruction's backward: d(sum_k <a_k, g_k>) / dθ carries the returned
        // gradients g_k into the networks; the lifting term adds its own (here, unless the
        // device's lifted Gaussians already carried it).
        let t_back = Instant::now();
        let mut surrogate = Tensor::zeros((), DType::F32, &Device::Cpu)?;
        for (t, gk) in attrs.iter().zip(acc) {
            let Some(t) = t else { continue };
            let gk = Tensor::from_vec(gk, t.dims(), t.device())?.to_dtype(t.dtype())?;
            surrogate = (surrogate + (*t * gk)?.sum_all()?.to_dtype(DType::F32)?)?;
        }
        let point = match (&graph, self.losses.cfg.lifting) {
            (_, false) => None,
            (Graph::Lift { .. }, true) => Some(point_sum / b as f64),
            (Graph::Whole { avatar, .. }, true) => {
                let p = lifting_loss(&avatar.lifted_xyz, &batch.target_vertices)?;
                let v = p.to_dtype(DType::F64)?.to_scalar::<f64>()?;
                surrogate = (surrogate + p.to_dtype(DType::F32)?)?;
                Some(v)
            }
        };
        let mut grads = surrogate.backward()?;
        for (name, v) in device_grads {
            let var = vars.get(&name).ok_or_else(|| {
                device(format!("a gradient of {name}, which the model does not train").into())
            })?;
            let t = var.as_tensor();
            if v.len() != t.elem_count() {
                return Err(device(
                    format!(
                        "{} gradient values for {name} of {}",
                        v.len(),
                        t.elem_count()
                    )
                    .into(),
                ));
            }
            grads.insert(
                t,
                Tensor::from_vec(v, t.dims(), t.device())?.to_dtype(t.dtype())?,
            );
        }
        timing.backward_s = t_back.elapsed().as_secs_f64();
        timing.host_s = t_start.elapsed().as_secs_f64()
            - timing.reconstruct_s
            - timing.device_s
            - timing.backward_s;
        let b = b as f64;
        let (img, box_l1) = (img / b, box_l1 / b);
        let percep = percep.map(|_| percep_sum / b);
        let loss = img + box_l1 + percep.unwrap_or(0.0) + point.unwrap_or(0.0);
        Ok((
            StepTerms {
                loss,
                img,
                box_l1,
                percep,
                point,
            },
            Some(grads),
            timing,
        ))
    }

    /// Replaces each gradient by its mean over the ranks (every rank holds the same
    /// parameters, so the flattened gradients line up in name order).
    fn average_gradients(
        &self,
        vars: &[(String, Var)],
        grads: &mut candle_core::backprop::GradStore,
    ) -> RunResult<()> {
        let c = &self.collective;
        let mut flat: Vec<f32> = Vec::new();
        let mut have = Vec::with_capacity(vars.len());
        for (_, v) in vars {
            match grads.get(v.as_tensor()) {
                Some(g) => {
                    flat.extend(g.flatten_all()?.to_dtype(DType::F32)?.to_vec1::<f32>()?);
                    have.push(true);
                }
                None => have.push(false),
            }
        }
        // The same layout on every rank: sum(n)^2 = size sum(n^2) only when all n are equal.
        let n = flat.len() as f64;
        let mut sums = [n, n * n];
        c.sum_f64(&mut sums)?;
        if sums[0] * sums[0] != c.size() as f64 * sums[1] {
            return Err(RunError::Ranks {
                rank: c.rank(),
                size: c.size(),
                reason: "the ranks' gradients differ in size (different models?)".into(),
            });
        }
        c.sum_f32(&mut flat)?;
        let scale = 1.0 / c.size() as f64;
        let mut at = 0;
        for ((_, v), h) in vars.iter().zip(have) {
            if !h {
                continue;
            }
            let t = v.as_tensor();
            let k = t.elem_count();
            let g = Tensor::from_slice(&flat[at..at + k], t.dims(), t.device())?
                .affine(scale, 0.0)?
                .to_dtype(t.dtype())?;
            grads.insert(t, g);
            at += k;
        }
        Ok(())
    }

    /// Restores a state from a checkpoint's tensors (`model`, `optimizer`) at step `step`.
    pub fn restore(
        cfg: TrainConfig,
        model: HashMap<String, Tensor>,
        optimizer: &HashMap<String, Tensor>,
        step: u64,
        skipped_steps: u64,
        percep: Option<PerceptualLoss>,
        device: &Device,
    ) -> RunResult<Self> {
        let mut s = Self::new(cfg, Some(model), percep, device)?;
        s.adam.load_state(optimizer)?;
        s.step = step;
        s.skipped_steps = skipped_steps;
        Ok(s)
    }

    /// The trainable parameters by checkpoint key.
    pub fn vars(&self) -> RunResult<Vec<(String, Var)>> {
        named_vars(&self.varmap)
    }

    /// Makes the loss of 0-based step `step` NaN, as a numerical blow-up would: exercises the
    /// NaN guard (tests, debugging).
    pub fn poison_step(&mut self, step: u64) {
        self.poisoned.insert(step);
    }

    /// The seed of the renderer noise at 0-based step `step`.
    pub fn noise_seed(&self, step: u64) -> u64 {
        mix(mix(self.cfg.train.seed, SALT_NOISE), step)
    }

    /// The loss terms of this state's next step on `batch` and, when the loss is finite, every
    /// trained parameter's gradient (this rank's, before any averaging over ranks); changes
    /// nothing. [`Self::train_step`] is this, the ranks' averaging, the NaN guard and Adam.
    pub fn forward_backward(
        &mut self,
        batch: &BatchTensors,
    ) -> RunResult<(StepTerms, Option<GradStore>)> {
        // This rank's samples sit at rank x share in the step's whole batch.
        let first = self.collective.rank() * batch.source_image.dim(0)?;
        let seed = self.noise_seed(self.step);
        let ranks = self.collective.size();
        let poisoned = self.poisoned.contains(&self.step);
        let (terms, grads) = match self.render_half.take() {
            Some(mut rh) => {
                let r = self.split_forward_backward(rh.as_mut(), batch, seed, first);
                self.render_half = Some(rh);
                let (terms, grads, timing) = r?;
                self.last_split = Some(timing);
                (terms, grads.filter(|_| !poisoned))
            }
            None => {
                let noise = if ranks > 1 {
                    Noise::SeededFrom { seed, first }
                } else {
                    Noise::Seeded(seed)
                };
                let out = self.model.train_forward(
                    &batch.source_image,
                    &batch.source_transform,
                    &batch.target_vertices,
                    &batch.target_transform,
                    noise,
                )?;
                let t = self.losses.compute(&LossInputs {
                    coarse: &out.coarse,
                    fine: &out.fine,
                    gt: &batch.target_image,
                    bbox: &batch.bbox,
                    lifted: &out.avatar.lifted_xyz,
                    targets: &batch.target_vertices,
                })?;
                let grads = if t.total.value.is_finite() && !poisoned {
                    Some(t.total.tensor.backward()?)
                } else {
                    None
                };
                let values = StepTerms {
                    loss: t.total.value,
                    img: t.img.value,
                    box_l1: t.box_l1.value,
                    percep: t.percep.as_ref().map(|t| t.value),
                    point: t.point.as_ref().map(|t| t.value),
                };
                (values, grads)
            }
        };
        Ok((terms, grads))
    }

    /// One optimisation step on `batch` (which must be the batch of step `self.step`).
    pub fn train_step(&mut self, batch: &BatchTensors) -> RunResult<StepReport> {
        let t0 = Instant::now();
        let step = self.step;
        let adam_cfg = self.adam.config();
        let lr = adam_cfg.lr * adam_cfg.factor(self.adam.schedule_step());
        let ranks = self.collective.size();
        let (terms, grads) = self.forward_backward(batch)?;
        let poisoned = self.poisoned.contains(&step);
        let StepTerms {
            mut loss,
            mut img,
            mut box_l1,
            mut percep,
            mut point,
        } = terms;
        if poisoned {
            loss = f64::NAN;
        }
        if ranks > 1 {
            // The step's loss is the mean over the whole batch: the ranks' means averaged (a
            // NaN on any rank makes every rank skip the step).
            let mut v = [
                loss,
                img,
                box_l1,
                percep.unwrap_or(0.0),
                point.unwrap_or(0.0),
            ];
            self.collective.sum_f64(&mut v)?;
            let m = v.map(|x| x / ranks as f64);
            (loss, img, box_l1) = (m[0], m[1], m[2]);
            percep = percep.map(|_| m[3]);
            point = point.map(|_| m[4]);
        }
        let mut report = StepReport {
            step: step + 1,
            loss,
            img,
            box_l1,
            percep,
            point,
            lr,
            grad_norm: f64::NAN,
            skipped: None,
            no_grad: Vec::new(),
            seconds: 0.0,
        };
        if let (true, Some(mut grads)) = (loss.is_finite(), grads) {
            let mut vars = self.vars()?;
            vars.sort_by(|a, b| a.0.cmp(&b.0));
            if ranks > 1 {
                self.average_gradients(&vars, &mut grads)?;
            }
            let mut sums = Vec::with_capacity(vars.len());
            for (name, v) in &vars {
                match grads.get(v.as_tensor()) {
                    Some(g) => sums.push(g.to_dtype(DType::F64)?.sqr()?.sum_all()?),
                    None => report.no_grad.push(name.clone()),
                }
            }
            let sq = if sums.is_empty() {
                0.0
            } else {
                Tensor::stack(&sums, 0)?.sum_all()?.to_scalar::<f64>()?
            };
            report.grad_norm = sq.sqrt();
            if sq.is_finite() {
                self.adam.step(&grads)?;
            } else {
                let mut bad = Vec::new();
                for ((name, _), s) in vars
                    .iter()
                    .filter(|(n, _)| !report.no_grad.contains(n))
                    .zip(&sums)
                {
                    if !s.to_scalar::<f64>()?.is_finite() {
                        bad.push(name.clone());
                    }
                }
                let shown = bad.iter().take(3).cloned().collect::<Vec<_>>().join(", ");
                report.skipped = Some(format!(
                    "non-finite gradients in {} parameters ({shown}{})",
                    bad.len(),
                    if bad.len() > 3 { ", ..." } else { "" }
                ));
            }
        } else {
            report.skipped = Some(format!("the loss is {loss}"));
        }
        report.no_grad.sort();
        if report.skipped.is_some() {
            self.skipped_steps += 1;
        }
        self.step += 1;
        report.seconds = t0.elapsed().as_secs_f64();
        Ok(report)
    }

    /// Every model weight in the release key layout (trained copies and fixed weights).
    pub fn export(&self) -> RunResult<BTreeMap<String, Tensor>> {
        Ok(export_weights(&self.model, &self.varmap)?)
    }
}

/// Loads a FLAME asset (`None`: the built-in synthetic one, `synthesize(0)`) with all its
/// components, on the host in f32 (samples are built there).
pub fn load_flame(path: Option<&Path>) -> RunResult<FlameModel> {
    let asset = match path {
        Some(p) => FlameAsset::load(p, &LoadOptions::default()).map_err(|e| RunError::Flame {
            what: Some(p.display().to_string()),
            reason: e.to_string(),
        })?,
        None => synthesize(0),
    };
    Ok(FlameModel::from_asset(&asset, &Device::Cpu, DType::F32)?)
}

/// Perceptual-network weights (`percep_loss.*` keys) from a file: the release `.pt`, or
/// safetensors with or without the prefix.
fn read_percep_tensors(path: &Path) -> RunResult<HashMap<String, Tensor>> {
    let w = read_weights(path)?;
    let prefixed = w.tensors.keys().any(|k| k.starts_with(PERCEP_PREFIX));
    let out: HashMap<String, Tensor> = w
        .tensors
        .into_iter()
        .filter_map(|(k, v)| {
            if prefixed {
                k.starts_with(PERCEP_PREFIX).then_some((k, v))
            } else {
                Some((format!("{PERCEP_PREFIX}{k}"), v))
            }
        })
        .collect();
    if out.is_empty() {
        return Err(RunError::Checkpoint {
            path: path.to_owned(),
            reason: "holds no perceptual-network weights".into(),
        });
    }
    Ok(out)
}

/// Summary of [`Run::train`].
#[derive(Debug, Clone)]
pub struct RunSummary {
    /// 0-based step the call started at, and the step count reached.
    pub first: u64,
    pub last: u64,
    pub skipped_steps: u64,
    pub seconds: f64,
    /// Ended early by [`Monitor::stop_requested`] (a checkpoint was written).
    pub stopped: bool,
    pub last_loss: Option<f64>,
    pub last_validation: Option<EvalReport>,
}

/// A training run with its folder (see the module docs).
pub struct Run {
    pub state: TrainState,
    dir: PathBuf,
    device: Device,
    source: Arc<SampleSource>,
    sampler: Arc<PairSampler>,
    val_pairs: Vec<Pair>,
    /// `percep_loss.*` tensors, saved in checkpoints so a resume needs no other file.
    percep_tensors: HashMap<String, Tensor>,
    metrics: Vec<String>,
    warned_no_grad: bool,
    collective: Arc<dyn Collective>,
}

impl std::fmt::Debug for Run {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Run")
            .field("dir", &self.dir)
            .field("state", &self.state)
            .finish()
    }
}

/// Everything a run needs besides the state, checked before anything is written.
struct Prepared {
    source: Arc<SampleSource>,
    sampler: Arc<PairSampler>,
    val_pairs: Vec<Pair>,
}

fn prepare(
    cfg: &TrainConfig,
    first_step: u64,
    collective: &dyn Collective,
    monitor: &dyn Monitor,
) -> RunResult<Prepared> {
    let dir = cfg
        .data
        .dir
        .as_deref()
        .ok_or_else(|| config_err(None, "no dataset: pass --data DIR (or set [data] dir)"))?;
    let dataset = Dataset::open(dir)?;
    let (mut sampler, single) = PairSampler::new(
        &dataset.splits().train,
        cfg.train.seed,
        cfg.train.batch,
        cfg.data.cross_identity,
    )?;
    sampler.shard(collective.rank(), collective.size())?;
    if single > 0 {
        monitor.warn(&format!(
            "{single} videos of the train split have a single frame and form no pair; left out"
        ));
    }
    let flame = load_flame(cfg.data.flame.as_deref())?;
    if flame.n_vertices != cfg.model.n_vertices {
        return Err(RunError::Flame {
            what: cfg.data.flame.as_ref().map(|p| p.display().to_string()),
            reason: format!(
                "{} vertices, the model expects {}",
                flame.n_vertices, cfg.model.n_vertices
            ),
        });
    }
    // Codes longer than the FLAME asset takes would fail mid-run: check every record now.
    let (ns, ne) = (flame.config.n_shape, flame.config.n_exp);
    let splits = dataset.splits();
    for (split, names) in splits.splits() {
        for name in names {
            let r = dataset.record(name)?;
            for (field, len, max) in [
                ("shapecode", r.shapecode.len(), ns),
                ("expcode", r.expcode.len(), ne),
                ("posecode", r.posecode.len(), 6),
                ("eyecode", r.eyecode.len(), 6),
            ] {
                if len > max {
                    return Err(RunError::Sample {
                        dir: dir.to_owned(),
                        frame: name.clone(),
                        reason: format!(
                            "`{field}` has {len} values, the FLAME asset takes {max} (split `{split}`)"
                        ),
                    });
                }
            }
        }
    }
    let val_split = match cfg.val.split.as_str() {
        "train" => &splits.train,
        "test" => &splits.test,
        _ => &splits.val,
    };
    let val_pairs = eval_pairs(val_split, Some(cfg.val.frames));
    if cfg.val.every > 0 && val_pairs.is_empty() {
        monitor.warn(&format!(
            "the `{}` split has no pair (a video with two or more frames): no validation",
            cfg.val.split
        ));
    }
    let source = Arc::new(SampleSource::new(
        Arc::new(dataset),
        Arc::new(flame),
        cfg.model.image_size,
    ));
    if cfg.data.check_images {
        use rayon::prelude::*;
        let mut names: Vec<&String> = splits_names(&source.dataset);
        names.sort();
        names.dedup();
        names
            .par_iter()
            .try_for_each(|n| source.image(n).map(|_| ()))?;
    }
    // The first batch: a broken first sample fails before the run folder is touched.
    source.load_batch(first_step, &sampler.pairs(first_step))?;
    Ok(Prepared {
        source,
        sampler: Arc::new(sampler),
        val_pairs,
    })
}

fn splits_names(d: &Dataset) -> Vec<&String> {
    let s = d.splits();
    s.train.iter().chain(&s.val).chain(&s.test).collect()
}

/// The `percep_loss.*` tensors and the loss built from them, per the configuration: an
/// explicit `[loss] percep` file, else the `init` weights when they carry them.
fn percep_setup(
    cfg: &TrainConfig,
    init: Option<&HashMap<String, Tensor>>,
    device: &Device,
    monitor: &dyn Monitor,
) -> RunResult<(HashMap<String, Tensor>, Option<PerceptualLoss>)> {
    if cfg.loss.percep_weight == 0.0 {
        return Ok((HashMap::new(), None));
    }
    let tensors = match (&cfg.loss.percep, init) {
        (Some(p), _) => read_percep_tensors(p)?,
        (None, Some(init)) => init
            .iter()
            .filter(|(k, _)| k.starts_with(PERCEP_PREFIX))
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect(),
        (None, None) => HashMap::new(),
    };
    let loss = PerceptualLoss::from_tensors(&tensors, DType::F32, device)?;
    if loss.is_none() {
        monitor.warn(
            "no perceptual-network weights (percep_loss.*: pass --percep GAGAvatar.pt, or --init \
             a file that has them): the perceptual term is off",
        );
    }
    Ok((tensors, loss))
}

fn remove_if_exists(path: &Path) -> RunResult<()> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(io_err(path, "cannot remove")(e)),
        _ => Ok(()),
    }
}

/// Every rank learns whether every rank got its run: a rank whose own start failed returns
/// its error; the others stop too, naming it (so none waits for a partner that is gone).
fn agree(collective: &dyn Collective, run: RunResult<Run>) -> RunResult<Run> {
    if collective.size() == 1 {
        return run;
    }
    let all = collective.all_ok(run.is_ok())?;
    match run {
        Ok(r) if all => Ok(r),
        Ok(_) => Err(RunError::Ranks {
            rank: collective.rank(),
            size: collective.size(),
            reason: "another rank could not start the run (its error is printed by it)".into(),
        }),
        Err(e) => Err(e),
    }
}

/// The `step` field of a metrics line.
fn line_step(line: &str) -> Option<u64> {
    serde_json::from_str::<serde_json::Value>(line)
        .ok()?
        .get("step")?
        .as_u64()
}

impl Run {
    /// Starts a new run in `dir` (created; must not hold a run unless `overwrite`, which
    /// replaces the run files there). Everything that can be checked is checked before
    /// anything is written.
    pub fn create(
        cfg: TrainConfig,
        dir: &Path,
        overwrite: bool,
        device: &Device,
        monitor: &dyn Monitor,
    ) -> RunResult<Self> {
        Self::create_with(cfg, dir, overwrite, device, monitor, Arc::new(Single))
    }

    /// [`Run::create`] as one rank of a data-parallel run: every rank checks and prepares,
    /// rank 0 alone writes the folder, and all start only if all could.
    pub fn create_with(
        cfg: TrainConfig,
        dir: &Path,
        overwrite: bool,
        device: &Device,
        monitor: &dyn Monitor,
        collective: Arc<dyn Collective>,
    ) -> RunResult<Self> {
        let run = Self::create_rank(cfg, dir, overwrite, device, monitor, collective.clone());
        agree(&*collective, run)
    }

    fn create_rank(
        mut cfg: TrainConfig,
        dir: &Path,
        overwrite: bool,
        device: &Device,
        monitor: &dyn Monitor,
        collective: Arc<dyn Collective>,
    ) -> RunResult<Self> {
        cfg.pin()?;
        cfg.validate().map_err(|e| config_err(None, e))?;
        let writer = collective.rank() == 0;
        if writer && dir.exists() {
            if !dir.is_dir() {
                return Err(ckpt_err(dir, "exists and is not a folder"));
            }
            if !overwrite {
                if dir.join(CHECKPOINT_FILE).exists() {
                    return Err(ckpt_err(
                        dir,
                        "holds a training run: continue it with --resume, or choose another \
                         folder (--force starts over)",
                    ));
                }
                let non_empty = std::fs::read_dir(dir)
                    .map_err(io_err(dir, "cannot read"))?
                    .next()
                    .is_some();
                if non_empty {
                    return Err(ckpt_err(
                        dir,
                        "exists and is not empty (choose a new folder, or --force)",
                    ));
                }
            }
        }
        let prepared = prepare(&cfg, 0, &*collective, monitor)?;
        let init = match &cfg.train.init {
            Some(p) => Some(read_weights(p)?.tensors),
            None => None,
        };
        let (percep_tensors, percep) = percep_setup(&cfg, init.as_ref(), device, monitor)?;
        let mut state = TrainState::new(cfg, init, percep, device)?;
        state.set_collective(collective.clone());
        let run = Self {
            state,
            dir: dir.to_owned(),
            device: device.clone(),
            source: prepared.source,
            sampler: prepared.sampler,
            val_pairs: prepared.val_pairs,
            percep_tensors,
            metrics: Vec::new(),
            warned_no_grad: false,
            collective,
        };
        if !writer {
            return Ok(run);
        }
        std::fs::create_dir_all(dir).map_err(io_err(dir, "cannot create"))?;
        for f in [CHECKPOINT_FILE, WEIGHTS_FILE, METRICS_FILE, CONFIG_FILE] {
            remove_if_exists(&dir.join(f))?;
        }
        // A replaced run's validation grids would mix with the new ones.
        if let Ok(entries) = std::fs::read_dir(dir.join(VAL_DIR)) {
            for e in entries.flatten() {
                let name = e.file_name().to_string_lossy().into_owned();
                if name.starts_with("step_") && name.ends_with(".png") {
                    remove_if_exists(&e.path())?;
                }
            }
        }
        run.write_config()?;
        Ok(run)
    }

    /// Continues the run in `dir` from its checkpoint; `steps` replaces the total step count
    /// (the decay schedule stays the one the run started with).
    pub fn resume(
        dir: &Path,
        steps: Option<u64>,
        device: &Device,
        monitor: &dyn Monitor,
    ) -> RunResult<Self> {
        Self::resume_with(dir, steps, device, monitor, Arc::new(Single))
    }

    /// [`Run::resume`] as one rank of a data-parallel run (any rank count that divides the
    /// batch: the checkpoint does not depend on it).
    pub fn resume_with(
        dir: &Path,
        steps: Option<u64>,
        device: &Device,
        monitor: &dyn Monitor,
        collective: Arc<dyn Collective>,
    ) -> RunResult<Self> {
        let run = Self::resume_rank(dir, steps, device, monitor, collective.clone());
        agree(&*collective, run)
    }

    fn resume_rank(
        dir: &Path,
        steps: Option<u64>,
        device: &Device,
        monitor: &dyn Monitor,
        collective: Arc<dyn Collective>,
    ) -> RunResult<Self> {
        let ck_path = dir.join(CHECKPOINT_FILE);
        if !ck_path.exists() {
            return Err(ckpt_err(
                dir,
                format!(
                    "no {CHECKPOINT_FILE} to resume from (a run writes one every \
                     checkpoint_every steps, at its end and when stopped with Ctrl-C)"
                ),
            ));
        }
        let ck = read_checkpoint(&ck_path, device)?;
        let mut cfg = TrainConfig::from_toml_str(&ck.meta.config_toml, Some(&ck_path))?;
        if cfg.model != ck.model_config {
            return Err(ckpt_err(
                &ck_path,
                "the model configuration in the metadata disagrees with the stored config",
            ));
        }
        if let Ok(text) = std::fs::read_to_string(dir.join(CONFIG_FILE)) {
            if TrainConfig::from_toml_str(&text, None).ok().as_ref() != Some(&cfg) {
                monitor.warn(&format!(
                    "{} differs from the configuration stored in the checkpoint; resuming with \
                     the stored one (a resumed run keeps its settings)",
                    dir.join(CONFIG_FILE).display()
                ));
            }
        }
        if let Some(n) = steps {
            cfg.train.steps = n;
        }
        cfg.pin()?;
        let prepared = prepare(&cfg, ck.meta.step, &*collective, monitor)?;
        let percep = PerceptualLoss::from_tensors(&ck.model, DType::F32, device)?;
        if percep.is_none() && cfg.loss.percep_weight > 0.0 {
            monitor.warn(
                "the checkpoint has no perceptual-network weights: the perceptual term is off",
            );
        }
        let percep_tensors: HashMap<String, Tensor> = ck
            .model
            .iter()
            .filter(|(k, _)| k.starts_with(PERCEP_PREFIX))
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect();
        let mut state = TrainState::restore(
            cfg,
            ck.model,
            &ck.optimizer,
            ck.meta.step,
            ck.meta.skipped_steps,
            percep,
            device,
        )?;
        state.set_collective(collective.clone());
        let metrics = match std::fs::read_to_string(dir.join(METRICS_FILE)) {
            Ok(text) => text
                .lines()
                .filter(|l| line_step(l).is_some_and(|s| s <= ck.meta.step))
                .map(str::to_string)
                .collect(),
            Err(_) => Vec::new(),
        };
        let run = Self {
            state,
            dir: dir.to_owned(),
            device: device.clone(),
            source: prepared.source,
            sampler: prepared.sampler,
            val_pairs: prepared.val_pairs,
            percep_tensors,
            metrics,
            warned_no_grad: true,
            collective,
        };
        if run.collective.rank() == 0 {
            run.write_config()?;
        }
        Ok(run)
    }

    /// This process's rank and the rank count (0 and 1 without data parallelism).
    /// Runs the rendering half of every coming step on `rh` (see
    /// [`TrainState::set_render_half`]); checkpoints, logs and validation are unchanged.
    pub fn set_render_half(&mut self, rh: Box<dyn RenderHalf>) -> RunResult<()> {
        self.state.set_render_half(rh)
    }

    pub fn ranks(&self) -> (usize, usize) {
        (self.collective.rank(), self.collective.size())
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn config(&self) -> &TrainConfig {
        &self.state.cfg
    }

    /// Pairs the loop draws per epoch, and the videos they come from.
    pub fn train_pairs(&self) -> (usize, usize) {
        (self.sampler.len(), self.sampler.videos())
    }

    pub fn val_pairs(&self) -> &[Pair] {
        &self.val_pairs
    }

    fn write_config(&self) -> RunResult<()> {
        let path = self.dir.join(CONFIG_FILE);
        let text = self.state.cfg.to_toml_string()?;
        gagavatar_formats::atomic::write_atomic(&path, text.as_bytes())
            .map_err(|e| ckpt_err(&path, e.detail()))
    }

    fn write_metrics(&self) -> RunResult<()> {
        let path = self.dir.join(METRICS_FILE);
        let mut text = self.metrics.join("\n");
        text.push('\n');
        gagavatar_formats::atomic::write_atomic(&path, text.as_bytes())
            .map_err(|e| ckpt_err(&path, e.detail()))
    }

    /// Writes `checkpoint.safetensors` and `weights.safetensors` for the current step.
    pub fn save_checkpoint(&self) -> RunResult<PathBuf> {
        let s = &self.state;
        let mut model = s.export()?;
        let weights_path = self.dir.join(WEIGHTS_FILE);
        // The FLAME asset the weights go with, so using them with another one can be reported.
        let flame_meta = BTreeMap::from([(
            FLAME_METADATA_KEY.to_string(),
            format!("{:016x}", self.source.flame.asset_fingerprint),
        )]);
        write_tensors_with_metadata(&weights_path, &model, Some(&s.cfg.model), &flame_meta)?;
        for (k, t) in &self.percep_tensors {
            model.insert(k.clone(), t.clone());
        }
        let meta = TrainMeta {
            format: CHECKPOINT_FORMAT,
            step: s.step,
            seed: s.cfg.train.seed,
            skipped_steps: s.skipped_steps,
            config_toml: s.cfg.to_toml_string()?,
        };
        let path = self.dir.join(CHECKPOINT_FILE);
        write_checkpoint(&path, &model, &s.adam.state_tensors()?, &s.cfg.model, &meta)?;
        Ok(path)
    }

    /// Validates on the configured split (no pairs: `None`) and writes the grid PNG.
    pub fn validate(&self) -> RunResult<Option<EvalReport>> {
        if self.val_pairs.is_empty() {
            return Ok(None);
        }
        let cfg = &self.state.cfg;
        let (report, grid) = evaluate(
            &self.state.model,
            &self.source,
            &cfg.val.split,
            &self.val_pairs,
            cfg.val.grid_rows,
            &mut |_, _| true,
        )?;
        if !grid.is_empty() {
            let dir = self.dir.join(VAL_DIR);
            std::fs::create_dir_all(&dir).map_err(io_err(&dir, "cannot create"))?;
            write_grid(
                &dir.join(format!("step_{:07}.png", self.state.step)),
                &grid,
                cfg.model.image_size,
            )?;
        }
        Ok(Some(report))
    }

    /// Trains up to `train.steps` (see the module docs).
    pub fn train(&mut self, monitor: &dyn Monitor) -> RunResult<RunSummary> {
        let t0 = Instant::now();
        let until = self.state.cfg.train.steps;
        let first = self.state.step;
        let mut summary = RunSummary {
            first,
            last: first,
            skipped_steps: self.state.skipped_steps,
            seconds: 0.0,
            stopped: false,
            last_loss: None,
            last_validation: None,
        };
        if first >= until {
            monitor.warn(&format!(
                "the run is already at step {first} of {until}: nothing to train"
            ));
            return Ok(summary);
        }
        let data = &self.state.cfg.data;
        let mut loader = Loader::start(
            self.source.clone(),
            self.sampler.clone(),
            first,
            until,
            data.workers,
            data.prefetch,
        );
        monitor.started(first, until);
        let writer = self.collective.rank() == 0;
        while self.state.step < until {
            // Ranks stop together (a stop request reaches them at different moments).
            let stop = if self.collective.size() > 1 {
                !self.collective.all_ok(!monitor.stop_requested())?
            } else {
                monitor.stop_requested()
            };
            if stop {
                if writer {
                    let path = self.save_checkpoint()?;
                    monitor.checkpoint(self.state.step, &path);
                }
                summary.stopped = true;
                break;
            }
            let batch = loader.next_batch()?;
            if batch.step != self.state.step {
                return Err(RunError::Stopped {
                    step: self.state.step,
                    reason: format!("the loader delivered step {} instead", batch.step),
                });
            }
            let tensors = batch.to_tensors(&self.device)?;
            let report = self.state.train_step(&tensors)?;
            if let Some(why) = &report.skipped {
                monitor.warn(&format!(
                    "step {}: skipped by the NaN guard ({why}); no update",
                    report.step
                ));
            }
            if !self.warned_no_grad && report.skipped.is_none() {
                self.warned_no_grad = true;
                let unexpected: Vec<&String> = report
                    .no_grad
                    .iter()
                    .filter(|k| !gets_no_gradient(&self.state.cfg.model, k))
                    .collect();
                if !unexpected.is_empty() {
                    monitor.warn(&format!(
                        "{} trainable parameters got no gradient: {unexpected:?}",
                        unexpected.len()
                    ));
                }
            }
            let s = report.step;
            let cfg = &self.state.cfg;
            let val_now = cfg.val.every > 0
                && (s % cfg.val.every == 0 || s == until)
                && !self.val_pairs.is_empty();
            let ckpt_now = (cfg.train.checkpoint_every > 0 && s % cfg.train.checkpoint_every == 0)
                || s == until;
            let log_now = s <= cfg.log.every_step_until
                || (cfg.log.every > 0 && s % cfg.log.every == 0)
                || val_now
                || ckpt_now
                || report.skipped.is_some();
            let mut line = json!({
                "step": s,
                "loss": report.loss,
                "img": report.img,
                "box": report.box_l1,
                "lr": report.lr,
                "grad_norm": report.grad_norm,
                "step_s": report.seconds,
                "wall_s": t0.elapsed().as_secs_f64(),
            });
            if let Some(p) = report.percep {
                line["percep"] = json!(p);
            }
            if let Some(p) = report.point {
                line["point"] = json!(p);
            }
            if let Some(why) = &report.skipped {
                line["skipped"] = json!(why);
            }
            if val_now && writer {
                if let Some(v) = self.validate()? {
                    let (f, c) = (v.fine(), v.coarse());
                    line["val_psnr"] = json!(f.psnr);
                    line["val_ssim"] = json!(f.ssim);
                    line["val_psnr_coarse"] = json!(c.psnr);
                    line["val_ssim_coarse"] = json!(c.ssim);
                    monitor.validation(s, &v);
                    summary.last_validation = Some(v);
                }
            }
            if log_now && writer {
                self.metrics.push(line.to_string());
                self.write_metrics()?;
            }
            if ckpt_now && writer {
                let path = self.save_checkpoint()?;
                monitor.checkpoint(s, &path);
            }
            summary.last_loss = Some(report.loss);
            monitor.step(&report);
        }
        summary.last = self.state.step;
        summary.skipped_steps = self.state.skipped_steps;
        summary.seconds = t0.elapsed().as_secs_f64();
        Ok(summary)
    }
}
