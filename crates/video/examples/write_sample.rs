//! Writes a synthetic video and its exact input frames, for checking our files with other
//! decoders (see `tools/ffmpeg_check.py`).
//!
//! `cargo run -p gagavatar-video --example write_sample -- OUT WIDTH HEIGHT FRAMES FPS [--watermark]`
//! writes OUT (format from the extension) and OUT.rgb (the frames pushed, RGB u8, concatenated).

use std::io::Write;
use std::path::Path;

use gagavatar_video::{VideoOptions, VideoWriter};

fn frame(width: usize, height: usize, t: usize) -> Vec<u8> {
    let tf = t as f64;
    let mut out = vec![0u8; width * height * 3];
    for y in 0..height {
        for x in 0..width {
            let (xf, yf) = (x as f64, y as f64);
            let o = (y * width + x) * 3;
            out[o] = (128.0 + 100.0 * (xf * 0.045 + tf * 0.3).sin()) as u8;
            out[o + 1] = (128.0 + 90.0 * (yf * 0.038 - tf * 0.2).cos()) as u8;
            out[o + 2] = (128.0 + 80.0 * ((xf + yf) * 0.03 + tf * 0.1).sin()) as u8;
        }
    }
    out
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 5 {
        return Err("usage: write_sample OUT WIDTH HEIGHT FRAMES FPS [--watermark]".into());
    }
    let out = Path::new(&args[0]);
    let (w, h, n): (usize, usize, usize) = (args[1].parse()?, args[2].parse()?, args[3].parse()?);
    let opts = VideoOptions {
        fps: args[4].parse()?,
        watermark: args.iter().any(|a| a == "--watermark"),
    };
    let mut video = VideoWriter::create(out, w, h, opts)?;
    let mut raw = std::io::BufWriter::new(std::fs::File::create(format!("{}.rgb", args[0]))?);
    for t in 0..n {
        let f = frame(w, h, t);
        raw.write_all(&f)?;
        video.push_rgb(&f)?;
    }
    video.finish()?;
    raw.flush()?;
    Ok(())
}
