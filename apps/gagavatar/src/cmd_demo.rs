//! `gagavatar demo`: the first command on a fresh machine. Uses only files the repository ships
//! (`assets/demo/`: the trained demo model, a held-out synthetic identity and a driving sequence)
//! and the built-in synthetic FLAME asset, and writes a reenactment video, an orbit video, a
//! `.ply`, and the tracking of a real public-domain photo with its fit drawn over it into
//! `./demo_out/`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;

use crate::animate::SourceArgs;
use crate::cmd_model::SYNTHETIC_FLAME;
use crate::cmd_orbit::{ExportPlyArgs, ExpressionArgs, OrbitArgs};
use crate::cmd_reenact::ReenactArgs;
use crate::tracking::tracker_for;

#[derive(Debug, Args)]
#[command(
    after_help = "The demo model is the `tiny` preset trained on this CPU on synthetic \
heads (`gagavatar synth-data`); the source identity was held out of training. Outputs: \
demo_out/reenact.mp4 (driver | result), demo_out/orbit.mp4, demo_out/avatar.ply, and the \
tracking of a real public-domain photo (assets/demo/astronaut.jpg): demo_out/astronaut_track/ \
and its fit drawn over it, demo_out/astronaut_overlay.png.\n\n\
Example:\n  gagavatar demo\n  gagavatar demo --assets assets/demo -o demo_out --no-watermark"
)]
pub struct DemoArgs {
    /// Folder with weights.safetensors, source.png, source.json and driver.json.
    #[arg(long)]
    pub assets: Option<PathBuf>,
    /// Output folder.
    #[arg(short, long, default_value = "demo_out")]
    pub output: PathBuf,
    /// Do not draw the "AI-generated" watermark on the videos.
    #[arg(long)]
    pub no_watermark: bool,
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
}

/// What the demo runs: the reenactment, the orbit and the `.ply` export, all from `assets`.
fn steps(a: &DemoArgs, assets: &Path) -> (ReenactArgs, OrbitArgs, ExportPlyArgs) {
    let src = || SourceArgs {
        ckpt: assets.join("weights.safetensors"),
        // The asset the demo weights were trained with (the built-in synthetic one), found by
        // the library as a newcomer's run would.
        flame: None,
        source: assets.join("source.png"),
        source_record: Some(assets.join("source.json")),
        source_key: None,
        preset: None,
        n_shape: 300,
        n_exp: 100,
        fresh_noise: false,
        precision: gagavatar_ops::Precision::F32,
    };
    let reenact = ReenactArgs {
        src: src(),
        device: a.device,
        driver: Some(assets.join("driver.json")),
        output: a.output.join("reenact.mp4"),
        side_by_side: true,
        driver_video: None,
        fps: None,
        start: 0,
        max_frames: None,
        batch: 4,
        no_watermark: a.no_watermark,
    };
    let orbit = OrbitArgs {
        src: src(),
        device: a.device,
        output: a.output.join("orbit.mp4"),
        expression: ExpressionArgs::default(),
        yaw: 35.0,
        pitch: 15.0,
        frames: 75,
        fps: 25.0,
        batch: 4,
        no_watermark: a.no_watermark,
    };
    let ply = ExportPlyArgs {
        src: src(),
        output: a.output.join("avatar.ply"),
        expression: ExpressionArgs::default(),
        device: a.device.device,
    };
    (reenact, orbit, ply)
}

/// `assets/demo` from the working directory, else beside the source tree this binary was built
/// from (so `cargo run -- demo` works from any directory of a checkout).
pub fn find_assets(explicit: Option<&Path>) -> Result<PathBuf> {
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
        "astronaut.jpg",
    ] {
        if !assets.join(f).is_file() {
            bail!("the demo assets in {} lack {f}", assets.display());
        }
    }
    std::fs::create_dir_all(&a.output)
        .with_context(|| format!("creating {}", a.output.display()))?;
    let (reenact, orbit, ply) = steps(&a, &assets);
    eprintln!("1/4 reenactment (driver | result)");
    crate::cmd_reenact::run(reenact)?;
    eprintln!("2/4 orbit");
    crate::cmd_orbit::run_orbit(orbit)?;
    eprintln!("3/4 Gaussians as .ply");
    crate::cmd_orbit::run_export_ply(ply)?;
    eprintln!("4/4 tracking a real photo (astronaut.jpg, public domain: NASA via scikit-image)");
    let tracker = tracker_for(Path::new(SYNTHETIC_FLAME))?;
    let photo = tracker
        .track_photo_file(
            &assets.join("astronaut.jpg"),
            &a.output.join("astronaut_track"),
            Some(&a.output.join("astronaut_overlay.png")),
        )?
        .photo;
    eprintln!(
        "astronaut: landmark RMS {:.2} px at 512, crop window {:?}",
        photo.frame.fit_rms_px.unwrap_or(f64::NAN),
        photo.frame.window.as_array()
    );
    eprintln!(
        "demo done in {:.1} s: {}/reenact.mp4, orbit.mp4, avatar.ply, astronaut_track/, \
         astronaut_overlay.png",
        t0.elapsed().as_secs_f64(),
        a.output.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        demo: DemoArgs,
    }

    #[test]
    fn no_watermark_reaches_both_videos() {
        for (flag, want) in [(None, false), (Some("--no-watermark"), true)] {
            let argv: Vec<&str> = std::iter::once("demo").chain(flag).collect();
            let a = Cli::try_parse_from(argv).unwrap().demo;
            assert_eq!(a.no_watermark, want);
            let (reenact, orbit, _) = steps(&a, Path::new("assets/demo"));
            assert_eq!((reenact.no_watermark, orbit.no_watermark), (want, want));
        }
    }
}
