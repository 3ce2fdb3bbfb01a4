//! Images stored as LMDB values (or files): PNG / JPEG bytes (decoded by
//! `gagavatar_formats::image`, which reads the format from the bytes), or, as the release's
//! fallback, a `torch.save`d tensor (`[3,H,W]` or `[H,W,3]`, optionally with a leading batch of
//! 1; uint8, or floats in [0, 1]) read by `gagavatar_formats::torch_zip`.

use std::path::Path;

use gagavatar_formats::image::DecodeOptions;
use gagavatar_formats::tensor::RawData;
use gagavatar_formats::FormatError;
use image::RgbImage;

use crate::error::{DataError, Result};

/// Largest width or height accepted (a corrupt header could otherwise ask for gigabytes).
pub use gagavatar_formats::image::MAX_SIDE;

/// Decodes an image value; `path` and `key` only label errors (the LMDB and the entry, or the
/// file and its name).
pub fn decode_image(bytes: &[u8], path: &Path, key: &str) -> Result<RgbImage> {
    let err = |reason: String| DataError::Image {
        path: path.to_owned(),
        key: key.to_owned(),
        reason,
    };
    if bytes.starts_with(b"PK\x03\x04") {
        return decode_torch(bytes).map_err(err);
    }
    match gagavatar_formats::image::decode_image(bytes, key, &DecodeOptions::default()) {
        Ok(img) => Ok(img.rgb),
        Err(FormatError::Image { reason, .. }) => Err(err(reason)),
        Err(other) => Err(err(other.to_string())),
    }
}

/// Reads and decodes an image file (PNG / JPEG / torch tensor).
pub fn read_image_file(path: &Path) -> Result<RgbImage> {
    let bytes = std::fs::read(path).map_err(crate::error::io_err(path, "cannot read"))?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    decode_image(&bytes, path, &name)
}

fn decode_torch(bytes: &[u8]) -> std::result::Result<RgbImage, String> {
    let tensors = gagavatar_formats::torch_zip::read_torch_zip_bytes(bytes, "torch tensor")
        .map_err(|e| e.to_string())?;
    let tensor = match tensors.len() {
        1 => tensors.into_values().next(),
        n => {
            return Err(format!(
                "a torch file with {n} tensors, expected one image tensor"
            ))
        }
    }
    .ok_or("a torch file without a tensor")?;
    let mut shape = tensor.shape.clone();
    if shape.len() == 4 && shape[0] == 1 {
        shape.remove(0);
    }
    let (h, w, chw) = match shape.as_slice() {
        [3, h, w] => (*h, *w, true),
        [h, w, 3] => (*h, *w, false),
        _ => {
            return Err(format!(
                "torch tensor of shape {:?}, expected [3,H,W] or [H,W,3]",
                tensor.shape
            ))
        }
    };
    let (wu, hu) = (u32::try_from(w), u32::try_from(h));
    let (Ok(wu), Ok(hu)) = (wu, hu) else {
        return Err("torch tensor too large for an image".into());
    };
    if wu == 0 || hu == 0 || wu > MAX_SIDE || hu > MAX_SIDE {
        return Err(format!("torch tensor image of {w}x{h} pixels"));
    }
    let at = |y: usize, x: usize, c: usize| {
        if chw {
            (c * h + y) * w + x
        } else {
            (y * w + x) * 3 + c
        }
    };
    let mut out = RgbImage::new(wu, hu);
    match &tensor.data {
        RawData::Int(v) => {
            if tensor.file_dtype != "U8" {
                return Err(format!(
                    "torch tensor of dtype {}, expected uint8 or a float type",
                    tensor.file_dtype
                ));
            }
            for (x, y, px) in out.enumerate_pixels_mut() {
                for c in 0..3 {
                    // uint8 storage: always 0..=255.
                    px[c] = v[at(y as usize, x as usize, c)].clamp(0, 255) as u8;
                }
            }
        }
        RawData::Float(v) => {
            if let Some(bad) = v.iter().find(|x| !x.is_finite()) {
                return Err(format!("torch tensor holds a non-finite value ({bad})"));
            }
            for (x, y, px) in out.enumerate_pixels_mut() {
                for c in 0..3 {
                    // Float images are in [0, 1] (spec section 2); out-of-range values clamp.
                    let f = v[at(y as usize, x as usize, c)];
                    px[c] = (f * 255.0).round().clamp(0.0, 255.0) as u8;
                }
            }
        }
    }
    Ok(out)
}

/// PNG bytes of an image (for writing an `img_lmdb`).
pub fn encode_png(img: &RgbImage) -> Result<Vec<u8>> {
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)
        .map_err(|e| DataError::Encode {
            reason: e.to_string(),
        })?;
    Ok(out.into_inner())
}
