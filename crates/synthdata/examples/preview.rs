//! Contact sheets of synthetic heads.
//!
//! * Render: `cargo run -p gagavatar-synthdata --example preview -- OUT.png [SIZE] [IDENTITIES]
//!   [FRAMES] [SEED]` (rows are identities, columns frames; env `SHAPE_SIGMA`, `EXP_SIGMA`,
//!   `YAW`, `PITCH` override the sampling).
//! * From a written dataset: `... --example preview -- OUT.png --from DIR [COUNT]` (the first
//!   COUNT frames of `train`, 8 per row, with each record's bbox drawn in green).

use gagavatar_data::Dataset;
use gagavatar_flame::synthesize;
use gagavatar_synthdata::{Generator, SynthConfig};
use image::{Rgb, RgbImage};

type Error = Box<dyn std::error::Error>;

fn main() -> Result<(), Error> {
    let args: Vec<String> = std::env::args().collect();
    let out = args.get(1).ok_or(
        "usage: preview OUT.png [SIZE] [IDENTITIES] [FRAMES] [SEED] | OUT.png --from DIR [COUNT]",
    )?;
    if args.get(2).map(String::as_str) == Some("--from") {
        let dir = args.get(3).ok_or("--from needs a dataset folder")?;
        let count: usize = args.get(4).map(|s| s.parse()).transpose()?.unwrap_or(32);
        return from_dataset(out, dir.as_ref(), count);
    }
    let arg = |i: usize, d: usize| -> Result<usize, Error> {
        Ok(args.get(i).map(|s| s.parse()).transpose()?.unwrap_or(d))
    };
    let (size, ids, frames, seed) = (arg(2, 128)?, arg(3, 6)?, arg(4, 6)?, arg(5, 0)?);
    let asset = synthesize(0);
    let mut config = SynthConfig::new(ids, frames, size, seed as u64);
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<f64>().ok());
    if let Some(v) = env("SHAPE_SIGMA") {
        config.sampling.shape_sigma = v;
    }
    if let Some(v) = env("EXP_SIGMA") {
        config.sampling.exp_sigma = v;
    }
    if let Some(v) = env("YAW") {
        config.sampling.yaw_max_deg = v;
    }
    if let Some(v) = env("PITCH") {
        config.sampling.pitch_max_deg = v;
    }
    let generator = Generator::new(&asset, config)?;
    let mut sheet = RgbImage::new((frames * size) as u32, (ids * size) as u32);
    for i in 0..ids {
        for f in 0..frames {
            let r = generator.render(i, f)?;
            image::imageops::replace(&mut sheet, &r.image, (f * size) as i64, (i * size) as i64);
        }
    }
    sheet.save(out)?;
    Ok(())
}

fn from_dataset(out: &str, dir: &std::path::Path, count: usize) -> Result<(), Error> {
    let ds = Dataset::open(dir)?;
    let names: Vec<String> = ds.splits().train.iter().take(count).cloned().collect();
    let first = ds.image(names.first().ok_or("the dataset has no train frames")?)?;
    let (w, h) = (first.width(), first.height());
    let cols = 8.min(names.len()) as u32;
    let rows = names.len().div_ceil(8) as u32;
    let mut sheet = RgbImage::new(cols * w, rows * h);
    for (k, name) in names.iter().enumerate() {
        let mut img = ds.image(name)?;
        if let Some(b) = ds.record(name)?.bbox {
            let px = |v: f64, n: u32| ((v * n as f64) as u32).min(n - 1);
            let (x0, y0, x1, y1) = (px(b[0], w), px(b[1], h), px(b[2], w), px(b[3], h));
            for x in x0..=x1 {
                img.put_pixel(x, y0, Rgb([0, 255, 0]));
                img.put_pixel(x, y1, Rgb([0, 255, 0]));
            }
            for y in y0..=y1 {
                img.put_pixel(x0, y, Rgb([0, 255, 0]));
                img.put_pixel(x1, y, Rgb([0, 255, 0]));
            }
        }
        let (c, r) = (k as u32 % 8, k as u32 / 8);
        image::imageops::replace(&mut sheet, &img, (c * w) as i64, (r * h) as i64);
    }
    sheet.save(out)?;
    Ok(())
}
