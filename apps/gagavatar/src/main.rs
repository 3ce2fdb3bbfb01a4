//! The `gagavatar` command line. Each subcommand lives in its own `cmd_*.rs` and stays thin:
//! parsing, progress and file handling here, the work in the library crates.

mod cmd_bench;
mod cmd_flame;
mod cmd_model;
mod cmd_splat;

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
    /// Convert the release checkpoint (or any weights) to safetensors, checking every key.
    Convert(cmd_model::ConvertArgs),
    /// Write a complete checkpoint of seeded random weights in the release key layout.
    InitWeights(cmd_model::InitWeightsArgs),
    /// Run reconstruct + drive once and write every intermediate tensor (parity checks).
    Dump(cmd_model::DumpArgs),
    /// Benchmarks of the hot paths on this machine.
    #[command(subcommand)]
    Bench(cmd_bench::BenchCmd),
}

fn main() {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Splat(args) => cmd_splat::run_splat(args),
        Command::ExampleScene(args) => cmd_splat::run_example_scene(args),
        Command::Flame(cmd) => cmd_flame::run(cmd),
        Command::Convert(args) => cmd_model::run_convert(args),
        Command::InitWeights(args) => cmd_model::run_init_weights(args),
        Command::Dump(args) => cmd_model::run_dump(args),
        Command::Bench(cmd) => cmd_bench::run(cmd),
    };
    if let Err(err) = result {
        eprintln!("error: {err:#}");
        std::process::exit(1);
    }
}
