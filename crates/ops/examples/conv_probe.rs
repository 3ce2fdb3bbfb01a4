//! Quick timing probe (min of N runs, robust to a busy machine): `cargo run -p gagavatar-ops
//! --example conv_probe -- [filter] [runs]`.
use candle_core::{Device, Tensor};
use gagavatar_ops::{conv2d_with_algo, Conv2dSpec, ConvAlgo};
use std::time::Instant;

/// (name, cin, cout, k, stride, padding, h, w)
type ConvShape = (
    &'static str,
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
);

const SHAPES: &[ConvShape] = &[
    ("k3_64to32_512", 64, 32, 3, 1, 1, 512, 512),
    ("k3_16to16_512", 16, 16, 3, 1, 1, 512, 512),
    ("k3_32to32_512", 32, 32, 3, 1, 1, 512, 512),
    ("k3_128to128_296", 128, 128, 3, 1, 1, 296, 296),
    ("k3_283to128_296", 283, 128, 3, 1, 1, 296, 296),
    ("k3_256to256_148", 256, 256, 3, 1, 1, 148, 148),
    ("k3_1027to256_19", 1027, 256, 3, 1, 1, 19, 19),
    ("k1_128to41_296", 128, 41, 1, 1, 0, 296, 296),
    ("k3s2_256to256_37", 256, 256, 3, 2, 1, 37, 37),
    ("k3_256to256_37", 256, 256, 3, 1, 1, 37, 37),
    ("k3_256to256_74", 256, 256, 3, 1, 1, 74, 74),
    ("k3_256to256_19", 256, 256, 3, 1, 1, 19, 19),
    ("k3_512to512_8", 512, 512, 3, 1, 1, 8, 8),
    ("k3_512to512_16", 512, 512, 3, 1, 1, 16, 16),
    ("k3_512to512_32", 512, 512, 3, 1, 1, 32, 32),
    ("k3_256to256_64", 256, 256, 3, 1, 1, 64, 64),
    ("k3_128to128_128", 128, 128, 3, 1, 1, 128, 128),
    ("k3_64to64_256", 64, 64, 3, 1, 1, 256, 256),
    ("k3_3to32_512", 3, 32, 3, 1, 1, 512, 512),
];

/// Process CPU time (user + system) in seconds, from /proc (10 ms ticks).
fn cpu_time() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<f64> = after
        .split_whitespace()
        .map(|v| v.parse().unwrap_or(0.0))
        .collect();
    (f.get(11).copied().unwrap_or(0.0) + f.get(12).copied().unwrap_or(0.0)) / 100.0
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let filter = args.get(1).cloned().unwrap_or_default();
    let runs: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(5);
    if args.get(3).map(String::as_str) == Some("resize") {
        return resize(runs);
    }
    if args.get(3).map(String::as_str) == Some("bwd") {
        return backward(&filter, runs);
    }
    let algos: Vec<ConvAlgo> = match args.get(3).map(String::as_str) {
        Some("ours") => vec![ConvAlgo::Gemm, ConvAlgo::Winograd],
        Some("auto") => vec![ConvAlgo::Auto],
        _ => vec![
            ConvAlgo::Candle,
            ConvAlgo::Gemm,
            ConvAlgo::Winograd,
            ConvAlgo::Auto,
        ],
    };
    for &(name, cin, cout, k, stride, padding, h, w) in SHAPES {
        if !name.contains(&filter) {
            continue;
        }
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (1, cin, h, w), &dev).unwrap();
        let wt = (Tensor::randn(0f32, 1.0, (cout, cin, k, k), &dev).unwrap() * 0.05).unwrap();
        let b = Tensor::randn(0f32, 1.0, cout, &dev).unwrap();
        let spec = Conv2dSpec { stride, padding };
        let flops =
            2.0 * (cout * cin * k * k) as f64 * ((h + 2 * padding - k) / stride + 1).pow(2) as f64;
        let mut line = format!("{name:18}");
        for &algo in &algos {
            if algo == ConvAlgo::Winograd && !(k == 3 && stride == 1) {
                line += &format!(" {:>9}: {:>8}", format!("{algo:?}"), "-");
                continue;
            }
            let _ = conv2d_with_algo(&x, &wt, Some(&b), spec, algo).unwrap();
            let mut best = f64::MAX;
            let c0 = cpu_time();
            for _ in 0..runs {
                let t = Instant::now();
                let y = conv2d_with_algo(&x, &wt, Some(&b), spec, algo).unwrap();
                best = best.min(t.elapsed().as_secs_f64());
                drop(y);
            }
            let cpu = (cpu_time() - c0) / runs as f64;
            line += &format!(
                " {:>9}: {:7.1}ms cpu {:7.1}ms ({:4.0} GF/cpu-s)",
                format!("{algo:?}"),
                best * 1e3,
                cpu * 1e3,
                flops / cpu / 1e9
            );
        }
        println!("{line}");
    }
}

fn backward(filter: &str, runs: usize) {
    for &(name, cin, cout, k, stride, padding, h, w) in SHAPES {
        if !name.contains(filter) {
            continue;
        }
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (1, cin, h, w), &dev).unwrap();
        let wt = (Tensor::randn(0f32, 1.0, (cout, cin, k, k), &dev).unwrap() * 0.05).unwrap();
        let b = Tensor::randn(0f32, 1.0, cout, &dev).unwrap();
        let spec = Conv2dSpec { stride, padding };
        let mut line = format!("{name:18} backward");
        let algos = if std::env::var_os("ONLY_AUTO").is_some() {
            vec![ConvAlgo::Auto]
        } else {
            vec![ConvAlgo::Candle, ConvAlgo::Auto]
        };
        for algo in algos {
            let vars = [&x, &wt, &b].map(|t| candle_core::Var::from_tensor(t).unwrap());
            let y = conv2d_with_algo(
                vars[0].as_tensor(),
                vars[1].as_tensor(),
                Some(vars[2].as_tensor()),
                spec,
                algo,
            )
            .unwrap();
            let r = Tensor::randn(0f32, 1.0, y.dims(), &dev).unwrap();
            let loss = (y * r).unwrap().sum_all().unwrap();
            let _ = loss.backward().unwrap();
            let mut best = f64::MAX;
            let c0 = cpu_time();
            for _ in 0..runs {
                let t = Instant::now();
                let g = loss.backward().unwrap();
                best = best.min(t.elapsed().as_secs_f64());
                drop(g);
            }
            let cpu = (cpu_time() - c0) / runs as f64;
            line += &format!(
                " {:>7}: {:7.1}ms cpu {:7.1}ms",
                format!("{algo:?}"),
                best * 1e3,
                cpu * 1e3
            );
        }
        println!("{line}");
    }
}

fn resize(runs: usize) {
    use gagavatar_ops::resample::{resize, resize_dense, ResizeMode};
    let cases = [
        (
            "up 64x256->512 half",
            [1usize, 64, 256, 256],
            512usize,
            ResizeMode::HalfPixel,
        ),
        (
            "down 64x512->256 half",
            [1, 64, 512, 512],
            256,
            ResizeMode::HalfPixel,
        ),
        (
            "up 256x148->296 align",
            [1, 256, 148, 148],
            296,
            ResizeMode::AlignCorners,
        ),
        (
            "aa 3x512->518",
            [1, 3, 512, 512],
            518,
            ResizeMode::Antialias,
        ),
        (
            "aa 3x512->148",
            [1, 3, 512, 512],
            148,
            ResizeMode::Antialias,
        ),
    ];
    for (name, shape, out, mode) in cases {
        let x = Tensor::randn(0f32, 1.0, &shape[..], &Device::Cpu).unwrap();
        let mut line = format!("{name:24}");
        for dense in [true, false] {
            let f = || {
                if dense {
                    resize_dense(&x, out, out, mode).unwrap()
                } else {
                    resize(&x, out, out, mode).unwrap()
                }
            };
            let _ = f();
            let mut best = f64::MAX;
            let c0 = cpu_time();
            for _ in 0..runs {
                let t = Instant::now();
                let y = f();
                best = best.min(t.elapsed().as_secs_f64());
                drop(y);
            }
            let cpu = (cpu_time() - c0) / runs as f64;
            line += &format!(
                " {}: {:7.2}ms cpu {:7.1}ms",
                if dense { "dense" } else { "taps" },
                best * 1e3,
                cpu * 1e3
            );
        }
        println!("{line}");
    }
}
