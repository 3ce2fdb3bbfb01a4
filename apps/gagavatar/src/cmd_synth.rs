//! `gagavatar synth-data`: a synthetic-heads training dataset in the release layout.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use gagavatar_flame::{synthesize, FlameAsset, LoadOptions};
use gagavatar_synthdata::{Generator, Progress, SampleConfig, SynthConfig, WriteOptions};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Debug, Args)]
#[command(
    after_help = "Writes `img_lmdb/` (PNG images), `optim.pkl` (float32 records: \
shapecode, expcode, posecode, eyecode, transform_matrix, bbox) and `dataset.json`. Frames are \
named `id<identity>_<frame>`, so each identity is one video; the last --holdout identities go to \
val/test. Each frame has a random expression, jaw, gaze and camera (yaw within 35 degrees, pitch \
within 20, distance about 9, focal 12) on a black background, and the records are exact for the \
images. The same seed and settings give the same bytes on any number of threads.\n\n\
The heads use the built-in synthetic FLAME asset (the one `gagavatar flame synth` writes with \
its default seed 0): a model trained on them needs that asset at inference.\n\n\
Example:\n  gagavatar synth-data -o data/synth128 --identities 200 --frames 8 --size 128"
)]
pub struct SynthDataArgs {
    /// Output folder (must not exist or be empty, unless --force).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Number of people.
    #[arg(long)]
    pub identities: usize,
    /// Frames per person (training pairs need at least 2).
    #[arg(long)]
    pub frames: usize,
    /// Image side in pixels (16..=4096).
    #[arg(long, default_value_t = 512)]
    pub size: usize,
    /// Seed of everything drawn.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Identities held out for val/test [default: 10%, at least 1 when there are 2 or more].
    #[arg(long)]
    pub holdout: Option<usize>,
    /// FLAME asset (`FLAME_with_eye.pt` or a safetensors with its keys) instead of the built-in
    /// synthetic one.
    #[arg(long)]
    pub flame: Option<PathBuf>,
    /// Antialiasing samples per pixel along each axis [default: 4 at 64 px, 3 at 128, else 2].
    #[arg(long)]
    pub supersample: Option<usize>,
    /// Standard deviation of the shape code (first 50 components).
    #[arg(long, default_value_t = SampleConfig::default().shape_sigma)]
    pub shape_sigma: f64,
    /// Standard deviation of the expression code (first 50 components).
    #[arg(long, default_value_t = SampleConfig::default().exp_sigma)]
    pub exp_sigma: f64,
    /// Replace the output folder if it exists and is not empty.
    #[arg(long)]
    pub force: bool,
}

struct Bar(ProgressBar);

impl Progress for Bar {
    fn advance(&self, frames: usize) {
        self.0.inc(frames as u64);
    }
    fn cancelled(&self) -> bool {
        crate::check_interrupt().is_err()
    }
}

pub fn run(a: SynthDataArgs) -> Result<()> {
    let occupied = std::fs::read_dir(&a.output).is_ok_and(|mut d| d.next().is_some());
    if occupied && !a.force {
        bail!(
            "{} exists and is not empty; choose a new folder or pass --force to replace it",
            a.output.display()
        );
    }
    let asset = match &a.flame {
        Some(path) => FlameAsset::load(path, &LoadOptions::default())
            .with_context(|| format!("loading FLAME {}", path.display()))?,
        None => synthesize(0),
    };
    let mut config = SynthConfig::new(a.identities, a.frames, a.size, a.seed);
    config.holdout = a.holdout;
    config.supersample = a.supersample;
    config.sampling.shape_sigma = a.shape_sigma;
    config.sampling.exp_sigma = a.exp_sigma;
    let generator = Generator::new(&asset, config)?;
    let total = a.identities * a.frames;
    let bar = ProgressBar::new(total as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{msg} [{bar:30}] {pos}/{len} frames, {per_sec}, elapsed {elapsed}, ETA {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_message("rendering");
    let progress = Bar(bar);
    let start = Instant::now();
    let options = WriteOptions { overwrite: a.force };
    let summary = generator.write_dataset(&a.output, options, &progress);
    progress.0.finish_and_clear();
    let summary = summary?;
    let secs = start.elapsed().as_secs_f64();
    let s = &summary.splits;
    eprintln!(
        "wrote {} ({} frames of {} identities at {}x{}, {}x{} supersampling; train {}, val {}, \
         test {} frames) in {:.1} s ({:.1} ms/frame on {} threads)",
        summary.dir.display(),
        summary.frames,
        a.identities,
        a.size,
        a.size,
        generator.rasterizer().ss,
        generator.rasterizer().ss,
        s.train.len(),
        s.val.len(),
        s.test.len(),
        secs,
        secs * 1e3 / summary.frames.max(1) as f64,
        rayon::current_num_threads()
    );
    Ok(())
}
