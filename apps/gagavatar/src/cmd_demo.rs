//! `gagavatar demo`: the first command on a fresh machine. Uses only files the repository ships
//! (`assets/demo/`: the trained demo model, a held-out synthetic identity and a driving sequence)
//! and the built-in synthetic FLAME asset, and writes a reenactment video, an orbit video and a
//! `.ply` into `./demo_out/`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;

use crate::animate::SourceArgs;
use crate::cmd_model::SYNTHETIC_FLAME;
use crate::cmd_orbit::{ExportPlyArgs, ExpressionArgs, OrbitArgs};
use crate::cmd_reenact::ReenactArgs;

#[derive(Debug, Args)]
#[command(
    after_help = "The demo model is the `tiny` preset trained on this CPU on synthetic \
heads (`gagavatar synth-data`); the source identity was held out of training. Outputs: \
demo_out/reenact.mp4 (driver | result), demo_out/orbit.mp4 and demo_out/avatar.ply.\n\n\
Example:\n  gagavatar demo\n  gagavatar demo --assets assets/demo -o demo_out"
)]
pub struct DemoArgs {
    /// Folder with weights.safetensors, source.png, source.json and driver.json.
    #[arg(long)]
    pub assets: Option<PathBuf>,
    /// Output folder.
    #[arg(short, long, default_value = "demo_out")]
    pub output: PathBuf,
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
}

/// `assets/demo` from the working directory, else beside the source tree this binary was built
/// from (so `cargo run -- demo` works from any directory of a checkout).
fn find_assets(explicit: Option<&Path>) -> Result<PathBuf> {
    if let Some(p) = explicit {
        return Ok(p.to_path_buf());
    }
    let local = PathBuf::from("assets/demo");
    if local.join("weights.safetensors").is_file() {
        return Ok(local);
    }
    let built = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo");
    if built.join("weights.safetensors").is_file() {
        return Ok(built);
    }
    bail!("cannot find the demo assets (assets/demo/weights.safetensors); run from the repository root or pass --assets DIR")
}

pub fn run(a: DemoArgs) -> Result<()> {
    let t0 = Instant::now();
    let assets = find_assets(a.assets.as_deref())?;
    for f in [
        "weights.safetensors",
        "source.png",
        "source.json",
        "driver.json",
    ] {
        if !assets.join(f).is_file() {
            bail!("the demo assets in {} lack {f}", assets.display());
        }
    }
    std::fs::create_dir_all(&a.output)
        .with_context(|| format!("creating {}", a.output.display()))?;
    let src = || SourceArgs {
        ckpt: assets.join("weights.safetensors"),
        flame: PathBuf::from(SYNTHETIC_FLAME),
        source: assets.join("source.png"),
        source_record: assets.join("source.json"),
        source_key: None,
        preset: None,
        n_shape: 300,
        n_exp: 100,
        fresh_noise: false,
    };
    eprintln!("1/3 reenactment (driver | result)");
    crate::cmd_reenact::run(ReenactArgs {
        src: src(),
        device: a.device,
        driver: assets.join("driver.json"),
        output: a.output.join("reenact.mp4"),
        side_by_side: true,
        driver_video: None,
        fps: None,
        start: 0,
        max_frames: None,
        batch: 4,
        no_watermark: false,
    })?;
    eprintln!("2/3 orbit");
    crate::cmd_orbit::run_orbit(OrbitArgs {
        src: src(),
        device: a.device,
        output: a.output.join("orbit.mp4"),
        expression: ExpressionArgs::default(),
        yaw: 35.0,
        pitch: 15.0,
        frames: 75,
        fps: 25.0,
        batch: 4,
        no_watermark: false,
    })?;
    eprintln!("3/3 Gaussians as .ply");
    crate::cmd_orbit::run_export_ply(ExportPlyArgs {
        src: src(),
        output: a.output.join("avatar.ply"),
        expression: ExpressionArgs::default(),
    })?;
    eprintln!(
        "demo done in {:.1} s: {}/reenact.mp4, orbit.mp4, avatar.ply",
        t0.elapsed().as_secs_f64(),
        a.output.display()
    );
    Ok(())
}
