//! Writes the demo source photo at 64, 128, 256, 512 and 1024 pixels with the watermark, to look
//! at the label at every size: `cargo run -p gagavatar-video --example watermark_samples -- OUT_DIR`.

use gagavatar_video::{draw_watermark, watermark_rect, WATERMARK_TEXT};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::path::PathBuf::from(std::env::args().nth(1).ok_or("usage: OUT_DIR")?);
    std::fs::create_dir_all(&out)?;
    let src = image::open(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo/source.png"),
    )?
    .to_rgb8();
    for size in [64u32, 128, 256, 512, 1024] {
        let img = image::imageops::resize(&src, size, size, image::imageops::FilterType::Triangle);
        let (w, h) = (size as usize, size as usize);
        let mut rgb = img.into_raw();
        draw_watermark(&mut rgb, w, h, WATERMARK_TEXT);
        let r = watermark_rect(w, h, WATERMARK_TEXT).ok_or("no label")?;
        let area = (r[2] - r[0]) * (r[3] - r[1]);
        println!(
            "{size}x{size}: box {}x{} at ({}, {}), {:.1}% of the frame",
            r[2] - r[0],
            r[3] - r[1],
            r[0],
            r[1],
            100.0 * area as f64 / (w * h) as f64
        );
        let path = out.join(format!("watermark_{size}.png"));
        image::RgbImage::from_raw(size, size, rgb)
            .ok_or("size")?
            .save(&path)?;
    }
    Ok(())
}
