//! The `gagavatar` command line. Each subcommand lives in its own `cmd_*.rs` and stays thin:
//! parsing, progress and file handling here, the work in the library crates.

mod cmd_bench;
mod cmd_flame;
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
        Command::Bench(cmd) => cmd_bench::run(cmd),
    };
    if let Err(err) = result {
        eprintln!("error: {err:#}");
        std::process::exit(1);
    }
}
