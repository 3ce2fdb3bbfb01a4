//! Times the release-size neural renderer (StyleUNet, 32 x 512 x 512 -> 3 x 512 x 512) on one
//! frame with seeded random weights of the release shapes, stage by stage.
//!
//! `RAYON_NUM_THREADS=2 cargo run --example renderer_timing -p gagavatar-net [runs]`

use std::time::Instant;

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarBuilder};
use gagavatar_net::style_unet::{Noise, StyleUNet};
use gagavatar_net::ModelConfig;

fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Uniform values with the given mean and standard deviation, seeded by the name.
fn uniform(name: &str, n: usize, mean: f64, std: f64) -> Vec<f32> {
    let key = name.bytes().fold(17, |h, b| splitmix(h ^ b as u64));
    (0..n as u64)
        .map(|i| {
            let u = (splitmix(key ^ i.wrapping_mul(0x2545_F491_4F6C_DD1D)) >> 11) as f64
                / (1u64 << 53) as f64;
            (mean + std * 3f64.sqrt() * (2.0 * u - 1.0)) as f32
        })
        .collect()
}

/// Weights of realistic magnitude for whatever shape the modules ask for.
struct RandomWeights;

impl SimpleBackend for RandomWeights {
    fn get(
        &self,
        s: Shape,
        name: &str,
        _: Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let dims = s.dims();
        let (mean, std) = if name.contains("noises.") || name.ends_with("constant_input.weight") {
            (0.0, 1.0)
        } else if name.ends_with("modulation.bias") {
            (1.0, 0.1)
        } else if dims == [1] {
            (0.3, 0.1)
        } else if name.ends_with("bias") {
            (0.0, 0.05)
        } else {
            let fan_in: usize = if dims.len() == 5 {
                dims[2..].iter().product()
            } else {
                dims[1..].iter().product()
            };
            (0.0, (1.0 / fan_in.max(1) as f64).sqrt())
        };
        Tensor::from_vec(uniform(name, s.elem_count(), mean, std), s, dev)?.to_dtype(dtype)
    }
    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("no shape for {name}")
    }
    fn contains_tensor(&self, _: &str) -> bool {
        true
    }
}

/// CPU seconds (user + system, all threads) this process has used, from `/proc/self/stat`;
/// under contention for the cores it tracks the work better than the wall clock. 0 elsewhere.
fn cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let Some(rest) = stat.rsplit(')').next() else {
        return 0.0;
    };
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // USER_HZ is 100 on Linux.
    (ticks(11) + ticks(12)) / 100.0
}

fn main() -> candle_core::Result<()> {
    let runs: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(3);
    let cfg = ModelConfig::release();
    let dev = Device::Cpu;
    let t = Instant::now();
    let vb = VarBuilder::from_backend(Box::new(RandomWeights), DType::F32, dev.clone());
    let net = StyleUNet::new(&cfg, vb.pp("upsampler"))?;
    eprintln!("weights: {:.2} s", t.elapsed().as_secs_f64());
    let s = cfg.image_size;
    let x = Tensor::from_vec(uniform("input", 32 * s * s, 0.5, 0.25), (1, 32, s, s), &dev)?;
    println!(
        "threads (rayon): {}; {} timed runs after one warm-up",
        rayon::current_num_threads(),
        runs
    );
    let mut rows: Vec<[(f64, f64); 4]> = Vec::new();
    for run in 0..=runs {
        let mut marks = vec![(Instant::now(), cpu_seconds())];
        let (feat, skips) = net.down(&x)?;
        marks.push((Instant::now(), cpu_seconds()));
        let code = net.style_code(&feat)?;
        let conditions = net.conditions(&feat, &skips)?;
        marks.push((Instant::now(), cpu_seconds()));
        let image = net.decoder().forward(&code, &conditions, Noise::Fixed)?;
        let out = candle_nn::ops::sigmoid(&image)?;
        marks.push((Instant::now(), cpu_seconds()));
        assert_eq!(out.dims(), &[1, 3, s, s]);
        let span = |a: usize, b: usize| {
            (
                (marks[b].0 - marks[a].0).as_secs_f64(),
                marks[b].1 - marks[a].1,
            )
        };
        if run > 0 {
            rows.push([span(0, 1), span(1, 2), span(2, 3), span(0, 3)]);
        }
    }
    let names = ["U-Net down", "U-Net up + SFT", "decoder + sigmoid", "total"];
    println!(
        "{:>18}   wall ms: median (min..max)     CPU ms (all threads): median",
        ""
    );
    for (i, name) in names.iter().enumerate() {
        let mut v: Vec<f64> = rows.iter().map(|r| r[i].0).collect();
        let mut c: Vec<f64> = rows.iter().map(|r| r[i].1).collect();
        v.sort_by(f64::total_cmp);
        c.sort_by(f64::total_cmp);
        println!(
            "{name:>18}: {:8.1} ({:7.1} .. {:7.1})   {:8.0}",
            v[v.len() / 2] * 1e3,
            v[0] * 1e3,
            v[v.len() - 1] * 1e3,
            c[c.len() / 2] * 1e3
        );
    }
    Ok(())
}
