//! Times one training pass of the network (`train_forward` on a synthetic scene, a loss on
//! fine + coarse + lifted points, `backward`) with seeded initial weights; no optimiser step.
//!
//! `cargo run --example train_step_timing -p gagavatar-net [preset] [batch] [runs]`
//! (preset `tiny` by default; `small`; `release` freezes the backbone).

use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use gagavatar_net::style_unet::Noise;
use gagavatar_net::train::trainable_model;
use gagavatar_net::ModelConfig;
use gagavatar_splat::Camera;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let preset = args.get(1).map_or("tiny", String::as_str);
    let batch: usize = args.get(2).map_or(Ok(1), |s| s.parse())?;
    let runs: usize = args.get(3).map_or(Ok(5), |s| s.parse())?;
    let cfg = ModelConfig::preset(preset).ok_or(format!("unknown preset {preset}"))?;
    let dev = Device::Cpu;
    let t0 = Instant::now();
    let (model, map) = trainable_model(&cfg, None, 1, &dev)?;
    let n_vars = map.all_vars().iter().map(|v| v.elem_count()).sum::<usize>();
    eprintln!(
        "{preset}: {n_vars} trained values, backbone frozen: {}, built in {:.2?}",
        cfg.backbone_frozen(),
        t0.elapsed()
    );

    let s = cfg.image_size;
    let image = (Tensor::rand(0f32, 1f32, (batch, 3, s, s), &dev)?).to_dtype(DType::F32)?;
    let tm = |yaw: f64| -> Result<Tensor, Box<dyn std::error::Error>> {
        let m = Camera::look_at_origin_matrix(9.0, yaw, 0.1);
        let flat: Vec<f32> = m.iter().flatten().map(|&v| v as f32).collect();
        let one = Tensor::from_vec(flat, (1, 3, 4), &dev)?;
        Ok(Tensor::cat(&vec![one; batch], 0)?)
    };
    let (source, target) = (tm(0.2)?, tm(-0.1)?);
    let vertices =
        (Tensor::randn(0f32, 0.3, (batch, cfg.n_vertices, 3), &dev)?).clamp(-1f32, 1f32)?;
    let mut times = Vec::new();
    for run in 0..runs {
        let t = Instant::now();
        let out = model.train_forward(
            &image,
            &source,
            &vertices,
            &target,
            Noise::Seeded(run as u64),
        )?;
        let fwd = t.elapsed();
        let loss = ((out.fine.mean_all()? + out.coarse.mean_all()?)?
            + out.avatar.lifted_xyz.sqr()?.mean_all()?)?;
        let grads = loss.backward()?;
        let total = t.elapsed();
        let with_grad = map
            .all_vars()
            .iter()
            .filter(|v| grads.get(v.as_tensor()).is_some())
            .count();
        eprintln!(
            "run {run}: forward {fwd:.2?}, forward + backward {total:.2?} ({with_grad} of {} variables with a gradient)",
            map.all_vars().len()
        );
        times.push(total.as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    if let Some(m) = times.get(times.len() / 2) {
        println!(
            "{preset} batch {batch}: median forward + backward {:.1} ms",
            m * 1e3
        );
    }
    Ok(())
}
