//! `gagavatar eval`'s arguments, apart from the command: the protocol (`cmd_eval`) and the
//! training validation table (`cmd_train::run_eval`) both read them.

use std::path::PathBuf;

use clap::Args;

#[derive(Debug, Args)]
#[command(
    after_help = "With --mode: the paper's protocol. Self reenactment: in each video of \
the split the first frame is the source, every other frame the driver and the ground truth; \
scores PSNR, SSIM, LPIPS (with --lpips), CSIM, AED, APD, AKD. Cross reenactment: the source is \
the first frame of one video, the driver a frame of another (seeded pairing, written to \
OUT/pairs.json); scores CSIM, AED, APD. Result and reference are realigned to the same 512 head \
crop first. Writes OUT/scores.csv (one row per pair; a rerun skips the pairs already there), \
OUT/summary.json and prints the table in the paper's column order.\n\nWithout --mode: PSNR and \
SSIM of the fine image, the coarse splatted RGB and the copied source (the training validation \
table).\n\nExamples:\n  gagavatar eval --ckpt GAGAvatar.pt --flame FLAME_with_eye.pt --data \
tracked_test --mode both -o eval_out --pairs 500 --seed 0\n  gagavatar eval \
--ground-truth-as-result --data tracked_test --mode self -o eval_gt\n  gagavatar eval --ckpt \
runs/tiny/weights.safetensors --data data/synth64 --split test"
)]
pub struct EvalArgs {
    /// Model weights (safetensors with their configuration, or GAGAvatar.pt).
    #[arg(long)]
    pub ckpt: Option<PathBuf>,
    /// Dataset folder (release layout, ours, or a tracker output).
    #[arg(long)]
    pub data: PathBuf,
    /// Split: train, val or test.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Architecture when the file does not say (a .pt is the release).
    #[arg(long)]
    pub preset: Option<String>,
    /// FLAME asset; default the built-in synthetic one.
    #[arg(long)]
    pub flame: Option<PathBuf>,
    /// The paper's protocol: self, cross or both.
    #[arg(long)]
    pub mode: Option<String>,
    /// Output folder of the protocol (scores.csv, summary.json, pairs.json).
    #[arg(short, long)]
    pub out: Option<PathBuf>,
    /// At most this many self pairs (a seeded subset); the number of cross pairs (default:
    /// as many as self pairs).
    #[arg(long)]
    pub pairs: Option<usize>,
    /// Seed of the pair selection.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Score the reference itself as the result (no model): the sanity floor of every metric.
    #[arg(long, conflicts_with = "source_as_result")]
    pub ground_truth_as_result: bool,
    /// Score the source photo itself as the result (no model): the copy-the-source baseline
    /// (no motion at all).
    #[arg(long)]
    pub source_as_result: bool,
    /// Pairs rendered, then scored in parallel, per batch (the CSV is written after each).
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// Without --mode: evaluate at most this many pairs.
    #[arg(long)]
    pub limit: Option<usize>,
    /// Without --mode: also write the means and per-pair scores as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Without --mode: also write a PNG of the first pairs (target | coarse | fine).
    #[arg(long)]
    pub grid: Option<PathBuf>,
    /// LPIPS (AlexNet) weights: the `lpips` package's `LPIPS(net='alex')` state dict as
    /// safetensors; adds LPIPS.
    #[arg(long)]
    pub lpips: Option<PathBuf>,
    /// CSIM with this ArcFace ONNX model (e.g. InsightFace's IResNet-50/100 export, weights
    /// inside the file) instead of the shipped dlib ResNet.
    #[arg(long)]
    pub arcface: Option<PathBuf>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
}
