//! dlib's face chips for the 5-point landmarks: `get_face_chip_details(shape, 150, 0.25)` and
//! `extract_image_chip` with bilinear interpolation, as dlib 20 computes them.
//!
//! * The chip's placement is the least-squares similarity from dlib's 5-point template
//!   (padded by `padding` on every side and scaled to the chip size) to the landmarks; dlib
//!   keeps its rotation angle and a rectangle of `size * scale` pixels centred where the
//!   chip's centre lands.
//! * When that rectangle is much larger than the chip (its half-size area exceeds the chip's
//!   area), dlib first builds an image pyramid (`pyramid_down<2>`: a 5-tap [1 4 6 4 1] filter
//!   in integers, every other row and column, over the part of the image around the chip) and
//!   samples the level where the chip rectangle, halved once more, would be smaller than the
//!   chip. Pyramid coordinates follow dlib's `point_down`: `p / 2 - (1.25, 0.75)`.
//! * Each chip pixel maps to the image by the affine map taking the chip's top-left, top-right
//!   and bottom-left corners to the rotated rectangle's; its value is the bilinear mix of the
//!   four neighbours in f64, truncated to u8; samples whose 2x2 neighbourhood is not inside
//!   the sampled image (the whole image cut to the region dlib crops, or the pyramid level)
//!   are black.

use image::RgbImage;

use crate::error::{input_err, Result};
use crate::geometry::{rotate_point, similarity_transform, Affine2, DRect};
use crate::shape_predictor::{Landmarks5, NUM_LANDMARKS};

/// dlib's chip size for its face-recognition network.
pub const CHIP_SIZE: usize = 150;
/// dlib's default padding around the 5-point template for face recognition.
pub const CHIP_PADDING: f64 = 0.25;

/// dlib's 5-point template in the unit square (`get_face_chip_details`).
const TEMPLATE_5: [[f64; 2]; NUM_LANDMARKS] = [
    [0.8595674595992, 0.2134981538014],
    [0.6460604764104, 0.2289674387677],
    [0.1205750620789, 0.2137274526848],
    [0.3340850613712, 0.2290642403242],
    [0.4901123135679, 0.6277975316475],
];

/// Where a chip is cut from: a rectangle in the image, turned by `angle` radians about its
/// centre, resampled to `rows x cols` (dlib's `chip_details`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChipDetails {
    pub rect: DRect,
    pub angle: f64,
    pub rows: usize,
    pub cols: usize,
}

/// The chip placement for 5 landmarks (dlib's `get_face_chip_details(det, size, padding)`).
pub fn face_chip_details(landmarks: &Landmarks5, size: usize, padding: f64) -> Result<ChipDetails> {
    if size == 0 || size > 4096 {
        return Err(input_err("chip size", format!("{size} is not in 1..=4096")));
    }
    if !(padding.is_finite() && padding >= 0.0) {
        return Err(input_err(
            "chip padding",
            format!("{padding} is not a finite value >= 0"),
        ));
    }
    let s = size as f64;
    let from: Vec<[f64; 2]> = TEMPLATE_5
        .iter()
        .map(|p| {
            [
                (padding + p[0]) / (2.0 * padding + 1.0) * s,
                (padding + p[1]) / (2.0 * padding + 1.0) * s,
            ]
        })
        .collect();
    let to: Vec<[f64; 2]> = landmarks
        .points
        .iter()
        .map(|p| [p[0] as f64, p[1] as f64])
        .collect();
    let tform = similarity_transform(&from, &to);
    let (px, py) = (tform.m[0][0], tform.m[1][0]);
    let angle = py.atan2(px);
    let scale = (px * px + py * py).sqrt();
    if !(scale.is_finite() && scale > 0.0) {
        return Err(input_err(
            "landmarks",
            format!(
                "degenerate landmarks {:?} (scale {scale})",
                landmarks.points
            ),
        ));
    }
    let centre = tform.apply([s / 2.0, s / 2.0]);
    Ok(ChipDetails {
        rect: DRect::centered(centre, s * scale, s * scale),
        angle,
        rows: size,
        cols: size,
    })
}

/// dlib's `point_down` of `pyramid_down<2>`.
fn point_down(p: [f64; 2]) -> [f64; 2] {
    [p[0] / 2.0 - 1.25, p[1] / 2.0 - 0.75]
}

fn rect_down(r: &DRect) -> DRect {
    let a = point_down(r.tl());
    let b = point_down(r.br());
    DRect {
        left: a[0],
        top: a[1],
        right: b[0],
        bottom: b[1],
    }
}

/// An RGB image as a plain buffer (a crop of the input or a pyramid level).
struct Plane {
    w: usize,
    h: usize,
    data: Vec<u8>,
}

impl Plane {
    fn crop(img: &RgbImage, left: i64, top: i64, right: i64, bottom: i64) -> Plane {
        let (w, h) = ((right - left + 1) as usize, (bottom - top + 1) as usize);
        let iw = img.width() as usize;
        let raw = img.as_raw();
        let mut data = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            let start = ((top as usize + y) * iw + left as usize) * 3;
            data.extend_from_slice(&raw[start..start + w * 3]);
        }
        Plane { w, h, data }
    }

    /// dlib's `pyramid_down<2>` for RGB: rows filtered with [1 4 6 4 1] at every other column
    /// (u16 sums), then columns at every other row, divided by 256 (truncating). Output
    /// `(h - 3) / 2 x (w - 3) / 2`; empty for a side of 8 or less.
    fn pyramid_down(&self) -> Plane {
        if self.h <= 8 || self.w <= 8 {
            return Plane {
                w: 0,
                h: 0,
                data: Vec::new(),
            };
        }
        let tw = (self.w - 3) / 2;
        let (ow, oh) = (tw, (self.h - 3) / 2);
        let mut tmp = vec![0u32; self.h * tw * 3];
        for r in 0..self.h {
            let row = &self.data[r * self.w * 3..(r + 1) * self.w * 3];
            for c in 0..tw {
                let oc = 2 * c;
                for ch in 0..3 {
                    let p = |k: usize| row[(oc + k) * 3 + ch] as u32;
                    tmp[(r * tw + c) * 3 + ch] = p(0) + 4 * p(1) + 6 * p(2) + 4 * p(3) + p(4);
                }
            }
        }
        let mut data = vec![0u8; oh * ow * 3];
        for dr in 0..oh {
            let r = 2 + 2 * dr;
            for c in 0..tw {
                for ch in 0..3 {
                    let t = |rr: usize| tmp[(rr * tw + c) * 3 + ch];
                    let v = t(r - 2) + 4 * t(r - 1) + 6 * t(r) + 4 * t(r + 1) + t(r + 2);
                    data[(dr * ow + c) * 3 + ch] = (v / 256) as u8;
                }
            }
        }
        Plane { w: ow, h: oh, data }
    }
}

/// Cuts the chip (dlib's `extract_image_chip(img, details, chip)` with bilinear
/// interpolation). Parts of the chip outside the image are black.
pub fn extract_image_chip(img: &RgbImage, d: &ChipDetails) -> Result<RgbImage> {
    let (iw, ih) = (img.width() as i64, img.height() as i64);
    if iw == 0 || ih == 0 {
        return Err(input_err("image", "the image is empty"));
    }
    if d.rows == 0 || d.cols == 0 || d.rows > 4096 || d.cols > 4096 {
        return Err(input_err(
            "chip",
            format!("{}x{} is not a chip size", d.cols, d.rows),
        ));
    }
    let vals = [
        d.rect.left,
        d.rect.top,
        d.rect.right,
        d.rect.bottom,
        d.angle,
    ];
    if !vals.iter().all(|v| v.is_finite()) || d.rect.is_empty() {
        return Err(input_err(
            "chip",
            format!("rectangle {:?} angle {} is not usable", d.rect, d.angle),
        ));
    }
    let chip_area = (d.rows * d.cols) as f64;

    // The fast path: no rotation or scaling, a plain copy (dlib's basic_extract_image_chip).
    if d.angle == 0.0 && d.rows as f64 == d.rect.height() && d.cols as f64 == d.rect.width() {
        let (l, t) = (round_px_lround(d.rect.left), round_px_lround(d.rect.top));
        let mut chip = RgbImage::new(d.cols as u32, d.rows as u32);
        for r in 0..d.rows as i64 {
            for c in 0..d.cols as i64 {
                let (x, y) = (l + c, t + r);
                if x >= 0 && y >= 0 && x < iw && y < ih {
                    chip.put_pixel(c as u32, r as u32, *img.get_pixel(x as u32, y as u32));
                }
            }
        }
        return Ok(chip);
    }

    // Pyramid depth and the region of the image dlib works on.
    let mut depth = 0usize;
    let mut grow = 2.0f64;
    let mut r = rect_down(&d.rect);
    while r.area() > chip_area {
        r = rect_down(&r);
        depth += 1;
        grow = grow * 2.0 + 2.0;
        if depth > 64 {
            return Err(input_err("chip", "the chip rectangle is implausibly large"));
        }
    }
    let c = d.rect.center();
    let corners = [d.rect.tl(), d.rect.tr(), d.rect.bl(), d.rect.br()];
    let mut rot = DRect {
        left: f64::INFINITY,
        top: f64::INFINITY,
        right: f64::NEG_INFINITY,
        bottom: f64::NEG_INFINITY,
    };
    for p in corners {
        let q = rotate_point(c, p, d.angle);
        rot = rot.union(&DRect {
            left: q[0],
            top: q[1],
            right: q[0],
            bottom: q[1],
        });
    }
    let img_rect = DRect {
        left: 0.0,
        top: 0.0,
        right: (iw - 1) as f64,
        bottom: (ih - 1) as f64,
    };
    let region = rot.grow(grow).intersect(&img_rect);
    // dlib converts the region to an integer rectangle with lround.
    let (bl, bt, br, bb) = (
        round_px_lround(region.left),
        round_px_lround(region.top),
        round_px_lround(region.right),
        round_px_lround(region.bottom),
    );
    if region.is_empty() || br < bl || bb < bt {
        return Err(input_err(
            "chip",
            format!(
                "the chip rectangle {:?} does not overlap the {iw}x{ih} image",
                d.rect
            ),
        ));
    }
    let base = Plane::crop(img, bl, bt, br, bb);
    let mut levels: Vec<Plane> = Vec::with_capacity(depth);
    for i in 0..depth {
        let next = if i == 0 {
            base.pyramid_down()
        } else {
            levels[i - 1].pyramid_down()
        };
        levels.push(next);
    }

    // The level to sample, and the chip rectangle in its coordinates.
    let mut level: Option<usize> = None;
    let mut rect = d.rect.translate(-(bl as f64), -(bt as f64));
    while rect_down(&rect).area() > chip_area {
        level = Some(level.map_or(0, |l| l + 1));
        rect = rect_down(&rect);
    }
    let src = match level {
        None => &base,
        Some(l) => levels.get(l).unwrap_or(&base),
    };
    let rc = rect.center();
    let map = Affine2::from_axes(
        (d.cols - 1).max(1) as f64,
        (d.rows - 1).max(1) as f64,
        rotate_point(rc, rect.tl(), d.angle),
        rotate_point(rc, rect.tr(), d.angle),
        rotate_point(rc, rect.bl(), d.angle),
    );
    Ok(sample_bilinear(src, &map, d.cols, d.rows))
}

/// dlib's `lround` of a drectangle side (round half away from zero).
fn round_px_lround(v: f64) -> i64 {
    v.round() as i64
}

/// Every chip pixel (c, r) takes the bilinear value at `map(c, r)` in `src`, truncated; black
/// where the 2x2 neighbourhood leaves `src`.
fn sample_bilinear(src: &Plane, map: &Affine2, cols: usize, rows: usize) -> RgbImage {
    let mut out = vec![0u8; cols * rows * 3];
    let (w, h) = (src.w as i64, src.h as i64);
    for r in 0..rows {
        for c in 0..cols {
            let p = map.apply([c as f64, r as f64]);
            let left = p[0].floor();
            let top = p[1].floor();
            if !(left.is_finite() && top.is_finite()) {
                continue;
            }
            let (l, t) = (left as i64, top as i64);
            if !(l >= 0 && t >= 0 && l + 1 < w && t + 1 < h) {
                continue;
            }
            let lr = p[0] - left;
            let tb = p[1] - top;
            let px = |y: i64, x: i64, ch: usize| src.data[((y * w + x) * 3) as usize + ch] as f64;
            for ch in 0..3 {
                let v = (1.0 - tb) * ((1.0 - lr) * px(t, l, ch) + lr * px(t, l + 1, ch))
                    + tb * ((1.0 - lr) * px(t + 1, l, ch) + lr * px(t + 1, l + 1, ch));
                out[(r * cols + c) * 3 + ch] = v as u8;
            }
        }
    }
    // The buffer has exactly cols x rows pixels.
    RgbImage::from_raw(cols as u32, rows as u32, out).unwrap_or_default()
}

/// The map from image pixels to chip pixels (dlib's `get_mapping_to_chip`), e.g. to draw the
/// landmarks on a chip.
pub fn mapping_to_chip(d: &ChipDetails) -> Affine2 {
    let c = d.rect.center();
    let p0 = rotate_point(c, d.rect.tl(), d.angle);
    let p1 = rotate_point(c, d.rect.tr(), d.angle);
    let p2 = rotate_point(c, d.rect.bl(), d.angle);
    // chip -> image, then inverted.
    let f = Affine2::from_axes(
        (d.cols - 1).max(1) as f64,
        (d.rows - 1).max(1) as f64,
        p0,
        p1,
        p2,
    );
    let det = f.m[0][0] * f.m[1][1] - f.m[0][1] * f.m[1][0];
    let inv = [
        [f.m[1][1] / det, -f.m[0][1] / det],
        [-f.m[1][0] / det, f.m[0][0] / det],
    ];
    Affine2 {
        m: inv,
        b: [
            -(inv[0][0] * f.b[0] + inv[0][1] * f.b[1]),
            -(inv[1][0] * f.b[0] + inv[1][1] * f.b[1]),
        ],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn landmarks(points: [[i64; 2]; NUM_LANDMARKS]) -> Landmarks5 {
        Landmarks5 {
            points,
            precise: points.map(|p| [p[0] as f64, p[1] as f64]),
        }
    }

    /// Rounding error of a few f64 operations on coordinates of a few hundred pixels.
    const TOL: f64 = 1e-9;

    #[test]
    fn landmarks_land_near_the_template_in_the_chip() {
        let lm = landmarks([[163, 104], [146, 105], [103, 101], [120, 103], [132, 134]]);
        let d = face_chip_details(&lm, CHIP_SIZE, CHIP_PADDING).unwrap();
        let to_chip = mapping_to_chip(&d);
        // The least-squares fit leaves residuals of a few chip pixels for a real face.
        for (p, t) in lm.points.iter().zip(TEMPLATE_5) {
            let q = to_chip.apply([p[0] as f64, p[1] as f64]);
            let want = [
                (CHIP_PADDING + t[0]) / (1.0 + 2.0 * CHIP_PADDING) * CHIP_SIZE as f64,
                (CHIP_PADDING + t[1]) / (1.0 + 2.0 * CHIP_PADDING) * CHIP_SIZE as f64,
            ];
            let err = ((q[0] - want[0]).powi(2) + (q[1] - want[1]).powi(2)).sqrt();
            assert!(err < 6.0, "landmark {p:?} maps to {q:?}, template {want:?}");
        }
    }

    #[test]
    fn the_template_itself_gives_an_unrotated_unit_chip() {
        // Landmarks exactly on the (padded, scaled) template: scale 1, angle 0, the chip
        // rectangle is the chip itself.
        let s = CHIP_SIZE as f64;
        let pts: Vec<[f64; 2]> = TEMPLATE_5
            .iter()
            .map(|t| {
                [
                    (CHIP_PADDING + t[0]) / (1.0 + 2.0 * CHIP_PADDING) * s,
                    (CHIP_PADDING + t[1]) / (1.0 + 2.0 * CHIP_PADDING) * s,
                ]
            })
            .collect();
        let a = similarity_transform(&pts, &pts);
        assert!((a.m[0][0] - 1.0).abs() < TOL && a.m[1][0].abs() < TOL);
        assert!(a.b[0].abs() < TOL && a.b[1].abs() < TOL);
    }

    #[test]
    fn pyramid_level_of_a_constant_image_is_constant() {
        let p = Plane {
            w: 21,
            h: 13,
            data: vec![200; 21 * 13 * 3],
        };
        let d = p.pyramid_down();
        assert_eq!((d.w, d.h), (9, 5));
        assert!(d.data.iter().all(|v| *v == 200), "{:?}", &d.data[..9]);
        let tiny = Plane {
            w: 8,
            h: 30,
            data: vec![1; 8 * 30 * 3],
        };
        assert_eq!(tiny.pyramid_down().w, 0);
    }

    #[test]
    fn pyramid_filter_weights_are_1_4_6_4_1() {
        // A single bright pixel at (row 4, column 6) of an 11x11 image spreads as the outer
        // product of [1 4 6 4 1] / 16 around output (1, 2) (input row 2 + 2r, column 2 + 2c).
        let mut p = Plane {
            w: 11,
            h: 11,
            data: vec![0; 11 * 11 * 3],
        };
        p.data[(4 * 11 + 6) * 3] = 255;
        let d = p.pyramid_down();
        let at = |r: usize, c: usize| d.data[(r * d.w + c) * 3] as u32;
        // Output (r, c) sees input row 4 with weight taps[4 - 2r], column 6 with taps[6 - 2c].
        let taps = [1u32, 4, 6, 4, 1];
        for r in 0..d.h {
            for c in 0..d.w {
                let (dy, dx) = (4i64 - 2 * r as i64, 6i64 - 2 * c as i64);
                let w = if (0..5).contains(&dy) && (0..5).contains(&dx) {
                    taps[dy as usize] * taps[dx as usize]
                } else {
                    0
                };
                assert_eq!(at(r, c), 255 * w / 256, "output ({r}, {c})");
            }
        }
    }

    #[test]
    fn unrotated_unscaled_chip_is_a_plain_copy_with_black_outside() {
        let img = RgbImage::from_fn(40, 30, |x, y| image::Rgb([x as u8, y as u8, 7]));
        let d = ChipDetails {
            rect: DRect {
                left: 30.0,
                top: -2.0,
                right: 39.0 + 5.0,
                bottom: 7.0,
            },
            angle: 0.0,
            rows: 10,
            cols: 15,
        };
        let chip = extract_image_chip(&img, &d).unwrap();
        assert_eq!(chip.get_pixel(0, 2).0, [30, 0, 7]);
        assert_eq!(chip.get_pixel(9, 9).0, [39, 7, 7]);
        assert_eq!(chip.get_pixel(10, 5).0, [0, 0, 0], "right of the image");
        assert_eq!(chip.get_pixel(3, 1).0, [0, 0, 0], "above the image");
    }

    #[test]
    fn degenerate_inputs_are_errors() {
        let same = landmarks([[10, 10]; NUM_LANDMARKS]);
        assert!(face_chip_details(&same, CHIP_SIZE, CHIP_PADDING).is_err());
        let lm = landmarks([[163, 104], [146, 105], [103, 101], [120, 103], [132, 134]]);
        assert!(face_chip_details(&lm, 0, CHIP_PADDING).is_err());
        assert!(face_chip_details(&lm, CHIP_SIZE, f64::NAN).is_err());
        assert!(face_chip_details(&lm, CHIP_SIZE, -0.1).is_err());
        let img = RgbImage::new(64, 64);
        let mut d = face_chip_details(&lm, CHIP_SIZE, CHIP_PADDING).unwrap();
        // The face of these landmarks is far outside a 64x64 image.
        assert!(extract_image_chip(&img, &d).is_err());
        d.angle = f64::NAN;
        assert!(extract_image_chip(&RgbImage::new(300, 300), &d).is_err());
        assert!(extract_image_chip(&RgbImage::new(0, 0), &d).is_err());
    }
}
