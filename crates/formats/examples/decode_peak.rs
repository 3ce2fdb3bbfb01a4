//! Decodes one photo as the CLI does for a model of a given size (downscaled during decoding to
//! fit 4x the model size), to measure peak memory with `/usr/bin/time -v`:
//! `cargo run --release -p gagavatar-formats --example decode_peak -- PHOTO [FIT]`.

use gagavatar_formats::image::{read_image, DecodeOptions};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let path = std::env::args()
        .nth(1)
        .ok_or("usage: decode_peak PHOTO [FIT]")?;
    let fit: u32 = std::env::args()
        .nth(2)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(2048);
    let t0 = std::time::Instant::now();
    let d = read_image(
        path.as_ref(),
        &DecodeOptions {
            min_side: 1,
            fit_within: Some(fit),
        },
    )?;
    println!(
        "{path}: {} {}x{} -> {}x{} in {:.2} s",
        d.kind.name(),
        d.original_width,
        d.original_height,
        d.rgb.width(),
        d.rgb.height(),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
