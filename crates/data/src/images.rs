//! Images stored as LMDB values (or files): PNG / JPEG bytes, or, as the release's fallback, a
//! `torch.save`d tensor (`[3,H,W]` or `[H,W,3]`, optionally with a leading batch of 1; uint8, or
//! floats in [0, 1]).
//!
//! The tensor is read by `gagavatar_flame::read_torch_zip` (our data-only torch reader), which
//! takes a file path: the bytes go through a private temporary file that is removed afterwards.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use gagavatar_flame::asset::RawData;
use image::RgbImage;

use crate::error::{DataError, Result};

/// Largest width or height accepted (a corrupt header could otherwise ask for gigabytes).
pub const MAX_SIDE: u32 = 16384;

/// What the bytes are, from their first bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ImageKind {
    Png,
    Jpeg,
    TorchZip,
}

pub fn sniff(bytes: &[u8]) -> Option<ImageKind> {
    if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        Some(ImageKind::Png)
    } else if bytes.starts_with(&[0xff, 0xd8, 0xff]) {
        Some(ImageKind::Jpeg)
    } else if bytes.starts_with(b"PK\x03\x04") {
        Some(ImageKind::TorchZip)
    } else {
        None
    }
}

/// Decodes an image value; `path` and `key` only label errors (the LMDB and the entry, or the
/// file and its name).
pub fn decode_image(bytes: &[u8], path: &Path, key: &str) -> Result<RgbImage> {
    let err = |reason: String| DataError::Image {
        path: path.to_owned(),
        key: key.to_owned(),
        reason,
    };
    match sniff(bytes) {
        Some(ImageKind::Png) => decode_with(bytes, image::ImageFormat::Png).map_err(err),
        Some(ImageKind::Jpeg) => decode_with(bytes, image::ImageFormat::Jpeg).map_err(err),
        Some(ImageKind::TorchZip) => decode_torch(bytes).map_err(err),
        None => Err(err(format!(
            "{} bytes that are neither PNG, JPEG nor a torch-saved tensor",
            bytes.len()
        ))),
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

fn decode_with(bytes: &[u8], format: image::ImageFormat) -> std::result::Result<RgbImage, String> {
    let mut reader = image::ImageReader::with_format(std::io::Cursor::new(bytes), format);
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_SIDE);
    limits.max_image_height = Some(MAX_SIDE);
    reader.limits(limits);
    let img = reader
        .decode()
        .map_err(|e| format!("corrupt {format:?} data: {e}"))?;
    // Grey images are expanded and an alpha channel is dropped: the model takes RGB.
    Ok(img.to_rgb8())
}

static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Removes the temporary file when dropped, on every path out.
struct TempFile(PathBuf);

impl Drop for TempFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

fn decode_torch(bytes: &[u8]) -> std::result::Result<RgbImage, String> {
    let name = format!(
        "gagavatar-data-{}-{}.pt",
        std::process::id(),
        TEMP_COUNTER.fetch_add(1, Ordering::Relaxed)
    );
    let tmp = TempFile(std::env::temp_dir().join(name));
    std::fs::write(&tmp.0, bytes)
        .map_err(|e| format!("cannot stage the torch tensor in {}: {e}", tmp.0.display()))?;
    let tensors = gagavatar_flame::read_torch_zip(&tmp.0).map_err(|e| {
        // The temp path means nothing to the user; keep the reason only.
        let text = e.to_string();
        let reason = text
            .split_once(": ")
            .map(|(_, r)| r.to_owned())
            .unwrap_or(text);
        format!("torch tensor: {reason}")
    })?;
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
