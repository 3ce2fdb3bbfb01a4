//! Between images and the model's tensors: RGB images in, cameras as `[B, 3, 4]`, RGB u8
//! frames out.

use candle_core::{DType, Device, Tensor};
use gagavatar_ops::{resize, ResizeMode};

use crate::error::{input_err, Result};

/// An RGB image as `[1, 3, size, size]` in [0, 1], resized (antialiased) when its size differs.
pub fn image_tensor(img: &image::RgbImage, size: usize) -> Result<Tensor> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    if w == 0 || h == 0 {
        return Err(input_err("image", "empty (0 pixels)"));
    }
    let mut planar = vec![0f32; 3 * w * h];
    for (i, px) in img.pixels().enumerate() {
        for c in 0..3 {
            planar[c * w * h + i] = px[c] as f32 / 255.0;
        }
    }
    let t = Tensor::from_vec(planar, (1, 3, h, w), &Device::Cpu)?;
    if h != size || w != size {
        return Ok(resize(&t, size, size, ResizeMode::Antialias)?);
    }
    Ok(t)
}

/// Cameras (3x4 world-to-camera transforms) as `[B, 3, 4]` f32.
pub fn transforms_tensor(tms: &[[[f64; 4]; 3]]) -> Result<Tensor> {
    let flat: Vec<f32> = tms
        .iter()
        .flat_map(|m| m.iter().flatten().map(|&x| x as f32))
        .collect();
    Ok(Tensor::from_vec(flat, (tms.len(), 3, 4), &Device::Cpu)?)
}

/// `[B, 3, H, W]` in [0, 1] -> B interleaved RGB u8 frames (NaN -> 0, so a broken frame shows
/// as black, not as an error).
pub fn to_rgb8(images: &Tensor) -> Result<Vec<Vec<u8>>> {
    let (b, c, h, w) = images.dims4()?;
    if c != 3 {
        return Err(input_err(
            "images",
            format!("expected RGB images, got {c} channels"),
        ));
    }
    let data: Vec<f32> = images.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
    let plane = h * w;
    Ok((0..b)
        .map(|i| {
            let img = &data[i * 3 * plane..(i + 1) * 3 * plane];
            let mut out = vec![0u8; 3 * plane];
            for p in 0..plane {
                for ch in 0..3 {
                    let v = img[ch * plane + p];
                    out[3 * p + ch] = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
                }
            }
            out
        })
        .collect())
}
