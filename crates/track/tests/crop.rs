//! The crop rule, the crop itself against `gagavatar_ops`' PyTorch-matched resize, the matte
//! composite, the framing calibration and the video window smoothing.

mod common;

use candle_core::{Device, Tensor};
use gagavatar_ops::resample::{resize, ResizeMode};
use gagavatar_track::crop::{
    apply_matte, crop_image, framing_stats, smooth_head_boxes, CropWindow, FramingCalibration,
    HeadBox,
};
use gagavatar_track::observation::FaceLandmarks;
use image::RgbImage;

#[test]
fn window_follows_the_release_rule() {
    // Centre (150, 110), sides 100 x 120: S = 1.65 sqrt(12000) = 180.75, half 90.37.
    let b = HeadBox::new(100.0, 50.0, 200.0, 170.0).unwrap();
    let w = CropWindow::from_head_box(&b).unwrap();
    assert_eq!(w.as_array(), [59, 19, 240, 200]);
    // Corners left of / above the frame truncate toward zero like Python's `.long()`.
    let b = HeadBox::square([10.0, 10.0], 100.0).unwrap();
    let w = CropWindow::from_head_box(&b).unwrap();
    assert_eq!(w.as_array(), [-72, -72, 92, 92]);
    // Absurd boxes (landmarks at 1e12) are refused, not overflowed.
    let far = HeadBox::square([1e12, 0.0], 10.0).unwrap();
    assert!(CropWindow::from_head_box(&far).is_err());
    let huge = CropWindow {
        x0: i64::MIN,
        y0: 0,
        x1: i64::MAX,
        y1: 10,
    };
    assert!(crop_image(&RgbImage::new(4, 4), &huge).is_err());
    // Frame <-> crop pixels: the window's edges map onto the crop's.
    let p = w.frame_to_crop([-72.0, 92.0]);
    assert!(p[0].abs() < 1e-12 && (p[1] - 512.0).abs() < 1e-12);
    let q = w.crop_to_frame(w.frame_to_crop([13.25, -4.5]));
    assert!((q[0] - 13.25).abs() < 1e-12 && (q[1] + 4.5).abs() < 1e-12);
    // The release `bbox` field: the head box in the crop / 512, clamped.
    let nb = w.normalized_box(&HeadBox::new(-100.0, 0.0, 10.0, 50.0).unwrap());
    assert_eq!(nb[0], 0.0);
    assert!(nb.iter().all(|v| (0.0..=1.0).contains(v)));
}

fn test_image(w: u32, h: u32) -> RgbImage {
    RgbImage::from_fn(w, h, |x, y| {
        let v = |k: u32| ((x * 7 + y * 13 + k * 71) % 256) as u8;
        image::Rgb([v(0), v(1), v(2)])
    })
}

/// Reference: the window cut out with zeros outside the frame, then `gagavatar_ops`'
/// antialiased bilinear (its weights are PyTorch's, checked by the ops crate's goldens).
fn reference_crop(img: &RgbImage, w: &CropWindow) -> Vec<f32> {
    let (ww, wh) = (w.width() as usize, w.height() as usize);
    let mut data = vec![0f32; 3 * wh * ww];
    for y in 0..wh {
        for x in 0..ww {
            let (fx, fy) = (w.x0 + x as i64, w.y0 + y as i64);
            if fx >= 0 && fy >= 0 && (fx as u32) < img.width() && (fy as u32) < img.height() {
                let p = img.get_pixel(fx as u32, fy as u32);
                for c in 0..3 {
                    data[(c * wh + y) * ww + x] = p[c] as f32;
                }
            }
        }
    }
    let t = Tensor::from_vec(data, (1, 3, wh, ww), &Device::Cpu).unwrap();
    let r = resize(&t, 512, 512, ResizeMode::Antialias).unwrap();
    r.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

#[test]
fn crop_matches_the_reference_resize() {
    // Upscaling (window smaller than 512) and downscaling, both reaching outside the frame.
    for (iw, ih, win) in [
        (
            97u32,
            61u32,
            CropWindow {
                x0: -20,
                y0: -5,
                x1: 80,
                y1: 95,
            },
        ),
        (
            1500,
            1100,
            CropWindow {
                x0: 900,
                y0: 500,
                x1: 1700,
                y1: 1300,
            },
        ),
    ] {
        let img = test_image(iw, ih);
        let got = crop_image(&img, &win).unwrap();
        assert_eq!(got.dimensions(), (512, 512));
        let want = reference_crop(&img, &win);
        let mut worst = 0f32;
        for y in 0..512usize {
            for x in 0..512usize {
                for c in 0..3 {
                    let g = got.get_pixel(x as u32, y as u32)[c] as f32;
                    let r = want[(c * 512 + y) * 512 + x];
                    worst = worst.max((g - r).abs());
                }
            }
        }
        // Rounding to 8 bits (0.5) plus f32 summation-order differences.
        assert!(
            worst <= 0.5 + 1e-3,
            "window {:?}: worst difference {worst}",
            win.as_array()
        );
    }
    // Fully outside the frame: black.
    let img = test_image(50, 50);
    let far = crop_image(
        &img,
        &CropWindow {
            x0: 100,
            y0: 100,
            x1: 200,
            y1: 200,
        },
    )
    .unwrap();
    assert!(far.as_raw().iter().all(|&v| v == 0));
}

#[test]
fn matte_composites_on_black_with_truncation() {
    let img = RgbImage::from_fn(2, 2, |x, y| image::Rgb([255, 100 + x as u8, 3 + y as u8]));
    let out = apply_matte(&img, &[1.0, 0.0, 0.5, 0.25]).unwrap();
    assert_eq!(out.get_pixel(0, 0).0, [255, 100, 3]);
    assert_eq!(out.get_pixel(1, 0).0, [0, 0, 0]);
    // 255 * 0.5 = 127.5 -> 127 (the release casts to uint8, truncating).
    assert_eq!(out.get_pixel(0, 1).0, [127, 50, 2]);
    assert_eq!(out.get_pixel(1, 1).0, [63, 25, 1]);
    assert!(apply_matte(&img, &[1.0; 3]).is_err());
    assert!(apply_matte(&img, &[1.0, f32::NAN, 0.0, 0.0]).is_err());
    assert!(apply_matte(&img, &[1.0, f32::INFINITY, 0.0, 0.0]).is_err());
    // Overshoots of a soft matte are clamped.
    let c = apply_matte(&img, &[1.5, -0.2, 0.5, 0.25]).unwrap();
    assert_eq!(c.get_pixel(0, 0).0, [255, 100, 3]);
    assert_eq!(c.get_pixel(1, 0).0, [0, 0, 0]);
}

/// A plausible 478-point face: an elliptic mesh of given height around `centre`, turned by
/// `roll`, irises on the eye line.
fn fake_face(centre: [f64; 2], height: f64, roll: f64) -> FaceLandmarks {
    let (s, c) = roll.sin_cos();
    let place = |x: f64, y: f64| [centre[0] + c * x - s * y, centre[1] + s * x + c * y];
    let mut pts = Vec::with_capacity(478);
    for i in 0..468 {
        let a = i as f64 * 0.7;
        let r = ((i * 37) % 100) as f64 / 100.0;
        pts.push(place(
            0.4 * height * r * a.cos(),
            0.5 * height * r * a.sin(),
        ));
    }
    // The mesh's extreme points along the face's up axis: top and bottom.
    pts[10] = place(0.0, -0.5 * height);
    pts[152] = place(0.0, 0.5 * height);
    for _ in 468..478 {
        pts.push(place(0.0, 0.0));
    }
    // Eyes a third of the way up.
    pts[468] = place(-0.17 * height, -0.25 * height);
    pts[473] = place(0.17 * height, -0.25 * height);
    FaceLandmarks::new(pts).unwrap()
}

fn in_crop(lm: &FaceLandmarks, w: &CropWindow) -> FaceLandmarks {
    FaceLandmarks::new(lm.points().iter().map(|&p| w.frame_to_crop(p)).collect()).unwrap()
}

/// Cropping with the calibrated head box reproduces the calibration's framing (up to the
/// window's integer truncation), upright and tilted.
#[test]
fn calibrated_crop_frames_the_face_like_the_release() {
    let cal = FramingCalibration::default();
    for (centre, height, roll) in [
        ([320.0, 240.0], 180.0, 0.0),
        ([900.0, 500.0], 420.0, 0.35),
        ([60.0, 70.0], 90.0, -0.2),
    ] {
        let lm = fake_face(centre, height, roll);
        let b = cal.head_box(&lm).unwrap();
        let w = CropWindow::from_head_box(&b).unwrap();
        let st = framing_stats(&in_crop(&lm, &w), 512.0);
        // One pixel of truncation in the frame is 512 / window-side crop pixels.
        let tol = 2.0 * 512.0 / w.width() as f64 + 1e-9;
        // The eyes sit at the calibrated offset from the crop centre in the face's own frame
        // (turned with the eye line), so a tilted head is framed like an upright one.
        let d = [st.eye_centre[0] - 256.0, st.eye_centre[1] - 256.0];
        let (s, c) = roll.sin_cos();
        let upright = [c * d[0] + s * d[1] + 256.0, -s * d[0] + c * d[1] + 256.0];
        let want = [cal.eye_centre[0] * 512.0, cal.eye_centre[1] * 512.0];
        for got in [upright, st.eye_centre_face] {
            assert!(
                (got[0] - want[0]).abs() <= tol && (got[1] - want[1]).abs() <= tol,
                "roll {roll}: eye centre in the face frame {got:?}, expected {want:?} (tol {tol})"
            );
        }
        assert!(
            (st.face_height - cal.face_height * 512.0).abs() <= tol,
            "roll {roll}: face height {}, expected {}",
            st.face_height,
            cal.face_height * 512.0
        );
    }
}

#[test]
fn calibration_is_remeasured_from_crops() {
    // Crops framed at (250, 205) with a height of 290 px, three of them (the median of three).
    let crops: Vec<FaceLandmarks> = [0.9, 1.0, 1.1]
        .iter()
        .map(|&k: &f64| {
            let h = 290.0 * k;
            // Eye centre at (250, 205): the fake face's eyes sit 0.25 height above its centre.
            fake_face([250.0, 205.0 + 0.25 * h], h, 0.0)
        })
        .collect();
    let cal = FramingCalibration::measure(&crops, 512.0).unwrap();
    assert!((cal.eye_centre[0] * 512.0 - 250.0).abs() < 1e-9);
    assert!((cal.eye_centre[1] * 512.0 - 205.0).abs() < 1e-9);
    assert!((cal.face_height * 512.0 - 290.0).abs() < 1e-9);
    assert!(FramingCalibration::measure(&[], 512.0).is_err());
}

#[test]
fn video_boxes_are_smoothed_and_gaps_filled() {
    // A still head with +-3 px jitter, and frames 5..8 without a face.
    let mut boxes = vec![];
    for i in 0..40 {
        let j = if i % 2 == 0 { 3.0 } else { -3.0 };
        boxes.push(if (5..8).contains(&i) {
            None
        } else {
            Some(HeadBox::square([200.0 + j, 150.0 - j], 100.0 + j).unwrap())
        });
    }
    let sm = smooth_head_boxes(&boxes, 1e4).unwrap();
    assert_eq!(sm.len(), 40);
    for (i, b) in sm.iter().enumerate() {
        let c = b.centre();
        // Within the jitter's bias (the gap removes two -3 frames and one +3 frame).
        assert!(
            (c[0] - 200.0).abs() < 1.0 && (c[1] - 150.0).abs() < 1.0,
            "frame {i}: centre {c:?}"
        );
        assert!(
            (b.mean_side() - 100.0).abs() < 1.0,
            "frame {i}: side {}",
            b.mean_side()
        );
        // The +-3 px alternation is gone: neighbouring windows differ by hundredths.
        if i > 0 {
            let p = sm[i - 1].centre();
            assert!(
                (c[0] - p[0]).abs() < 0.05 && (c[1] - p[1]).abs() < 0.05,
                "frame {i}: moved from {p:?} to {c:?}"
            );
        }
    }
    assert!(smooth_head_boxes(&[None, None], 1.0).is_err());
}
