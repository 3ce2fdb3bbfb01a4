//! Encode time per frame, size and quality of the mp4 / gif / PNG outputs on synthetic frames.
//!
//! `cargo run -p gagavatar-video --example encode_speed [frames]` (default 50). Frames are smooth
//! moving colour waves and a soft disc plus fine texture (a stand-in for hair and skin detail),
//! made before timing starts; times cover `push_rgb` (watermark, colour conversion, encoding,
//! writing) and `finish`.

use std::path::Path;
use std::time::Instant;

use gagavatar_video::mp4::decode_mp4;
use gagavatar_video::{VideoOptions, VideoWriter};

fn frame(width: usize, height: usize, t: usize) -> Vec<u8> {
    let tf = t as f64;
    let mut out = vec![0u8; width * height * 3];
    let (cx, cy) = (width as f64 * (0.45 + 0.01 * tf), height as f64 * 0.5);
    let r0 = width.min(height) as f64 * 0.3;
    for y in 0..height {
        for x in 0..width {
            let (xf, yf) = (x as f64, y as f64);
            let d = ((xf - cx).powi(2) + (yf - cy).powi(2)).sqrt() / r0;
            let disc = 90.0 * (-d * d).exp();
            // Deterministic fine texture that moves with the disc.
            let h = ((x as u32 + t as u32 * 3).wrapping_mul(2_654_435_761)
                ^ (y as u32).wrapping_mul(40_503))
            .wrapping_mul(2_246_822_519);
            let tex = ((h >> 24) as f64 / 255.0 - 0.5) * 16.0 * (-d * d).exp();
            let r = 110.0 + 50.0 * (xf * 0.045 + tf * 0.3).sin() + disc + tex;
            let g = 100.0 + 45.0 * (yf * 0.038 - tf * 0.2).cos() + 0.8 * disc + tex;
            let b = 120.0 + 40.0 * ((xf + yf) * 0.03 + tf * 0.1).sin() + 0.6 * disc + tex;
            let o = (y * width + x) * 3;
            out[o] = r.clamp(0.0, 255.0) as u8;
            out[o + 1] = g.clamp(0.0, 255.0) as u8;
            out[o + 2] = b.clamp(0.0, 255.0) as u8;
        }
    }
    out
}

fn psnr(a: &[u8], b: &[u8]) -> f64 {
    let se: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
        .sum();
    10.0 * (255.0f64 * 255.0 / (se / a.len() as f64)).log10()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let n: usize = std::env::args()
        .nth(1)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(50);
    let dir = std::env::temp_dir().join(format!("gagavatar-video-speed-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    for (w, h) in [(512, 512), (1024, 512)] {
        let frames: Vec<Vec<u8>> = (0..n).map(|t| frame(w, h, t)).collect();
        for name in ["out.mp4", "out.gif", "frames"] {
            let path = dir.join(name);
            let opts = VideoOptions {
                fps: 25.0,
                watermark: false,
            };
            let start = Instant::now();
            let mut v = VideoWriter::create(&path, w, h, opts)?;
            for f in &frames {
                v.push_rgb(f)?;
            }
            v.finish()?;
            let ms = start.elapsed().as_secs_f64() * 1e3 / n as f64;
            let bytes = size_of(&path)?;
            let mut line = format!(
                "{w}x{h} {name:8} {ms:7.2} ms/frame  {:8.1} KiB/frame",
                bytes as f64 / n as f64 / 1024.0
            );
            if name == "out.mp4" {
                let kbps = bytes as f64 * 8.0 / (n as f64 / 25.0) / 1000.0;
                let decoded = decode_mp4(&path)?;
                let mean = decoded
                    .iter()
                    .zip(&frames)
                    .map(|(d, f)| psnr(d, f))
                    .sum::<f64>()
                    / n as f64;
                let worst = decoded
                    .iter()
                    .zip(&frames)
                    .map(|(d, f)| psnr(d, f))
                    .fold(f64::MAX, f64::min);
                line += &format!(
                    "  {kbps:7.0} kbit/s at 25 fps  PSNR mean {mean:.2} dB, worst {worst:.2} dB"
                );
            }
            println!("{line}");
            if path.is_dir() {
                std::fs::remove_dir_all(&path)?;
            } else {
                std::fs::remove_file(&path)?;
            }
        }
    }
    std::fs::remove_dir(&dir)?;
    Ok(())
}

fn size_of(path: &Path) -> std::io::Result<u64> {
    if path.is_dir() {
        let mut total = 0;
        for e in std::fs::read_dir(path)? {
            total += e?.metadata()?.len();
        }
        Ok(total)
    } else {
        Ok(std::fs::metadata(path)?.len())
    }
}
