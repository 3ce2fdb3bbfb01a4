//! The target's head box (spec section 11) and the differentiable crop-and-resize of the box
//! losses.
//!
//! From a face bbox `(x0, y0, x1, y1)` normalised to [0, 1], the release takes a square of side
//! `s = 1.1 sqrt((x1 - x0)(y1 - y0))` around the bbox centre `(cx, cy)`, shrunk so it stays
//! inside the image: `s = min(s, 2 cx, 2 cy, 2 (1 - cx), 2 (1 - cy))`. Its corners
//! `c -+ s/2` are clamped to [0, 1], scaled by the image size and **truncated** to integers
//! (`.long()`), and the crop is rows `y0..y1`, columns `x0..x1` (end exclusive). Every step runs
//! in f32 in the release's order (as PyTorch does on a float32 bbox tensor), so the integer box
//! is the release's bit for bit. Because of the truncation the crop can be one pixel wider than
//! high or vice versa; each crop is resized to `out x out` on its own.
//!
//! The release scales both axes by the image width (its images are square); here x is scaled
//! by the width and y by the height, which is the same for square images.

use candle_core::{DType, Tensor};
use gagavatar_ops::resample::{resize, ResizeMode};

use crate::error::{input_err, Result};

/// The release's expansion factor of the bbox.
pub const HEAD_BOX_SCALE: f32 = 1.1;

/// An integer pixel crop: rows `y0..y1`, columns `x0..x1` (end exclusive, never empty).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HeadBox {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
}

impl HeadBox {
    pub fn width(&self) -> usize {
        self.x1 - self.x0
    }
    pub fn height(&self) -> usize {
        self.y1 - self.y0
    }
}

/// The head box of a normalised bbox `[x0, y0, x1, y1]` in an `h x w` image.
///
/// Errors: non-finite values, a bbox with no area (`x1 <= x0` or `y1 <= y0`), or a box that
/// truncates to an empty crop (a tiny bbox, or a centre on or outside the image border).
pub fn head_box(bbox: [f32; 4], h: usize, w: usize) -> Result<HeadBox> {
    let name = "bbox";
    if let Some(v) = bbox.iter().find(|v| !v.is_finite()) {
        return Err(input_err(
            name,
            format!("{bbox:?} has a non-finite value {v}"),
        ));
    }
    let [x0, y0, x1, y1] = bbox;
    if x1 <= x0 || y1 <= y0 {
        return Err(input_err(
            name,
            format!("{bbox:?} has no area (needs x1 > x0 and y1 > y0)"),
        ));
    }
    if h == 0 || w == 0 {
        return Err(input_err("image", format!("size {h}x{w} is empty")));
    }
    let cx = (x0 + x1) / 2.0;
    let cy = (y0 + y1) / 2.0;
    let mut side = ((y1 - y0) * (x1 - x0)).sqrt() * HEAD_BOX_SCALE;
    for limit in [cx * 2.0, cy * 2.0, (1.0 - cx) * 2.0, (1.0 - cy) * 2.0] {
        side = side.min(limit);
    }
    let half = side / 2.0;
    let px = |v: f32, n: usize| -> usize {
        // Clamped to [0, 1] first, so the truncating cast cannot go negative or past n.
        (v.clamp(0.0, 1.0) * n as f32) as usize
    };
    let hb = HeadBox {
        x0: px(cx - half, w),
        y0: px(cy - half, h),
        x1: px(cx + half, w),
        y1: px(cy + half, h),
    };
    if hb.x1 <= hb.x0 || hb.y1 <= hb.y0 {
        return Err(input_err(
            name,
            format!(
                "{bbox:?} gives an empty head box (columns {}..{}, rows {}..{}) in a {h}x{w} image",
                hb.x0, hb.x1, hb.y0, hb.y1
            ),
        ));
    }
    Ok(hb)
}

/// Head boxes of a `[B, 4]` bbox tensor (any float dtype) for `h x w` images.
pub fn head_boxes(bbox: &Tensor, h: usize, w: usize) -> Result<Vec<HeadBox>> {
    match bbox.dims() {
        [_, 4] => {}
        other => return Err(input_err("bbox", format!("expected [B, 4], got {other:?}"))),
    }
    let rows: Vec<Vec<f32>> = bbox.to_dtype(DType::F32)?.to_vec2()?;
    rows.iter()
        .enumerate()
        .map(|(i, r)| {
            head_box([r[0], r[1], r[2], r[3]], h, w).map_err(|e| match e {
                crate::TrainError::Input { reason, .. } => input_err(&format!("bbox[{i}]"), reason),
                other => other,
            })
        })
        .collect()
}

/// Crops `boxes[b]` out of image `b` of `images` `[B, C, H, W]` and resizes each crop to
/// `out x out` with the antialiased bilinear resize (PyTorch `antialias=True`), giving
/// `[B, C, out, out]`. Differentiable with respect to `images`.
pub fn crop_resize(images: &Tensor, boxes: &[HeadBox], out: usize) -> Result<Tensor> {
    let (b, _, h, w) = match images.dims() {
        &[b, c, h, w] if b > 0 && c > 0 => (b, c, h, w),
        other => {
            return Err(input_err(
                "images",
                format!("expected a non-empty [B, C, H, W] batch, got {other:?}"),
            ))
        }
    };
    if boxes.len() != b {
        return Err(input_err(
            "boxes",
            format!("{} boxes for a batch of {b}", boxes.len()),
        ));
    }
    if out == 0 {
        return Err(input_err("out", "the crop size must be positive"));
    }
    let mut crops = Vec::with_capacity(b);
    for (i, hb) in boxes.iter().enumerate() {
        if hb.x1 <= hb.x0 || hb.y1 <= hb.y0 || hb.x1 > w || hb.y1 > h {
            return Err(input_err(
                &format!("boxes[{i}]"),
                format!("{hb:?} is empty or outside the {h}x{w} image"),
            ));
        }
        let crop = images
            .narrow(0, i, 1)?
            .narrow(2, hb.y0, hb.height())?
            .narrow(3, hb.x0, hb.width())?;
        crops.push(resize(&crop, out, out, ResizeMode::Antialias)?);
    }
    Ok(Tensor::cat(&crops, 0)?)
}
