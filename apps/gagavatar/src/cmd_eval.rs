//! `gagavatar eval`: the paper's evaluation protocol (`--mode self|cross|both`), or without
//! `--mode` the training validation table (`cmd_train::run_eval`).
//!
//! The protocol (README, "Evaluation protocol"): pairs from `gagavatar_metrics::protocol`,
//! each rendered by the model (source shape + driver expression, jaw, eyes and camera), then
//! scored by `gagavatar_metrics::scorer` (realignment, CSIM, AED, APD, AKD) and by the
//! training crate's PSNR / SSIM / LPIPS on the realigned 512 images. Pairs are rendered one
//! after the other (the network uses every thread) and scored in parallel, a batch at a time;
//! after each batch the CSV is rewritten atomically, so a rerun skips the finished pairs.

use std::collections::{BTreeSet, HashMap};
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor};
use gagavatar_data::{group_by_video, Dataset};
use gagavatar_flame::{synthesize, FlameAsset, LoadOptions};
use gagavatar_metrics::report::{self, PairRow};
use gagavatar_metrics::{
    cross_pairs, default_asset_dir, self_pairs, EvalPair, FaceScorer, IdentityModel, IdentityNet,
    Mode, SourceFace,
};
use gagavatar_track::rig::LandmarkRig;
use gagavatar_train::metrics::{psnr_slice, ssim_plane, SsimWindows, LUMA};
use gagavatar_train::pairs::SampleSource;
use gagavatar_train::Lpips;
use image::RgbImage;
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;

use gagavatar_avatar::{Avatar, CpuDrive, Drive, Engine, EngineConfig, FlameSource};

pub use crate::eval_args::EvalArgs;

pub fn run(a: EvalArgs) -> Result<()> {
    if a.mode.is_none() {
        if a.out.is_some() || a.ground_truth_as_result || a.source_as_result || a.arcface.is_some()
        {
            bail!("-o, --arcface, --ground-truth-as-result and --source-as-result belong to the paper's protocol: add --mode self|cross|both");
        }
        return crate::cmd_train::run_eval(a);
    }
    let out = a
        .out
        .clone()
        .ok_or_else(|| anyhow::anyhow!("--mode needs an output folder (-o OUT)"))?;
    let outcome = run_protocol(&a, &out)?;
    print!("{}", report::table(&outcome.rows));
    eprintln!(
        "{} pairs scored now ({} kept from an earlier run); render {:.1} s, metrics {:.1} s \
         wall ({:.1} ms a pair); wrote {}",
        outcome.scored,
        outcome.resumed,
        outcome.render.as_secs_f64(),
        outcome.metrics.as_secs_f64(),
        outcome.metrics_ms_per_pair(),
        out.display()
    );
    Ok(())
}

/// What a protocol run did.
pub struct Outcome {
    pub rows: Vec<PairRow>,
    pub scored: usize,
    pub resumed: usize,
    /// Time rendering (model) and scoring (all metrics, parallel wall time).
    pub render: Duration,
    pub metrics: Duration,
}

impl Outcome {
    pub fn metrics_ms_per_pair(&self) -> f64 {
        self.metrics.as_secs_f64() * 1e3 / self.scored.max(1) as f64
    }
}

fn modes(s: &str) -> Result<Vec<Mode>> {
    Ok(match s {
        "self" => vec![Mode::SelfReenactment],
        "cross" => vec![Mode::Cross],
        "both" => vec![Mode::SelfReenactment, Mode::Cross],
        other => bail!("--mode must be self, cross or both, not `{other}`"),
    })
}

fn load_flame_asset(path: Option<&Path>) -> Result<FlameAsset> {
    match path {
        Some(p) => FlameAsset::load(p, &LoadOptions::default())
            .with_context(|| format!("loading FLAME {}", p.display())),
        None => Ok(synthesize(0)),
    }
}

/// The model side: renders a pair's result through the pipeline library.
struct Renderer {
    engine: Engine,
    source: SampleSource,
    /// The last source's avatar and its drive (pairs are rendered grouped by source).
    avatar: Option<(String, Avatar, CpuDrive)>,
}

fn transform_of(ds: &Dataset, name: &str) -> Result<[[f64; 4]; 3]> {
    ds.record(name)?
        .transform_matrix
        .ok_or_else(|| anyhow::anyhow!("frame `{name}`: the record has no transform_matrix"))
}

impl Renderer {
    fn render(&mut self, pair: &EvalPair) -> Result<RgbImage> {
        let ds = self.source.dataset.clone();
        let size = self.engine.image_size();
        let (avatar, mut drive) = match self.avatar.take() {
            Some((name, av, drive)) if name == pair.source => (av, drive),
            _ => {
                let img = Tensor::from_vec(
                    self.source.image(&pair.source)?,
                    (1, 3, size, size),
                    &Device::Cpu,
                )?;
                let av = self
                    .engine
                    .avatar_from_tensor(&img, ds.record(&pair.source)?)
                    .with_context(|| format!("source frame `{}`", pair.source))?;
                let drive = av.cpu_drive();
                (av, drive)
            }
        };
        // Source identity, driver expression, jaw, eyes (spec section 10), driver camera.
        let what = format!("driver frame `{}`", pair.driver);
        let codes = avatar.codes(ds.record(&pair.driver)?, &what)?;
        let px = drive.render(&codes, &transform_of(&ds, &pair.driver)?)?;
        self.avatar = Some((pair.source.clone(), avatar, drive));
        RgbImage::from_raw(size as u32, size as u32, px)
            .ok_or_else(|| anyhow::anyhow!("the model's image has the wrong size"))
    }
}

fn chw_tensor(img: &RgbImage) -> Result<Tensor> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let t = Tensor::from_vec(img.as_raw().clone(), (h, w, 3), &Device::Cpu)?
        .permute((2, 0, 1))?
        .unsqueeze(0)?
        .to_dtype(candle_core::DType::F32)?;
    Ok((t / 255.0)?)
}

/// PSNR, SSIM (and LPIPS) of the realigned result against the realigned ground truth: the
/// training validation's definitions (PSNR over RGB in [0, 1]; SSIM on luma, 11x11 Gaussian
/// window, reflect padding), computed on the 8-bit images directly.
fn pixel_scores(
    row: &mut PairRow,
    result: &RgbImage,
    gt: &RgbImage,
    lpips: Option<&Lpips>,
) -> Result<()> {
    let (w, h) = (gt.width() as usize, gt.height() as usize);
    if result.dimensions() != gt.dimensions() {
        bail!("realigned images differ in size");
    }
    let unit =
        |img: &RgbImage| -> Vec<f64> { img.as_raw().iter().map(|&v| v as f64 / 255.0).collect() };
    let luma = |img: &RgbImage| -> Vec<f64> {
        img.pixels()
            .map(|p| {
                (LUMA[0] * p[0] as f64 + LUMA[1] * p[1] as f64 + LUMA[2] * p[2] as f64) / 255.0
            })
            .collect()
    };
    row.psnr = Some(psnr_slice(&unit(result), &unit(gt)));
    row.ssim = Some(ssim_plane(
        &luma(result),
        &luma(gt),
        h,
        w,
        SsimWindows::Reflect,
    )?);
    if let Some(net) = lpips {
        row.lpips = net
            .distances(&chw_tensor(result)?, &chw_tensor(gt)?)?
            .first()
            .copied();
    }
    Ok(())
}

/// Runs the protocol into `out` (see the module docs); the CLI's and the benchmark's core.
pub fn run_protocol(a: &EvalArgs, out: &Path) -> Result<Outcome> {
    crate::cmd_train::set_threads(a.threads);
    // Parallelism is over pairs: the face networks run one pair per thread.
    gagavatar_face::pool::set_threads(1);
    let modes = modes(a.mode.as_deref().unwrap_or("self"))?;
    if a.batch == 0 {
        bail!("--batch must be at least 1");
    }
    let dataset = Arc::new(Dataset::open(&a.data)?);
    let splits = dataset.splits();
    let names = match a.split.as_str() {
        "train" => &splits.train,
        "val" => &splits.val,
        "test" => &splits.test,
        other => bail!("--split must be train, val or test, not `{other}`"),
    };
    let videos: Vec<Vec<String>> = group_by_video(names.iter().map(String::as_str))
        .into_values()
        .collect();
    let self_list = self_pairs(&videos, a.pairs, a.seed);
    let mut pairs = Vec::new();
    for m in &modes {
        match m {
            Mode::SelfReenactment => pairs.extend(self_list.iter().cloned()),
            Mode::Cross => {
                let n = a.pairs.unwrap_or(self_list.len().max(1));
                pairs.extend(cross_pairs(&videos, n, a.seed)?)
            }
        }
    }
    if pairs.is_empty() {
        bail!(
            "the `{}` split of {} has no pair (no video with two or more frames)",
            a.split,
            a.data.display()
        );
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let pairs_json = serde_json::to_string_pretty(&serde_json::json!({
        "data": a.data.display().to_string(),
        "split": a.split,
        "seed": a.seed,
        "pairs": pairs,
    }))? + "\n";
    let pairs_path = out.join("pairs.json");
    let csv_path = out.join("scores.csv");
    // A resumed run must score the same pairs; old rows of other pairs would mix two runs.
    let mut rows = report::read_csv(&csv_path)?;
    let wanted: BTreeSet<&EvalPair> = pairs.iter().collect();
    if let Some(r) = rows.iter().find(|r| !wanted.contains(&r.pair)) {
        bail!(
            "{} holds pair {} <- {} ({}) that these settings do not make; use another -o or \
             delete it",
            csv_path.display(),
            r.pair.driver,
            r.pair.source,
            r.pair.mode.name()
        );
    }
    gagavatar_formats::atomic::write_atomic(&pairs_path, pairs_json.as_bytes())?;
    let done: BTreeSet<EvalPair> = rows.iter().map(|r| r.pair.clone()).collect();
    let resumed = done.len();
    let mut todo: Vec<EvalPair> = pairs
        .iter()
        .filter(|p| !done.contains(p))
        .cloned()
        .collect();
    // Grouped by source, so each avatar is reconstructed once per group.
    todo.sort_by(|x, y| (x.mode, &x.source).cmp(&(y.mode, &y.source)));

    let asset = load_flame_asset(a.flame.as_deref())?;
    let rig = LandmarkRig::for_tracking(&asset)?;
    let identity = match &a.arcface {
        Some(p) => IdentityModel::ArcFace(
            gagavatar_metrics::arcface::ArcFace::load(p)
                .with_context(|| format!("loading ArcFace {}", p.display()))?,
        ),
        None => IdentityModel::Dlib(
            IdentityNet::load(&default_asset_dir())
                .context("loading the identity models (assets/identity)")?,
        ),
    };
    let identity_name = identity.name();
    let scorer = FaceScorer::new(identity, rig)?;
    let lpips = a
        .lpips
        .as_deref()
        .map(|p| Lpips::load(p, &Device::Cpu))
        .transpose()?;
    let mut renderer = if a.ground_truth_as_result || a.source_as_result {
        None
    } else {
        let ckpt = a.ckpt.as_deref().ok_or_else(|| {
            anyhow::anyhow!(
                "--ckpt is required (or --ground-truth-as-result / --source-as-result for the \
                 baselines)"
            )
        })?;
        let mut cfg = EngineConfig::new(ckpt);
        cfg.preset = a.preset.clone();
        // Without --flame, eval scores with the built-in synthetic asset (its data's).
        cfg.flame = a
            .flame
            .as_deref()
            .map_or(FlameSource::Synthetic, FlameSource::from_arg);
        let engine = Engine::open(&cfg).map_err(crate::cmd_model::with_flag_hints)?;
        for w in engine.warnings() {
            eprintln!("warning: {w}");
        }
        let size = engine.image_size();
        Some(Renderer {
            source: SampleSource::new(dataset.clone(), Arc::new(engine.flame().clone()), size),
            engine,
            avatar: None,
        })
    };

    let bar = ProgressBar::new(pairs.len() as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "evaluating [{bar:30}] {pos}/{len} pairs, {per_sec}, ETA {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_position(resumed as u64);
    let mut sources: HashMap<String, SourceFace> = HashMap::new();
    let (mut render_t, mut metrics_t) = (Duration::ZERO, Duration::ZERO);
    let mut scored = 0;
    for chunk in todo.chunks(a.batch) {
        crate::check_interrupt()?;
        let t0 = Instant::now();
        let mut jobs = Vec::with_capacity(chunk.len());
        for pair in chunk {
            let reference = dataset.image(&pair.driver)?;
            let result = match renderer.as_mut() {
                Some(r) => r
                    .render(pair)
                    .with_context(|| format!("rendering {} <- {}", pair.driver, pair.source))?,
                None if a.source_as_result => dataset.image(&pair.source)?,
                None => reference.clone(),
            };
            jobs.push((pair, result, reference));
        }
        let t1 = Instant::now();
        render_t += t1 - t0;
        let new_sources: BTreeSet<&String> = chunk
            .iter()
            .map(|p| &p.source)
            .filter(|s| !sources.contains_key(*s))
            .collect();
        let faces: Vec<(String, SourceFace)> = new_sources
            .into_par_iter()
            .map(|s| -> Result<_> {
                let img = dataset.image(s)?;
                Ok((s.clone(), scorer.source(&img)?))
            })
            .collect::<Result<_>>()?;
        sources.extend(faces);
        let new_rows: Vec<PairRow> = jobs
            .par_iter()
            .map(|(pair, result, reference)| -> Result<PairRow> {
                let mut row = PairRow::new((*pair).clone());
                let src = sources
                    .get(&pair.source)
                    .ok_or_else(|| anyhow::anyhow!("source `{}` not prepared", pair.source))?;
                let aligned = scorer
                    .score(src, result, reference, &mut row)
                    .with_context(|| format!("scoring {} <- {}", pair.driver, pair.source))?;
                if pair.mode == Mode::SelfReenactment {
                    pixel_scores(
                        &mut row,
                        &aligned.result.image,
                        &aligned.reference.image,
                        lpips.as_ref(),
                    )?;
                }
                Ok(row)
            })
            .collect::<Result<_>>()?;
        metrics_t += t1.elapsed();
        scored += new_rows.len();
        rows.extend(new_rows);
        report::write_csv(&csv_path, &sorted(&rows, &pairs))?;
        bar.inc(chunk.len() as u64);
    }
    bar.finish_and_clear();
    let rows = sorted(&rows, &pairs);
    report::write_csv(&csv_path, &rows)?;
    let meta = serde_json::json!({
        "data": a.data.display().to_string(),
        "split": a.split,
        "seed": a.seed,
        "ckpt": a.ckpt.as_ref().map(|p| p.display().to_string()),
        "ground_truth_as_result": a.ground_truth_as_result,
        "source_as_result": a.source_as_result,
        "flame": a.flame.as_ref().map(|p| p.display().to_string()).unwrap_or_else(|| "synthetic".into()),
        "lpips": a.lpips.is_some(),
        "identity": identity_name,
        "arcface": a.arcface.as_ref().map(|p| p.display().to_string()),
        "pose_estimator": "gagavatar-track photo fit (FLAME), not the paper's BFM regressor",
        "realign_size": gagavatar_metrics::REALIGN_SIZE,
    });
    let mut text = serde_json::to_string_pretty(&report::summary_json(&rows, meta))?;
    text.push('\n');
    gagavatar_formats::atomic::write_atomic(&out.join("summary.json"), text.as_bytes())?;
    Ok(Outcome {
        rows,
        scored,
        resumed,
        render: render_t,
        metrics: metrics_t,
    })
}

/// Rows in the pair list's order.
fn sorted(rows: &[PairRow], pairs: &[EvalPair]) -> Vec<PairRow> {
    let pos: HashMap<&EvalPair, usize> = pairs.iter().enumerate().map(|(i, p)| (p, i)).collect();
    let mut v = rows.to_vec();
    v.sort_by_key(|r| pos.get(&r.pair).copied().unwrap_or(usize::MAX));
    v
}
