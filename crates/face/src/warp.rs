//! Image to model input, as MediaPipe's CPU `ImageToTensorCalculator` does it: a rotated
//! rectangle of the image is sampled into the tensor by OpenCV's `warpPerspective` (bilinear,
//! 8-bit fixed point: coordinates rounded to 1/32 pixel, weights in 1/32768), the result rounded
//! to 8 bits, then mapped linearly to the model's value range.
//!
//! The sampling here reproduces OpenCV's integer arithmetic, so the crops are the same bytes
//! MediaPipe feeds its models (checked against MediaPipe's own calculator in the tests; a pixel
//! can differ by one level only where a coordinate lands within rounding error of a 1/64-pixel
//! tie).

use image::RgbImage;

use crate::tensor::Nhwc;

/// A rectangle of the image in pixels: centre, size, and rotation in radians (positive turns
/// the rectangle's x axis towards +y, the image's down).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RotatedRect {
    pub cx: f32,
    pub cy: f32,
    pub w: f32,
    pub h: f32,
    pub rotation: f32,
}

/// What a sample outside the image reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Border {
    /// Zero (black): the detectors' letterbox and the segmentation input.
    Zero,
    /// The nearest edge pixel: the landmark crop.
    Replicate,
}

/// Sub-pixel positions per pixel (OpenCV's `INTER_TAB_SIZE`).
const TAB: i64 = 32;
/// Fixed-point scale of the bilinear weights (OpenCV's `INTER_REMAP_COEF_SCALE`).
const COEF_BITS: u32 = 15;

impl RotatedRect {
    /// The four corners as OpenCV's `RotatedRect::points` computes them in f32: bottom-left,
    /// top-left, top-right, bottom-right of the unrotated rectangle.
    fn corners(&self) -> [(f32, f32); 4] {
        // MediaPipe hands OpenCV the angle in f32 degrees; OpenCV converts back in f64.
        let degrees = ((self.rotation * 180.0) as f64 / std::f64::consts::PI) as f32;
        let angle = degrees as f64 * std::f64::consts::PI / 180.0;
        let b = angle.cos() as f32 * 0.5;
        let a = angle.sin() as f32 * 0.5;
        let p0 = (
            self.cx - a * self.h - b * self.w,
            self.cy + b * self.h - a * self.w,
        );
        let p1 = (
            self.cx + a * self.h - b * self.w,
            self.cy - b * self.h - a * self.w,
        );
        let p2 = (2.0 * self.cx - p0.0, 2.0 * self.cy - p0.1);
        let p3 = (2.0 * self.cx - p1.0, 2.0 * self.cy - p1.1);
        [p0, p1, p2, p3]
    }

    /// The 3x3 map from output pixel coordinates of an `ow x oh` crop to image coordinates,
    /// computed as MediaPipe gets it from OpenCV: `getPerspectiveTransform` from the corners to
    /// the crop's edges (0 and `ow`, not pixel centres), solved by LU with partial pivoting in
    /// f64, then inverted by cofactors. (Analytically it is affine; reproducing OpenCV's
    /// rounding keeps the sampled coordinates on the same side of 1/64-pixel ties.)
    pub fn crop_to_image(&self, ow: usize, oh: usize) -> [f64; 9] {
        let src = self.corners();
        let (ow, oh) = (ow as f32, oh as f32);
        let dst = [(0.0f32, oh), (0.0, 0.0), (ow, 0.0), (ow, oh)];
        let mut a = [[0.0f64; 8]; 8];
        let mut b = [0.0f64; 8];
        for i in 0..4 {
            let ((sx, sy), (dx, dy)) = (src[i], dst[i]);
            a[i][0] = sx as f64;
            a[i][1] = sy as f64;
            a[i][2] = 1.0;
            a[i + 4][3] = sx as f64;
            a[i + 4][4] = sy as f64;
            a[i + 4][5] = 1.0;
            // OpenCV multiplies the f32 coordinates in f32.
            a[i][6] = (-sx * dx) as f64;
            a[i][7] = (-sy * dx) as f64;
            a[i + 4][6] = (-sx * dy) as f64;
            a[i + 4][7] = (-sy * dy) as f64;
            b[i] = dx as f64;
            b[i + 4] = dy as f64;
        }
        let x = lu_solve(a, b);
        let m = [x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7], 1.0];
        invert3(&m)
    }
}

/// Gaussian elimination with partial pivoting and back substitution, in the order of
/// OpenCV's `LUImpl` (a singular system gives zeros).
#[allow(clippy::needless_range_loop)] // indexed as the elimination is written
fn lu_solve(mut a: [[f64; 8]; 8], mut b: [f64; 8]) -> [f64; 8] {
    const N: usize = 8;
    for i in 0..N {
        let mut k = i;
        for j in i + 1..N {
            if a[j][i].abs() > a[k][i].abs() {
                k = j;
            }
        }
        if a[k][i].abs() < f64::EPSILON * 100.0 {
            return [0.0; N];
        }
        if k != i {
            a.swap(i, k);
            b.swap(i, k);
        }
        let d = -1.0 / a[i][i];
        for j in i + 1..N {
            let alpha = a[j][i] * d;
            for c in i + 1..N {
                a[j][c] += alpha * a[i][c];
            }
            b[j] += alpha * b[i];
        }
    }
    for i in (0..N).rev() {
        let mut s = b[i];
        for k in i + 1..N {
            s -= a[i][k] * b[k];
        }
        b[i] = s / a[i][i];
    }
    b
}

/// 3x3 inverse by cofactors over the determinant (OpenCV's `invert` for 3x3 f64).
fn invert3(m: &[f64; 9]) -> [f64; 9] {
    let s = |r: usize, c: usize| m[r * 3 + c];
    let det = s(0, 0) * (s(1, 1) * s(2, 2) - s(1, 2) * s(2, 1))
        - s(0, 1) * (s(1, 0) * s(2, 2) - s(1, 2) * s(2, 0))
        + s(0, 2) * (s(1, 0) * s(2, 1) - s(1, 1) * s(2, 0));
    if det == 0.0 {
        return [0.0; 9];
    }
    let d = 1.0 / det;
    [
        (s(1, 1) * s(2, 2) - s(1, 2) * s(2, 1)) * d,
        (s(0, 2) * s(2, 1) - s(0, 1) * s(2, 2)) * d,
        (s(0, 1) * s(1, 2) - s(0, 2) * s(1, 1)) * d,
        (s(1, 2) * s(2, 0) - s(1, 0) * s(2, 2)) * d,
        (s(0, 0) * s(2, 2) - s(0, 2) * s(2, 0)) * d,
        (s(0, 2) * s(1, 0) - s(0, 0) * s(1, 2)) * d,
        (s(1, 0) * s(2, 1) - s(1, 1) * s(2, 0)) * d,
        (s(0, 1) * s(2, 0) - s(0, 0) * s(2, 1)) * d,
        (s(0, 0) * s(1, 1) - s(0, 1) * s(1, 0)) * d,
    ]
}

/// OpenCV's `cvRound` of a double: to nearest, ties to even (the SSE2 conversion in the
/// default rounding mode), after clamping to the i32 range as `warpPerspective` does.
#[inline(always)]
fn round_even(v: f64) -> i32 {
    // Adding 1.5 * 2^52 rounds to an integer in the current (nearest-even) mode for
    // |v| < 2^51, and leaves that integer in the low 32 bits of the result.
    const MAGIC: f64 = 6_755_399_441_055_744.0;
    let v = v.max(i32::MIN as f64).min(i32::MAX as f64);
    (v + MAGIC).to_bits() as u32 as i32
}

/// The fixed-point source coordinates (1/32 pixel) of output pixels `x0..x0 + sx.len()` of a
/// row, continuing a block of OpenCV's evaluation from its start values.
#[inline(always)]
fn row_coords(m: &[f64; 9], start: [f64; 3], sx: &mut [i32], sy: &mut [i32]) {
    let [x0, y0, w0] = start;
    for (i, (a, b)) in sx.iter_mut().zip(sy.iter_mut()).enumerate() {
        let x1 = i as f64;
        let w = w0 + m[6] * x1;
        let w = if w != 0.0 { TAB as f64 / w } else { 0.0 };
        *a = round_even((x0 + m[0] * x1) * w);
        *b = round_even((y0 + m[3] * x1) * w);
    }
}

crate::simd::dispatch!(fn row_coords_d(m: &[f64; 9], start: [f64; 3], sx: &mut [i32], sy: &mut [i32]) = plain row_coords);

/// Samples `roi` of `img` into an `ow x oh` 8-bit RGB crop (OpenCV `warpPerspective`,
/// `INTER_LINEAR`).
pub fn warp_u8(img: &RgbImage, roi: &RotatedRect, ow: usize, oh: usize, border: Border) -> Vec<u8> {
    let (iw, ih) = (img.width() as i64, img.height() as i64);
    let src = img.as_raw().as_slice();
    let m = roi.crop_to_image(ow, oh);
    let mut out = vec![0u8; ow * oh * 3];
    if iw == 0 || ih == 0 {
        return out;
    }
    let stride = (iw * 3) as usize;
    let half = 1i32 << (COEF_BITS - 1);
    // The bilinear weights are products of multiples of 1/32: exact in 1/32768 units.
    let unit = ((1 << COEF_BITS) / (TAB * TAB)) as i32;
    // OpenCV evaluates the map per block of output pixels (16 rows by up to 1024/16 columns):
    // the row start at the block's first column, then one step per column.
    let bh0 = 16.min(oh).max(1);
    let bw0 = (1024 / bh0).min(ow).max(1);
    crate::kernels::for_rows(&mut out, oh, ow * 3, ow * oh * 40, |y0, band| {
        let (mut sxs, mut sys) = (vec![0i32; bw0], vec![0i32; bw0]);
        for (dy, row) in band.chunks_exact_mut(ow * 3).enumerate() {
            let y = y0 + dy;
            let yf = y as f64;
            for bx in (0..ow).step_by(bw0) {
                let n = bw0.min(ow - bx);
                let bxf = bx as f64;
                let start = [
                    m[0] * bxf + m[1] * yf + m[2],
                    m[3] * bxf + m[4] * yf + m[5],
                    m[6] * bxf + m[7] * yf + m[8],
                ];
                row_coords_d(&m, start, &mut sxs[..n], &mut sys[..n]);
                // Chunks of 16 pixels go through the gather kernel when their taps allow,
                // the rest through the scalar loop below.
                let mut simd_done = [false; 1024];
                #[cfg(target_arch = "x86_64")]
                if crate::simd::level() == crate::simd::Level::Avx512 {
                    for c in (0..n / 16).map(|c| c * 16) {
                        let dst = &mut row[(bx + c) * 3..(bx + c + 16) * 3];
                        // SAFETY: AVX-512F was detected; the function checks every pixel's taps
                        // against the image before reading.
                        simd_done[c] = unsafe {
                            sample16_avx512(
                                src,
                                iw as i32,
                                ih as i32,
                                &sxs[c..c + 16],
                                &sys[c..c + 16],
                                border == Border::Zero,
                                dst,
                            )
                        };
                    }
                }
                for (i, (&sx, &sy)) in sxs[..n].iter().zip(&sys[..n]).enumerate() {
                    if simd_done[i / 16 * 16] {
                        continue;
                    }
                    let x = bx + i;
                    let (px, py) = ((sx >> 5) as i64, (sy >> 5) as i64);
                    let (fx, fy) = (sx & (TAB as i32 - 1), sy & (TAB as i32 - 1));
                    let t = TAB as i32;
                    let wt = [
                        (t - fy) * (t - fx) * unit,
                        (t - fy) * fx * unit,
                        fy * (t - fx) * unit,
                        fy * fx * unit,
                    ];
                    let o = &mut row[x * 3..x * 3 + 3];
                    if px >= 0 && py >= 0 && px + 1 < iw && py + 1 < ih {
                        let a = (py * iw + px) as usize * 3;
                        debug_assert!(a + stride + 6 <= src.len());
                        for (c, v) in o.iter_mut().enumerate() {
                            // SAFETY: (px, py) and (px + 1, py + 1) are inside the image (checked
                            // above), so bytes a..a+6 of rows py and py + 1 are in `src`.
                            let (a0, a1, b0, b1) = unsafe {
                                (
                                    *src.get_unchecked(a + c) as i32,
                                    *src.get_unchecked(a + c + 3) as i32,
                                    *src.get_unchecked(a + stride + c) as i32,
                                    *src.get_unchecked(a + stride + c + 3) as i32,
                                )
                            };
                            // Weights sum to 2^15, so the result is within 0..=255.
                            *v = ((a0 * wt[0] + a1 * wt[1] + b0 * wt[2] + b1 * wt[3] + half)
                                >> COEF_BITS) as u8;
                        }
                        continue;
                    }
                    // Near or past the edge: each tap reads the border rule.
                    let taps = match border {
                        Border::Zero => {
                            if px >= iw || px + 1 < 0 || py >= ih || py + 1 < 0 {
                                continue;
                            }
                            let inside = |x: i64, y: i64| {
                                (x >= 0 && y >= 0 && x < iw && y < ih).then_some((x, y))
                            };
                            [
                                inside(px, py),
                                inside(px + 1, py),
                                inside(px, py + 1),
                                inside(px + 1, py + 1),
                            ]
                        }
                        Border::Replicate => {
                            let (xa, xb) = (px.clamp(0, iw - 1), (px + 1).clamp(0, iw - 1));
                            let (ya, yb) = (py.clamp(0, ih - 1), (py + 1).clamp(0, ih - 1));
                            [
                                Some((xa, ya)),
                                Some((xb, ya)),
                                Some((xa, yb)),
                                Some((xb, yb)),
                            ]
                        }
                    };
                    for (c, v) in o.iter_mut().enumerate() {
                        let mut s = 0i32;
                        for (tap, w) in taps.iter().zip(wt) {
                            if let Some((tx, ty)) = tap {
                                s += src[(ty * iw + tx) as usize * 3 + c] as i32 * w;
                            }
                        }
                        *v = ((s + half) >> COEF_BITS).clamp(0, 255) as u8;
                    }
                }
            }
        }
    });
    out
}

/// Samples 16 consecutive output pixels whose four taps are all inside the image, or (with
/// `zero_outside`, the zero border) all outside it (returns false, writing nothing, when a
/// pixel straddles the edge): the same integer arithmetic as the scalar loop, 16 pixels per
/// instruction, the taps fetched with gathers.
///
/// # Safety
/// AVX-512F must be available.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn sample16_avx512(
    src: &[u8],
    iw: i32,
    ih: i32,
    sx: &[i32],
    sy: &[i32],
    zero_outside: bool,
    dst: &mut [u8],
) -> bool {
    use std::arch::x86_64::*;
    debug_assert!(sx.len() == 16 && sy.len() == 16 && dst.len() == 48);
    // SAFETY: 16 values in each slice.
    let (vx, vy) = unsafe {
        (
            _mm512_loadu_si512(sx.as_ptr().cast()),
            _mm512_loadu_si512(sy.as_ptr().cast()),
        )
    };
    let px = _mm512_srai_epi32::<5>(vx);
    let py = _mm512_srai_epi32::<5>(vy);
    let zero = _mm512_setzero_si512();
    let inside = _mm512_cmpge_epi32_mask(px, zero)
        & _mm512_cmpge_epi32_mask(py, zero)
        & _mm512_cmplt_epi32_mask(px, _mm512_set1_epi32(iw - 1))
        & _mm512_cmplt_epi32_mask(py, _mm512_set1_epi32(ih - 1));
    // Every tap outside: px >= iw, px + 1 < 0, py >= ih or py + 1 < 0.
    let minus1 = _mm512_set1_epi32(-1);
    let outside = _mm512_cmpge_epi32_mask(px, _mm512_set1_epi32(iw))
        | _mm512_cmplt_epi32_mask(px, minus1)
        | _mm512_cmpge_epi32_mask(py, _mm512_set1_epi32(ih))
        | _mm512_cmplt_epi32_mask(py, minus1);
    let covered = if zero_outside {
        inside | outside
    } else {
        inside
    };
    if covered != 0xffff {
        return false;
    }
    let m31 = _mm512_set1_epi32(31);
    let fx = _mm512_and_si512(vx, m31);
    let fy = _mm512_and_si512(vy, m31);
    let t = _mm512_set1_epi32(32);
    let (gx, gy) = (_mm512_sub_epi32(t, fx), _mm512_sub_epi32(t, fy));
    // Weights in 1/32768: products of the 1/32 fractions, times 32.
    let w00 = _mm512_slli_epi32::<5>(_mm512_mullo_epi32(gy, gx));
    let w01 = _mm512_slli_epi32::<5>(_mm512_mullo_epi32(gy, fx));
    let w10 = _mm512_slli_epi32::<5>(_mm512_mullo_epi32(fy, gx));
    let w11 = _mm512_slli_epi32::<5>(_mm512_mullo_epi32(fy, fx));
    let three = _mm512_set1_epi32(3);
    let a = _mm512_add_epi32(
        _mm512_mullo_epi32(py, _mm512_set1_epi32(iw * 3)),
        _mm512_mullo_epi32(px, three),
    );
    let a2 = _mm512_add_epi32(a, _mm512_set1_epi32(2));
    let stride = _mm512_set1_epi32(iw * 3);
    let b = _mm512_add_epi32(a, stride);
    let b2 = _mm512_add_epi32(a2, stride);
    let base = src.as_ptr();
    // Dwords at a (r0 g0 b0 r1) and a + 2 (b0 r1 g1 b1) of both rows: every byte read belongs
    // to the two pixels of the tap, inside the image (px + 1 < iw, py + 1 < ih). Lanes outside
    // the image read nothing and stay zero, so they compute 0 (the zero border).
    // SAFETY: as just said, every offset read and the 4 bytes after it are inside `src`.
    let (g0, g1, g2, g3) = unsafe {
        (
            _mm512_mask_i32gather_epi32::<1>(zero, inside, a, base.cast()),
            _mm512_mask_i32gather_epi32::<1>(zero, inside, a2, base.cast()),
            _mm512_mask_i32gather_epi32::<1>(zero, inside, b, base.cast()),
            _mm512_mask_i32gather_epi32::<1>(zero, inside, b2, base.cast()),
        )
    };
    let byte = _mm512_set1_epi32(0xff);
    let half = _mm512_set1_epi32(1 << (COEF_BITS - 1));
    let mut rgb = _mm512_setzero_si512();
    // Channel c: byte c of the dword at a (left pixel), byte c + 1 of the dword at a + 2
    // (right pixel).
    macro_rules! channel {
        ($c:literal, $shl:literal, $shr_l:literal, $shr_r:literal) => {{
            let l0 = _mm512_and_si512(_mm512_srli_epi32::<$shr_l>(g0), byte);
            let r0 = _mm512_and_si512(_mm512_srli_epi32::<$shr_r>(g1), byte);
            let l1 = _mm512_and_si512(_mm512_srli_epi32::<$shr_l>(g2), byte);
            let r1 = _mm512_and_si512(_mm512_srli_epi32::<$shr_r>(g3), byte);
            let s = _mm512_add_epi32(
                _mm512_add_epi32(_mm512_mullo_epi32(l0, w00), _mm512_mullo_epi32(r0, w01)),
                _mm512_add_epi32(_mm512_mullo_epi32(l1, w10), _mm512_mullo_epi32(r1, w11)),
            );
            let v = _mm512_srli_epi32::<COEF_BITS>(_mm512_add_epi32(s, half));
            rgb = _mm512_or_si512(rgb, _mm512_slli_epi32::<$shl>(v));
        }};
    }
    channel!(0, 0, 0, 8);
    channel!(1, 8, 8, 16);
    channel!(2, 16, 16, 24);
    let mut px4 = [0u32; 16];
    // SAFETY: 16 writable values.
    unsafe { _mm512_storeu_si512(px4.as_mut_ptr().cast(), rgb) };
    for (d, p) in dst.chunks_exact_mut(3).zip(px4) {
        d.copy_from_slice(&p.to_le_bytes()[..3]);
    }
    true
}

/// The 8-bit crop mapped to `[lo, hi]` (0 -> lo, 255 -> hi) as a model input.
pub fn to_tensor(crop: &[u8], ow: usize, oh: usize, lo: f32, hi: f32) -> Nhwc {
    let scale = (hi - lo) / 255.0;
    Nhwc::from_vec(
        oh,
        ow,
        3,
        crop.iter().map(|&v| v as f32 * scale + lo).collect(),
    )
}

/// The whole image letterboxed (aspect kept, centred, zero border) into an `n x n` tensor:
/// the detectors' input. Returns the tensor and the padded rectangle it covers (for mapping
/// detections back).
pub fn letterbox(img: &RgbImage, n: usize, lo: f32, hi: f32) -> (Nhwc, RotatedRect) {
    let roi = letterbox_rect(img.width(), img.height());
    let crop = warp_u8(img, &roi, n, n, Border::Zero);
    (to_tensor(&crop, n, n, lo, hi), roi)
}

/// MediaPipe's `PadRoi` for a square tensor: the whole image, widened on its short side to a
/// square.
pub fn letterbox_rect(w: u32, h: u32) -> RotatedRect {
    let (w, h) = (w as f32, h as f32);
    let side = w.max(h);
    RotatedRect {
        cx: 0.5 * w,
        cy: 0.5 * h,
        w: side,
        h: side,
        rotation: 0.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identity_crop_copies_pixels() {
        let img = RgbImage::from_fn(8, 6, |x, y| image::Rgb([x as u8 * 10, y as u8 * 20, 7]));
        let roi = RotatedRect {
            cx: 4.0,
            cy: 3.0,
            w: 8.0,
            h: 6.0,
            rotation: 0.0,
        };
        let out = warp_u8(&img, &roi, 8, 6, Border::Zero);
        assert_eq!(out, img.as_raw().clone());
    }

    #[test]
    fn borders() {
        let img = RgbImage::from_pixel(4, 4, image::Rgb([200, 100, 50]));
        // A rectangle twice the image, centred: the outer ring samples outside.
        let roi = RotatedRect {
            cx: 2.0,
            cy: 2.0,
            w: 8.0,
            h: 8.0,
            rotation: 0.0,
        };
        let z = warp_u8(&img, &roi, 8, 8, Border::Zero);
        let r = warp_u8(&img, &roi, 8, 8, Border::Replicate);
        assert_eq!(&z[0..3], &[0, 0, 0]);
        assert_eq!(&r[0..3], &[200, 100, 50]);
        assert!(r.chunks(3).all(|p| p == [200, 100, 50]));
    }

    #[test]
    fn round_even_ties() {
        assert_eq!(round_even(2.5), 2);
        assert_eq!(round_even(3.5), 4);
        assert_eq!(round_even(-2.5), -2);
        assert_eq!(round_even(-3.7), -4);
        assert_eq!(round_even(2.4999), 2);
        assert_eq!(round_even(1e300), i32::MAX);
        assert_eq!(round_even(-1e300), i32::MIN);
    }
}
