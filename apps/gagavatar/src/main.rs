//! The `gagavatar` command line. Each subcommand lives in its own `cmd_*.rs` and stays thin:
//! parsing, progress and file handling here, the work in the library crates.

mod animate;
mod bench_stats;
mod cmd_bench;
mod cmd_bench_dpt_grad;
mod cmd_bench_drive;
mod cmd_bench_reconstruct;
mod cmd_bench_renderer_grad;
mod cmd_bench_serve;
mod cmd_bench_splat_gpu;
mod cmd_demo;
mod cmd_eval;
mod cmd_face;
mod cmd_flame;
mod cmd_model;
mod cmd_orbit;
mod cmd_reenact;
mod cmd_serve;
mod cmd_splat;
mod cmd_synth;
mod cmd_track;
mod cmd_train;
mod cmd_video;
mod device_args;
mod eval_args;
mod procstat;
mod progress;
mod tracking;

use clap::{Parser, Subcommand};

#[derive(Debug, Parser)]
#[command(
    name = "gagavatar",
    version,
    about = "GAGAvatar in Rust: one-shot animatable Gaussian head avatars"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Render a Gaussian scene (safetensors or 3DGS .ply) with a release-style camera.
    Splat(cmd_splat::SplatArgs),
    /// Write the avatar-like demo scene (two lifted planes + head points) and its camera.
    ExampleScene(cmd_splat::ExampleSceneArgs),
    /// FLAME head model utilities.
    #[command(subcommand)]
    Flame(cmd_flame::FlameCmd),
    /// Convert weights between the release `.pt` and safetensors (by extension), checking every key.
    Convert(cmd_model::ConvertArgs),
    /// Write a complete checkpoint of seeded random weights in the release key layout.
    InitWeights(cmd_model::InitWeightsArgs),
    /// Run reconstruct + drive once and write every intermediate tensor (parity checks).
    Dump(cmd_model::DumpArgs),
    /// The first command to run: reenact, orbit and export the shipped demo avatar into ./demo_out.
    Demo(cmd_demo::DemoArgs),
    /// Animate a photo with a driving sequence (release tracked folder or JSON) into a video.
    Reenact(cmd_reenact::ReenactArgs),
    /// Novel views around the reconstructed head, as a video.
    Orbit(cmd_orbit::OrbitArgs),
    /// Write the avatar's Gaussians as a standard 3DGS .ply (plus the feature channels).
    ExportPly(cmd_orbit::ExportPlyArgs),
    /// Read videos as every command does: metadata, frames.
    #[command(subcommand)]
    Video(cmd_video::VideoCmd),
    /// Find faces in a photo: boxes, keypoints, 478 landmarks, and the person matte.
    Face(cmd_face::FaceArgs),
    /// Track a photo, a video or a folder of images into FLAME + camera records (release layout).
    Track(cmd_track::TrackArgs),
    /// Benchmarks of the hot paths on this machine.
    #[command(subcommand)]
    Bench(cmd_bench::BenchCmd),
    /// Generate a synthetic-heads training dataset (release layout) from a FLAME asset.
    SynthData(cmd_synth::SynthDataArgs),
    /// Train a model (a preset or a TOML config) on a dataset, or resume a run.
    Train(cmd_train::TrainArgs),
    /// The paper's evaluation (--mode self|cross|both: PSNR, SSIM, LPIPS, CSIM, AED, APD, AKD),
    /// or without --mode the training validation table (fine, coarse, copy-the-source).
    Eval(cmd_eval::EvalArgs),
    /// Time training steps (forward, loss, backward, Adam) on a synthetic batch.
    TrainBench(cmd_train::TrainBenchArgs),
    /// A local web app and HTTP API: photo in, avatar, sliders, orbit, reenact, .ply.
    Serve(cmd_serve::ServeArgs),
}

/// Two glibc malloc settings for a process whose large tensors are allocated and freed over and
/// over:
/// - One arena. glibc gives each thread that frees memory its own arena and keeps freed blocks
///   per arena, so activations allocated on one thread and freed on another piled up in several
///   arenas: peak RSS for the release model was 1.39 GiB instead of about 1.0 GiB.
/// - Large blocks from the heap, kept after free. By default every block over 32 MiB is a fresh
///   `mmap`, returned with `munmap` when freed, so each activation of the network paid page
///   faults and kernel page zeroing again: 15% of reconstruct time (3.57 -> 3.05-3.26 s at 2
///   threads) and 30% of the dual-lifting generators. Peak RSS is unchanged (1.04 GiB), since
///   the heap reuses the same blocks; memory goes back to the OS when the process exits.
fn tune_malloc() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: called first thing in main, before any other thread exists.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, 1);
        libc::mallopt(libc::M_MMAP_THRESHOLD, MALLOC_HEAP_MAX);
        libc::mallopt(libc::M_TRIM_THRESHOLD, MALLOC_HEAP_MAX);
    }
}

/// Blocks up to this size come from the heap (bigger ones, none in the network, are mapped).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MALLOC_HEAP_MAX: i32 = 1 << 30;

/// Set by the first Ctrl-C; long loops check it and stop with an error, so writers drop and
/// remove their temporary files. A second Ctrl-C exits at once.
static INTERRUPTED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// An error once Ctrl-C was pressed.
/// Whether Ctrl-C was pressed (the library's monitors poll this to cancel).
pub fn interrupted() -> bool {
    INTERRUPTED.load(std::sync::atomic::Ordering::Relaxed)
}

pub fn check_interrupt() -> anyhow::Result<()> {
    if INTERRUPTED.load(std::sync::atomic::Ordering::Relaxed) {
        anyhow::bail!("interrupted (Ctrl-C); no output was written");
    }
    Ok(())
}

fn main() {
    // Before any thread starts (see the function).
    gagavatar_gpu::device::quiet_probe_env();
    tune_malloc();
    let cli = Cli::parse();
    let _ = ctrlc::set_handler(|| {
        if INTERRUPTED.swap(true, std::sync::atomic::Ordering::Relaxed) {
            std::process::exit(130);
        }
        eprintln!("\nstopping after the current step (Ctrl-C again to quit at once)");
    });
    let result = match cli.command {
        Command::Splat(args) => cmd_splat::run_splat(args),
        Command::ExampleScene(args) => cmd_splat::run_example_scene(args),
        Command::Flame(cmd) => cmd_flame::run(cmd),
        Command::Convert(args) => cmd_model::run_convert(args),
        Command::InitWeights(args) => cmd_model::run_init_weights(args),
        Command::Dump(args) => cmd_model::run_dump(args),
        Command::Demo(args) => cmd_demo::run(args),
        Command::Reenact(args) => cmd_reenact::run(args),
        Command::Orbit(args) => cmd_orbit::run_orbit(args),
        Command::ExportPly(args) => cmd_orbit::run_export_ply(args),
        Command::Video(cmd) => cmd_video::run(cmd),
        Command::Face(args) => cmd_face::run(args),
        Command::Track(args) => cmd_track::run(args),
        Command::Bench(cmd) => cmd_bench::run(cmd),
        Command::SynthData(args) => cmd_synth::run(args),
        Command::Train(args) => cmd_train::run_train(args),
        Command::Eval(args) => cmd_eval::run(args),
        Command::TrainBench(args) => cmd_train::run_bench(args),
        Command::Serve(args) => cmd_serve::run(args),
    };
    if let Err(err) = result {
        eprintln!("error: {err:#}");
        std::process::exit(1);
    }
}
