//! Times one release-size forward of the encoder (DINOv2 ViT-B/14 on 518x518, then the DPT head)
//! on random weights, plus the DPT head's largest convolutions alone.
//!
//! `cargo run -p gagavatar-net --example encoder_speed [runs]`; set `RAYON_NUM_THREADS` to choose
//! the thread count (candle's GEMM and the kernels share the rayon pool).

use std::collections::HashMap;
use std::time::Instant;

use candle_core::{DType, Device, Result, Tensor};
use candle_nn::{VarBuilder, VarMap};
use gagavatar_net::dino::Dinov2;
use gagavatar_net::dpt::DptHead;
use gagavatar_net::ModelConfig;
use gagavatar_ops::{conv2d, Conv2dSpec};

/// CPU seconds (user + system) this process has used, from `/proc/self/stat` (Linux; 0 where
/// unavailable). On a shared machine CPU time is a steadier measure than wall time.
fn cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    // Fields after the parenthesised command name; utime and stime are the 12th and 13th.
    let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else {
        return 0.0;
    };
    let f: Vec<f64> = rest
        .split_whitespace()
        .skip(11)
        .take(2)
        .filter_map(|v| v.parse().ok())
        .collect();
    // Clock ticks; 100 per second on every mainstream Linux configuration.
    f.iter().sum::<f64>() / 100.0
}

/// Best of `runs` (wall, CPU) timings in seconds, after one untimed warm-up run.
fn time<T>(runs: usize, mut f: impl FnMut() -> Result<T>) -> Result<(f64, f64)> {
    f()?;
    let mut best = (f64::INFINITY, f64::INFINITY);
    for _ in 0..runs {
        let (t, c) = (Instant::now(), cpu_seconds());
        f()?;
        let (wall, cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - c);
        if wall < best.0 {
            best = (wall, cpu);
        }
    }
    Ok(best)
}

fn main() -> Result<()> {
    let runs: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(1);
    let dev = Device::Cpu;
    let cfg = ModelConfig::release();
    // First pass: the names and shapes the modules ask for; second: N(0, 0.02^2) weights.
    let shapes: Vec<(String, Vec<usize>)> = {
        let map = VarMap::new();
        let vb = VarBuilder::from_varmap(&map, DType::F32, &dev);
        Dinov2::new(&cfg, vb.pp("base_model.dino_model"))?;
        DptHead::new(&cfg, vb.pp("base_model"))?;
        let data = map
            .data()
            .lock()
            .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
        data.iter()
            .map(|(k, v)| (k.clone(), v.dims().to_vec()))
            .collect()
    };
    let mut weights = HashMap::new();
    for (k, dims) in shapes {
        weights.insert(k, Tensor::randn(0f32, 0.02, dims, &dev)?);
    }
    let vb = VarBuilder::from_tensors(weights, DType::F32, &dev);
    let dino = Dinov2::new(&cfg, vb.pp("base_model.dino_model"))?;
    let head = DptHead::new(&cfg, vb.pp("base_model"))?;
    let s = cfg.dino_size;
    let x = Tensor::randn(0f32, 1.0, (1, 3, s, s), &dev)?;

    let threads = rayon::current_num_threads();
    println!("threads: {threads}");
    let feats = dino.forward(&x)?;
    let (wall, cpu) = time(runs, || dino.forward(&x))?;
    println!("Dinov2 forward (1x3x{s}x{s}): {wall:.3} s wall, {cpu:.2} s CPU");
    let (wall, cpu) = time(runs, || head.forward(&feats, &x))?;
    let p = cfg.plane_size();
    println!("DptHead forward (-> 1x256x{p}x{p}): {wall:.3} s wall, {cpu:.2} s CPU");

    // The head's convolutions by size: 3x3 256 -> 256 at each level, and layer_rn.0.
    let f = cfg.dpt_features;
    let spec = Conv2dSpec {
        stride: 1,
        padding: 1,
    };
    for (cin, side, count, what) in [
        (f, 2 * cfg.dpt_level_size(0), 1, "output_conv"),
        (f, cfg.dpt_level_size(0), 4, "refinenet.3 convs"),
        (f, cfg.dpt_level_size(1), 4, "refinenet.2 convs"),
        (f, cfg.dpt_level_size(2), 4, "refinenet.1 convs"),
        (
            3 + cfg.dpt_channels[0],
            cfg.dpt_level_size(0),
            1,
            "layer_rn.0",
        ),
        (
            3 + cfg.dpt_channels[1],
            cfg.dpt_level_size(1),
            1,
            "layer_rn.1",
        ),
    ] {
        let xi = Tensor::randn(0f32, 1.0, (1, cin, side, side), &dev)?;
        let w = Tensor::randn(0f32, 0.02, (f, cin, 3, 3), &dev)?;
        let (t, _) = time(runs, || conv2d(&xi, &w, None, spec))?;
        let gflop = 2.0 * (side * side * f * cin * 9) as f64 * 1e-9;
        println!(
            "  {what}: {count} x 3x3 {cin}->{f} at {side}x{side}: {:.3} s ({:.1} GFLOP/s)",
            t * count as f64,
            gflop / t
        );
    }
    Ok(())
}
