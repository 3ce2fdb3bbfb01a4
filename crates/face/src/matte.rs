//! The person matte: MediaPipe's selfie segmentation (spec TRACKING.md section 11). The whole
//! image is stretched (no letterbox) to 256x256, segmented, and the 256x256 probabilities are
//! resized back to the image with OpenCV's bilinear `resize` (half-pixel centres, edges
//! clamped): an H x W map of person probabilities in [0, 1], usable as alpha for a black
//! background (`out = image * matte`).

use image::RgbImage;

use crate::selfie_net::SelfieNet;
use crate::warp::{self, Border, RotatedRect};
use crate::weights::{bundled, WeightsFile};
use crate::FaceError;

/// A per-pixel person probability map, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Matte {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f32>,
}

impl Matte {
    pub fn at(&self, x: u32, y: u32) -> f32 {
        self.data[(y * self.width + x) as usize]
    }

    /// As an 8-bit grey image (probability x 255, rounded).
    pub fn to_luma8(&self) -> image::GrayImage {
        image::GrayImage::from_fn(self.width, self.height, |x, y| {
            image::Luma([(self.at(x, y).clamp(0.0, 1.0) * 255.0).round() as u8])
        })
    }
}

/// The selfie segmentation model.
#[derive(Debug, Clone)]
pub struct SelfieSegmenter {
    net: SelfieNet,
}

impl SelfieSegmenter {
    /// The model with the weights shipped in this crate.
    pub fn new() -> Result<Self, FaceError> {
        Self::from_weights(WeightsFile::from_bytes(
            bundled::SELFIE_SEGMENTATION,
            "selfie_segmentation.safetensors",
        )?)
    }

    pub fn from_weights(file: WeightsFile) -> Result<Self, FaceError> {
        Ok(SelfieSegmenter {
            net: file.build("selfie_segmentation", SelfieNet::new)?,
        })
    }

    /// The 256x256 probabilities for `img`.
    pub fn mask256(&self, img: &RgbImage) -> Result<crate::tensor::Nhwc, FaceError> {
        let (w, h) = (img.width() as f32, img.height() as f32);
        if img.width() == 0 || img.height() == 0 {
            return Err(FaceError::Input("the image is empty".into()));
        }
        let roi = RotatedRect {
            cx: 0.5 * w,
            cy: 0.5 * h,
            w,
            h,
            rotation: 0.0,
        };
        let n = SelfieNet::INPUT;
        let crop = warp::warp_u8(img, &roi, n, n, Border::Zero);
        Ok(self.net.forward(&warp::to_tensor(&crop, n, n, 0.0, 1.0)))
    }

    /// The matte at the image's size.
    pub fn matte(&self, img: &RgbImage) -> Result<Matte, FaceError> {
        let m = self.mask256(img)?;
        Ok(Matte {
            width: img.width(),
            height: img.height(),
            data: resize_linear(
                &m.data,
                m.w,
                m.h,
                img.width() as usize,
                img.height() as usize,
            ),
        })
    }
}

/// OpenCV's `resize(INTER_LINEAR)` of a one-channel f32 map: source position
/// `(d + 0.5) * src / dst - 0.5`, clamped to the edge pixels; rows interpolated first, then
/// columns.
pub fn resize_linear(src: &[f32], sw: usize, sh: usize, dw: usize, dh: usize) -> Vec<f32> {
    assert_eq!(src.len(), sw * sh, "resize source size");
    if (sw, sh) == (dw, dh) {
        return src.to_vec();
    }
    let taps = |d: usize, s: usize, n: usize| -> (usize, usize, f32) {
        let f = ((d as f64 + 0.5) * (s as f64 / n as f64) - 0.5) as f32;
        let mut i = f.floor() as isize;
        let mut t = f - i as f32;
        if i < 0 {
            i = 0;
            t = 0.0;
        }
        if i as usize >= s - 1 {
            i = s as isize - 1;
            t = 0.0;
        }
        let i = i as usize;
        (i, (i + 1).min(s - 1), t)
    };
    let xs: Vec<_> = (0..dw).map(|x| taps(x, sw, dw)).collect();
    // Each source row resampled to the output width, once.
    let mut rows = crate::tensor::take(sh * dw);
    for (r, out) in src.chunks_exact(sw).zip(rows.chunks_exact_mut(dw)) {
        for (o, &(a, b, t)) in out.iter_mut().zip(&xs) {
            *o = r[a] * (1.0 - t) + r[b] * t;
        }
    }
    let mut out = vec![0.0f32; dw * dh];
    crate::kernels::for_rows(&mut out, dh, dw, dw * dh * 4, |y0, band| {
        for (dy, o) in band.chunks_exact_mut(dw).enumerate() {
            let (a, b, t) = taps(y0 + dy, sh, dh);
            blend_d(
                &rows[a * dw..(a + 1) * dw],
                &rows[b * dw..(b + 1) * dw],
                1.0 - t,
                t,
                o,
            );
        }
    });
    crate::tensor::give(rows);
    out
}

/// `out = a * wa + b * wb`, element by element.
#[inline(always)]
fn blend(a: &[f32], b: &[f32], wa: f32, wb: f32, out: &mut [f32]) {
    for ((o, &x), &y) in out.iter_mut().zip(a).zip(b) {
        *o = x * wa + y * wb;
    }
}

crate::simd::dispatch!(fn blend_d(a: &[f32], b: &[f32], wa: f32, wb: f32, out: &mut [f32]) = plain blend);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resize_linear_edges_and_midpoints() {
        let src = [0.0, 1.0];
        // 2 -> 4: positions -0.25 (clamped to 0), 0.25, 0.75, 1.25 (clamped to 1).
        assert_eq!(resize_linear(&src, 2, 1, 4, 1), vec![0.0, 0.25, 0.75, 1.0]);
        assert_eq!(resize_linear(&src, 2, 1, 2, 1), vec![0.0, 1.0]);
    }
}
