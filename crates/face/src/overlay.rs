//! A picture of what was found, for looking at: detection boxes, the six keypoints, the 478
//! landmarks (irises in their own colour), drawn onto a copy of the image.

use image::{Rgb, RgbImage};

use crate::detection::Detection;

const BOX: Rgb<u8> = Rgb([40, 230, 80]);
const MESH: Rgb<u8> = Rgb([60, 200, 255]);
const IRIS: Rgb<u8> = Rgb([255, 220, 0]);
/// Right eye, left eye, nose tip, mouth, right ear, left ear.
const KEYPOINTS: [Rgb<u8>; 6] = [
    Rgb([255, 40, 40]),
    Rgb([255, 40, 200]),
    Rgb([255, 140, 0]),
    Rgb([160, 60, 255]),
    Rgb([255, 255, 255]),
    Rgb([120, 120, 120]),
];

/// What to draw for one face, in pixels of the image drawn on.
pub struct FaceDrawing<'a> {
    pub detection: Option<&'a Detection>,
    /// (x, y) per landmark, any count (478 expected: points 468.. are drawn as irises).
    pub landmarks: &'a [[f32; 2]],
}

/// Draws the faces onto a copy of `img`; sizes scale with each face.
pub fn draw(img: &RgbImage, faces: &[FaceDrawing]) -> RgbImage {
    let mut out = img.clone();
    let (w, h) = (img.width() as f32, img.height() as f32);
    for f in faces {
        let side = match f.detection {
            Some(d) => (d.width * w).max(d.height * h),
            None => extent(f.landmarks),
        }
        .max(8.0);
        if let Some(d) = f.detection {
            let t = (side / 120.0).clamp(1.0, 6.0).round() as i32;
            let [x0, y0, x1, y1] = d.box_pixels(img.width(), img.height());
            rect(&mut out, x0, y0, x1, y1, t, BOX);
            let r = (side / 40.0).clamp(2.0, 12.0);
            for (k, p) in d
                .keypoints_pixels(img.width(), img.height())
                .iter()
                .enumerate()
            {
                disc(&mut out, p[0], p[1], r, KEYPOINTS[k]);
            }
        }
        let r = (side / 250.0).clamp(0.7, 4.0);
        for (i, p) in f.landmarks.iter().enumerate() {
            disc(&mut out, p[0], p[1], r, if i >= 468 { IRIS } else { MESH });
        }
    }
    out
}

fn extent(pts: &[[f32; 2]]) -> f32 {
    let (mut x0, mut x1, mut y0, mut y1) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
    for p in pts {
        x0 = x0.min(p[0]);
        x1 = x1.max(p[0]);
        y0 = y0.min(p[1]);
        y1 = y1.max(p[1]);
    }
    if pts.is_empty() {
        0.0
    } else {
        (x1 - x0).max(y1 - y0)
    }
}

fn put(img: &mut RgbImage, x: i32, y: i32, c: Rgb<u8>) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, c);
    }
}

/// A filled disc of radius `r` centred at pixel coordinates (x, y) (pixel centres at +0.5).
fn disc(img: &mut RgbImage, x: f32, y: f32, r: f32, c: Rgb<u8>) {
    if !(x.is_finite() && y.is_finite()) {
        return;
    }
    let (x0, x1) = ((x - r).floor() as i32, (x + r).ceil() as i32);
    let (y0, y1) = ((y - r).floor() as i32, (y + r).ceil() as i32);
    for py in y0..=y1 {
        for px in x0..=x1 {
            let (dx, dy) = (px as f32 + 0.5 - x, py as f32 + 0.5 - y);
            if dx * dx + dy * dy <= r * r + 0.25 {
                put(img, px, py, c);
            }
        }
    }
}

/// A rectangle outline `t` pixels thick.
fn rect(img: &mut RgbImage, x0: f32, y0: f32, x1: f32, y1: f32, t: i32, c: Rgb<u8>) {
    if ![x0, y0, x1, y1].iter().all(|v| v.is_finite()) {
        return;
    }
    let (x0, y0, x1, y1) = (
        x0.round() as i32,
        y0.round() as i32,
        x1.round() as i32,
        y1.round() as i32,
    );
    let (w, h) = (img.width() as i32, img.height() as i32);
    for k in 0..t {
        for x in x0.max(-1)..=x1.min(w) {
            put(img, x, y0 + k, c);
            put(img, x, y1 - k, c);
        }
        for y in y0.max(-1)..=y1.min(h) {
            put(img, x0 + k, y, c);
            put(img, x1 - k, y, c);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_inside_and_clips_outside() {
        let img = RgbImage::new(40, 30);
        let d = Detection {
            score: 0.9,
            xmin: 0.25,
            ymin: 0.2,
            width: 0.5,
            height: 0.6,
            keypoints: [
                [0.4, 0.4],
                [0.6, 0.4],
                [0.5, 0.5],
                [0.5, 0.6],
                [0.3, 0.45],
                [2.0, -1.0],
            ],
        };
        let lm = vec![[20.0, 15.0], [-5.0, 100.0], [f32::NAN, 1.0]];
        let out = draw(
            &img,
            &[FaceDrawing {
                detection: Some(&d),
                landmarks: &lm,
            }],
        );
        assert_eq!(*out.get_pixel(10, 6), BOX);
        assert_eq!(*out.get_pixel(20, 15), MESH);
        assert_eq!(*out.get_pixel(0, 0), Rgb([0, 0, 0]));
    }
}
