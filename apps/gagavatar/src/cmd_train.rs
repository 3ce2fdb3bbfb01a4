//! `gagavatar train`, `gagavatar eval`, `gagavatar train-bench`: thin wrappers of
//! `gagavatar_train` (the loop, checkpoints, evaluation live there).

use std::path::PathBuf;
use std::sync::{Arc, OnceLock};

use anyhow::{bail, Context, Result};
use candle_core::{DType, Device};
use clap::Args;
use gagavatar_data::Dataset;
use gagavatar_gpu::grad::render_half::GpuRenderHalf;
use gagavatar_train::collective::{launched_by_mpi, local_rank, Collective, Single};
use gagavatar_train::eval::{evaluate_with, write_grid};
use gagavatar_train::pairs::{eval_pairs, SampleSource};
use gagavatar_train::perceptual::{seeded_weights, PerceptualLoss, PERCEP_PREFIX};
use gagavatar_train::trainer::load_flame;
use gagavatar_train::{EvalReport, Monitor, Run, StepReport, TrainConfig, TrainState};
use indicatif::{ProgressBar, ProgressStyle};

use crate::device_args::{DeviceArgs, DeviceChoice};

#[derive(Debug, Args)]
#[command(
    after_help = "A new run:\n  gagavatar train --preset tiny --data data/synth64 --steps 2000 \
--seed 1 --out runs/tiny\nContinue it (the same losses as if never interrupted):\n  gagavatar \
train --resume runs/tiny --steps 4000\n\n\
Presets are the files crates/train/configs/{tiny,release}.toml (embedded); copy one, edit it \
and pass --config FILE. Command-line values override the file. `release` is the published \
recipe (Adam betas (0, 0.99), lr 1e-4, style_mlp/final_linear at 1e-5, linear decay to 0.1x \
over 200k steps, batch 8, DINOv2 frozen). `tiny` trains a 64x64 model from scratch.\n\n\
FLAME: --flame FILE (FLAME_with_eye.pt or safetensors); default the built-in synthetic FLAME \
asset (seed 0: the one `gagavatar flame synth` writes and `gagavatar synth-data` renders with).\n\n\
The run folder gets config.toml (effective configuration), metrics.jsonl (one JSON object per \
logged step), val/step_*.png (target | coarse | fine), checkpoint.safetensors (resumable: \
weights, optimizer, step, config) and weights.safetensors (the model alone, release key layout: \
`gagavatar reenact --ckpt RUN/weights.safetensors` loads it; `gagavatar convert \
RUN/weights.safetensors GAGAvatar.pt` makes the release's torch checkpoint). Ctrl-C writes a \
checkpoint and stops.\n\n\
Device: --device gpu runs each sample's splatting, neural renderer, image, head-box, perceptual \
and lifting terms and the two lifting generators (forward and backward) on the GPU, f32, and \
with a frozen DINOv2 (the release's) its forward and the DPT head (forward and backward) too; \
the expression generator (forward and backward) and Adam stay on the CPU, so checkpoints are \
the same files and a run moves between devices at any resume. --device auto takes a real GPU when there is one. Under mpirun each rank takes the GPU \
of its local rank.\n\n\
Speed: unless the environment sets it, CANDLE_BARRIER_POOL_SPIN_LIMIT=0 is used (candle's \
element-wise pool otherwise spin-waits between the many small ops of a step: 4x slower tiny \
steps on a busy 2-core machine). CANDLE_NUM_THREADS=1 made tiny steps another ~20% faster there."
)]
pub struct TrainArgs {
    /// Training preset: tiny or release (see below).
    #[arg(long, conflicts_with_all = ["config", "resume"])]
    pub preset: Option<String>,
    /// Training configuration file (TOML), instead of a preset.
    #[arg(long, conflicts_with = "resume")]
    pub config: Option<PathBuf>,
    /// Dataset folder (release layout img_lmdb/ + optim.pkl + dataset.json, or images/ +
    /// records.json).
    #[arg(long, conflicts_with = "resume")]
    pub data: Option<PathBuf>,
    /// Total steps of the run (with --resume: the new total). The learning-rate decay runs
    /// over [optim] decay_steps, or else over the steps the run was started with.
    #[arg(long)]
    pub steps: Option<u64>,
    /// Seed of the initial weights, the pair sampling and the renderer noise.
    #[arg(long, conflicts_with = "resume")]
    pub seed: Option<u64>,
    /// Run folder to create.
    #[arg(long, required_unless_present = "resume", conflicts_with = "resume")]
    pub out: Option<PathBuf>,
    /// Continue the run in this folder from its checkpoint.
    #[arg(long)]
    pub resume: Option<PathBuf>,
    /// Initial weights (GAGAvatar.pt or safetensors); default seeded random weights.
    #[arg(long, conflicts_with = "resume")]
    pub init: Option<PathBuf>,
    /// Perceptual-network weights (percep_loss.*, e.g. GAGAvatar.pt); default: from --init if
    /// it has them, else the perceptual term is off.
    #[arg(long, conflicts_with = "resume")]
    pub percep: Option<PathBuf>,
    /// FLAME asset; default the built-in synthetic one.
    #[arg(long, conflicts_with = "resume")]
    pub flame: Option<PathBuf>,
    /// Pairs per step.
    #[arg(long, conflicts_with = "resume")]
    pub batch: Option<usize>,
    /// Validate every N steps (0: never).
    #[arg(long, conflicts_with = "resume")]
    pub val_every: Option<u64>,
    /// Replace the run files in --out if it already holds a run.
    #[arg(long)]
    pub force: bool,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    #[command(flatten)]
    pub device: DeviceArgs,
}

#[derive(Debug, Args)]
#[command(
    after_help = "Times full training steps (forward of both phases, every loss term, \
backward, NaN check, Adam) on a synthetic batch with seeded weights; data loading is not \
included (it runs on other threads).\n\nExample:\n  gagavatar train-bench --preset tiny --batch 1 \
--runs 10 --threads 2\n  gagavatar train-bench --preset release --batch 8 --runs 3 --device gpu"
)]
pub struct TrainBenchArgs {
    /// Training preset (tiny or release).
    #[arg(long, default_value = "tiny", conflicts_with = "config")]
    pub preset: String,
    #[arg(long)]
    pub config: Option<PathBuf>,
    #[arg(long, default_value_t = 1)]
    pub batch: usize,
    /// Timed steps (after one warm-up step); the median is reported.
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
    /// Perceptual weights to include the perceptual term.
    #[arg(long, conflicts_with = "seeded_percep")]
    pub percep: Option<PathBuf>,
    /// Include the perceptual term with seeded stand-in weights (same cost as the real ones).
    #[arg(long)]
    pub seeded_percep: bool,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// Thread settings; must run before candle or rayon start their pools.
pub fn set_threads(threads: Option<usize>) {
    if let Some(n) = threads {
        std::env::set_var("RAYON_NUM_THREADS", n.to_string());
        std::env::set_var("CANDLE_NUM_THREADS", n.to_string());
    }
    if std::env::var_os("CANDLE_BARRIER_POOL_SPIN_LIMIT").is_none() {
        std::env::set_var("CANDLE_BARRIER_POOL_SPIN_LIMIT", "0");
    }
}

fn thread_note() -> String {
    let env = |k: &str| std::env::var(k).unwrap_or_else(|_| "-".into());
    format!(
        "{} rayon threads (RAYON_NUM_THREADS {}, CANDLE_NUM_THREADS {}, \
         CANDLE_BARRIER_POOL_SPIN_LIMIT {})",
        rayon::current_num_threads(),
        env("RAYON_NUM_THREADS"),
        env("CANDLE_NUM_THREADS"),
        env("CANDLE_BARRIER_POOL_SPIN_LIMIT")
    )
}

/// Progress bar and messages of a run (of rank 0's alone in a data-parallel run).
struct CliMonitor {
    bar: OnceLock<ProgressBar>,
    quiet: bool,
}

impl CliMonitor {
    fn say(&self, msg: String) {
        if self.quiet {
            return;
        }
        match self.bar.get() {
            // A hidden bar (stderr not a terminal) swallows its printed lines.
            Some(b) if !b.is_hidden() => b.println(msg),
            _ => eprintln!("{msg}"),
        }
    }
}

impl Monitor for CliMonitor {
    fn warn(&self, msg: &str) {
        self.say(format!("warning: {msg}"));
    }
    fn started(&self, first: u64, until: u64) {
        if self.quiet {
            return;
        }
        let bar = ProgressBar::new(until);
        bar.set_style(
            ProgressStyle::with_template(
                "{msg} [{bar:30}] {pos}/{len} steps, {per_sec}, elapsed {elapsed}, ETA {eta}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar.set_position(first);
        bar.reset_eta();
        bar.set_message("training");
        let _ = self.bar.set(bar);
    }
    fn step(&self, r: &StepReport) {
        if let Some(b) = self.bar.get() {
            b.set_position(r.step);
            b.set_message(format!("loss {:.4}", r.loss));
        }
    }
    fn validation(&self, step: u64, v: &EvalReport) {
        let (f, c) = (v.fine(), v.coarse());
        self.say(format!(
            "step {step}: {} {} pairs: PSNR {:.2} SSIM {:.4} (coarse {:.2} / {:.4})",
            v.split,
            v.pairs.len(),
            f.psnr,
            f.ssim,
            c.psnr,
            c.ssim
        ));
    }
    fn checkpoint(&self, step: u64, path: &std::path::Path) {
        self.say(format!("step {step}: checkpoint {}", path.display()));
    }
    fn stop_requested(&self) -> bool {
        crate::check_interrupt().is_err()
    }
}

/// The ranks of this run: MPI's when an MPI launcher started the process, else one.
fn collective() -> Result<Arc<dyn Collective>> {
    if !launched_by_mpi() {
        return Ok(Arc::new(Single));
    }
    #[cfg(feature = "mpi")]
    {
        Ok(Arc::new(gagavatar_train::collective::Mpi::init()?))
    }
    #[cfg(not(feature = "mpi"))]
    {
        bail!(
            "started by an MPI launcher, but this gagavatar was built without MPI: build it \
             with `cargo build --release -p gagavatar --features mpi` (needs libopenmpi-dev and \
             libclang-dev)"
        )
    }
}

/// What the lead rank says when the job is torn down, set once before training.
static TEARDOWN_LINE: OnceLock<Vec<u8>> = OnceLock::new();

/// When one rank of an MPI job dies, or `mpirun` itself is interrupted (Ctrl-C reaches only
/// the launcher: OpenMPI starts each rank in its own process group), the launcher ends the
/// ranks with SIGTERM, and they would vanish without a word, some while waiting inside a
/// collective for a dead peer. Instead the lead rank says so in one line (the last checkpoint
/// is whole: it is written under a temporary name and renamed) and every rank exits at once:
/// the launcher kills what is left a moment later, so nothing more could be saved.
/// The handler only writes prepared bytes and calls `_exit`, both async-signal-safe.
#[cfg(unix)]
fn on_job_teardown(lead: bool, dir: &std::path::Path) {
    let line = if lead {
        format!(
            "\nerror: mpirun ended this job (a rank died, or mpirun was interrupted), so \
             training stopped; the last checkpoint in {0} is intact (resume with `gagavatar \
             train --resume {0}`)\n",
            dir.display()
        )
    } else {
        String::new()
    };
    let _ = TEARDOWN_LINE.set(line.into_bytes());
    extern "C" fn handler(_: libc::c_int) {
        if let Some(line) = TEARDOWN_LINE.get() {
            // SAFETY: write(2) on stderr from a live buffer; nothing is allocated or locked.
            unsafe { libc::write(2, line.as_ptr().cast(), line.len()) };
        }
        // SAFETY: ends the process without running destructors or atexit handlers.
        unsafe { libc::_exit(1) }
    }
    // SAFETY: installs a handler that touches only async-signal-safe calls (see above).
    unsafe { libc::signal(libc::SIGTERM, handler as *const () as libc::sighandler_t) };
}

#[cfg(not(unix))]
fn on_job_teardown(_lead: bool, _dir: &std::path::Path) {}

/// The ablation without a neural renderer has no rendering half to move: `--device gpu` is an
/// error, `auto` keeps the CPU.
fn check_device(device: &DeviceArgs, cfg: &TrainConfig) -> Result<()> {
    if cfg.model.no_neural_renderer && device.device == DeviceChoice::Gpu {
        bail!("the no_neural_renderer ablation trains on the CPU only: use --device cpu (or auto)");
    }
    Ok(())
}

/// What `train --device gpu` runs on the GPU for `cfg` (see [`set_render_half`]).
fn gpu_parts(cfg: &gagavatar_net::ModelConfig) -> &'static str {
    if cfg.backbone_frozen() {
        "backbone, DPT head, lifting generators, splatting and renderer"
    } else {
        "splatting, renderer and lifting generators"
    }
}

/// Moves the rendering half of `state`'s steps onto `gpu`.
fn set_render_half(
    state: &mut TrainState,
    gpu: Arc<gagavatar_gpu::Gpu>,
    device: &DeviceArgs,
) -> gagavatar_train::RunResult<()> {
    let describe = gpu.describe();
    let err = |e: gagavatar_gpu::GpuError| gagavatar_train::RunError::Render {
        device: describe.clone(),
        err: Box::new(e),
    };
    let tuning = device
        .tuning(&gpu)
        .map_err(|e| gagavatar_train::RunError::Render {
            device: describe.clone(),
            err: e.into(),
        })?;
    let weights = state.renderer_weights()?;
    let percep = state.percep_weights()?;
    let rh = GpuRenderHalf::new(
        gpu,
        &tuning,
        &state.cfg.model,
        &weights,
        state.cfg.losses().box_size,
        percep.as_ref().map(|(w, f)| (w, *f)),
    )
    .map_err(err)?;
    // A frozen backbone (the release's) runs its forward there too, and so do the lifting
    // generators (their convolutions at plane size are half the reconstruction's work).
    let rh = if state.cfg.model.backbone_frozen() {
        rh.with_backbone(&state.model).map_err(err)?
    } else {
        rh
    };
    let rh = rh
        .with_lifting(&state.cfg.model, &state.lifting_weights()?)
        .map_err(err)?;
    // With the backbone there, the DPT head too: F_local and its gradient stay on the device.
    let rh = if state.cfg.model.backbone_frozen() {
        rh.with_dpt(&state.cfg.model, &state.dpt_weights()?)
            .map_err(err)?
    } else {
        rh
    };
    state.set_render_half(Box::new(rh))
}

pub fn run_train(a: TrainArgs) -> Result<()> {
    set_threads(a.threads);
    let dev = Device::Cpu;
    let ranks = collective()?;
    let lead = ranks.rank() == 0;
    let monitor = CliMonitor {
        bar: OnceLock::new(),
        quiet: !lead,
    };
    let mut run = if let Some(dir) = &a.resume {
        Run::resume_with(dir, a.steps, &dev, &monitor, ranks.clone())?
    } else {
        let out = a.out.as_ref().context("--out RUN is required")?;
        let mut cfg = match (&a.config, &a.preset) {
            (Some(path), _) => TrainConfig::read_with_steps(path, a.steps)?,
            (None, Some(p)) => TrainConfig::preset(p)?,
            (None, None) => bail!("choose --preset tiny|release or --config FILE"),
        };
        if let Some(d) = &a.data {
            cfg.data.dir = Some(d.clone());
        }
        if let Some(n) = a.steps {
            cfg.train.steps = n;
        }
        if let Some(s) = a.seed {
            cfg.train.seed = s;
        }
        if let Some(p) = &a.init {
            cfg.train.init = Some(p.clone());
        }
        if let Some(p) = &a.percep {
            cfg.loss.percep = Some(p.clone());
        }
        if let Some(p) = &a.flame {
            cfg.data.flame = Some(p.clone());
        }
        if let Some(b) = a.batch {
            cfg.train.batch = b;
        }
        if let Some(v) = a.val_every {
            cfg.val.every = v;
        }
        cfg.validate().map_err(anyhow::Error::msg)?;
        // Before the run folder exists.
        check_device(&a.device, &cfg)?;
        Run::create_with(cfg, out, a.force, &dev, &monitor, ranks.clone())?
    };
    if ranks.size() > 1 {
        on_job_teardown(lead, run.dir());
    }
    check_device(&a.device, run.config())?;
    // Each rank on its machine takes its own GPU.
    let device = match run.config().model.no_neural_renderer {
        true => DeviceArgs {
            device: DeviceChoice::Cpu,
            ..a.device
        },
        false => a.device,
    };
    let what = format!("training's {}", gpu_parts(&run.config().model));
    if let Some(gpu) = device.open_for_training_nth(&what, local_rank())? {
        set_render_half(&mut run.state, gpu, &a.device)?;
    }
    if !lead {
        run.train(&monitor)?;
        return Ok(());
    }
    if ranks.size() > 1 {
        eprintln!(
            "data-parallel: {} ranks (MPI), {} pairs each of every step's batch of {}",
            ranks.size(),
            run.config().train.batch / ranks.size(),
            run.config().train.batch
        );
    }
    let cfg = run.config();
    let (pairs, videos) = run.train_pairs();
    eprintln!(
        "{}: model `{}`{}, batch {}, steps {} of {}, {} train targets in {} videos, {} val pairs; \
         {}",
        run.dir().display(),
        cfg.model.name,
        if cfg.model.backbone_frozen() {
            " (backbone frozen)"
        } else {
            ""
        },
        cfg.train.batch,
        run.state.step,
        cfg.train.steps,
        pairs,
        videos,
        run.val_pairs().len(),
        thread_note()
    );
    let summary = run.train(&monitor);
    if let Some(b) = monitor.bar.get() {
        b.finish_and_clear();
    }
    let summary = summary?;
    let steps = summary.last - summary.first;
    eprintln!(
        "{} steps {}..{} in {:.1} s ({:.2} steps/s){}; last loss {}; {} skipped by the NaN \
         guard",
        if summary.stopped {
            "stopped after"
        } else {
            "trained"
        },
        summary.first,
        summary.last,
        summary.seconds,
        steps as f64 / summary.seconds.max(1e-9),
        if summary.stopped {
            format!(
                " (resume with `gagavatar train --resume {}`)",
                run.dir().display()
            )
        } else {
            String::new()
        },
        summary
            .last_loss
            .map_or("-".to_string(), |l| format!("{l:.5}")),
        summary.skipped_steps
    );
    if let Some(v) = &summary.last_validation {
        eprint!("{}", v.table());
    }
    Ok(())
}

/// The release's validation table (`eval` without `--mode`).
pub fn run_eval(a: crate::eval_args::EvalArgs) -> Result<()> {
    set_threads(a.threads);
    let ckpt = a
        .ckpt
        .as_deref()
        .ok_or_else(|| anyhow::anyhow!("--ckpt is required"))?;
    let dev = Device::Cpu;
    let explicit = a
        .preset
        .as_deref()
        .map(crate::cmd_model::preset)
        .transpose()?;
    let model = gagavatar_net::checkpoint::load_model(ckpt, explicit.as_ref(), &dev)
        .with_context(|| format!("loading {}", ckpt.display()))?;
    let flame = load_flame(a.flame.as_deref())?;
    if flame.n_vertices != model.cfg.n_vertices {
        bail!(
            "the FLAME asset has {} vertices, the model expects {}",
            flame.n_vertices,
            model.cfg.n_vertices
        );
    }
    let lpips = a
        .lpips
        .as_deref()
        .map(|p| gagavatar_train::Lpips::load(p, &dev))
        .transpose()?;
    let dataset = Dataset::open(&a.data)?;
    let splits = dataset.splits();
    let names = match a.split.as_str() {
        "train" => &splits.train,
        "val" => &splits.val,
        "test" => &splits.test,
        other => bail!("--split must be train, val or test, not `{other}`"),
    };
    let pairs = eval_pairs(names, a.limit.or(a.pairs));
    if pairs.is_empty() {
        bail!(
            "the `{}` split of {} has no pair (no video with two or more frames)",
            a.split,
            a.data.display()
        );
    }
    if model.cfg.no_neural_renderer {
        eprintln!("note: the model has no neural renderer (ablation): fine = coarse");
    }
    let source = SampleSource::new(
        std::sync::Arc::new(dataset),
        std::sync::Arc::new(flame),
        model.cfg.image_size,
    );
    let bar = ProgressBar::new(pairs.len() as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "evaluating [{bar:30}] {pos}/{len} pairs, {per_sec}, ETA {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let grid_rows = if a.grid.is_some() { 8 } else { 0 };
    let result = evaluate_with(
        &model,
        &source,
        &a.split,
        &pairs,
        grid_rows,
        lpips.as_ref(),
        &mut |done, _| {
            bar.set_position(done as u64);
            crate::check_interrupt().is_ok()
        },
    );
    bar.finish_and_clear();
    let (report, grid) = result?;
    crate::check_interrupt()?;
    print!("{}", report.table());
    if let Some(path) = &a.json {
        let mut text = serde_json::to_string_pretty(&report.to_json())?;
        text.push('\n');
        gagavatar_formats::atomic::write_atomic(path, text.as_bytes())?;
        eprintln!("wrote {}", path.display());
    }
    if let Some(path) = &a.grid {
        write_grid(path, &grid, model.cfg.image_size)?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

pub fn run_bench(a: TrainBenchArgs) -> Result<()> {
    set_threads(a.threads);
    let dev = Device::Cpu;
    let mut cfg = match &a.config {
        Some(p) => TrainConfig::read(p)?,
        None => TrainConfig::preset(&a.preset)?,
    };
    cfg.train.batch = a.batch;
    let percep = if let Some(p) = &a.percep {
        Some(PerceptualLoss::load(p, DType::F32, &dev)?)
    } else if a.seeded_percep {
        let w: std::collections::HashMap<_, _> = seeded_weights(0)?
            .into_iter()
            .map(|(k, v)| (format!("{PERCEP_PREFIX}{k}"), v))
            .collect();
        PerceptualLoss::from_tensors(&w, DType::F32, &dev)?
    } else {
        None
    };
    let gpu = a
        .device
        .open_for_training(&format!("the training step's {}", gpu_parts(&cfg.model)))?;
    let on = gpu.as_ref().map(|g| g.describe());
    let t = gagavatar_train::bench::time_steps_with(&cfg, percep, a.batch, a.runs, &dev, |st| {
        if let Some(g) = gpu.clone() {
            set_render_half(st, g, &a.device)?;
        }
        Ok(())
    })?;
    let ms: Vec<String> = t
        .steps_s
        .iter()
        .map(|s| format!("{:.0}", s * 1e3))
        .collect();
    println!(
        "train step{}, model `{}` batch {}: median {:.1} ms ({:.2} steps/s); steps [{}] ms; \
         {} trained values{}, perceptual term {}; model built in {:.2} s; {}",
        on.map(|d| format!(" ({} on {d})", gpu_parts(&cfg.model)))
            .unwrap_or_default(),
        cfg.model.name,
        a.batch,
        t.median_s() * 1e3,
        1.0 / t.median_s(),
        ms.join(", "),
        t.trained_values,
        if t.backbone_frozen {
            " (backbone frozen)"
        } else {
            ""
        },
        if t.percep { "on" } else { "off" },
        t.build_s,
        thread_note()
    );
    if let Some([rec, dev, host, back]) = t.split_medians() {
        println!(
            "split step medians: reconstruction forward (CPU{}) {:.1} ms, device ({}, \
             image/box/perceptual terms, forward and backward) {:.1} ms, host {:.1} ms, \
             reconstruction backward (CPU) {:.1} ms",
            if cfg.model.backbone_frozen() {
                ": the expression generator; backbone forward on the device"
            } else {
                ""
            },
            rec * 1e3,
            gpu_parts(&cfg.model),
            dev * 1e3,
            host * 1e3,
            back * 1e3
        );
    }
    Ok(())
}
