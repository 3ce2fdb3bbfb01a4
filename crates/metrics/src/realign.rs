//! Realignment before scoring: the result and its reference (the ground-truth target in self
//! reenactment, the driver in cross reenactment) are cut to the *same* head crop, defined by
//! the reference's landmarks, and resized to 512 x 512.
//!
//! Definition (the README's "Evaluation protocol"):
//! 1. MediaPipe's 478 landmarks are found on the reference image (`crates/face`, static photo
//!    mode, the best face);
//! 2. the tracker's framing rule turns them into a head box and the release's crop window
//!    (`FramingCalibration::head_box`, `CropWindow::from_head_box`: a square of 1.65 x the head
//!    box side, calibrated on the release's own crops, so a release-cropped frame maps onto
//!    itself up to a few pixels);
//! 3. both images are cut through that window with the release's antialiased bilinear resize
//!    to 512 x 512, black outside the frame (`gagavatar_track::crop::crop_image`). A result of
//!    another size than the reference (a 64-pixel model on 512 data) is first resized to the
//!    reference's size (bilinear, triangle filter), since it is rendered in the reference's
//!    camera.
//!
//! When no face is found on the reference, the window is the whole frame (the frame is
//! resized to 512); the pair's scores then say so (`realigned = false`).

use gagavatar_face::face_mesh::FaceMesh;
use gagavatar_track::crop::{crop_image, CropWindow, FramingCalibration, CROP_PX};
use gagavatar_track::observation::FaceLandmarks;
use image::RgbImage;

use crate::error::{input_err, Result};

/// Side of the realigned images.
pub const REALIGN_SIZE: u32 = CROP_PX;

/// The head crop shared by a result and its reference.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Realignment {
    /// In the reference's pixels.
    pub window: CropWindow,
    /// `false`: no face on the reference, the window is the whole frame.
    pub from_landmarks: bool,
}

/// The best face's 478 landmarks in pixels, `None` when no face is found.
pub fn detect_landmarks(mesh: &FaceMesh, img: &RgbImage) -> Result<Option<FaceLandmarks>> {
    let faces = mesh
        .process(img, 1)
        .map_err(|e| input_err("image", format!("face landmarks: {e}")))?;
    let Some(face) = faces.first() else {
        return Ok(None);
    };
    let pts: Vec<[f64; 2]> = face
        .landmarks_pixels(img.width(), img.height())
        .iter()
        .map(|p| [p[0] as f64, p[1] as f64])
        .collect();
    FaceLandmarks::new(pts)
        .map(Some)
        .map_err(|e| input_err("face landmarks", e.to_string()))
}

impl Realignment {
    /// The whole frame of a `width x height` image.
    pub fn whole_frame(width: u32, height: u32) -> Result<Self> {
        if width == 0 || height == 0 {
            return Err(input_err("image", format!("{width}x{height} is empty")));
        }
        Ok(Self {
            window: CropWindow {
                x0: 0,
                y0: 0,
                x1: width as i64,
                y1: height as i64,
            },
            from_landmarks: false,
        })
    }

    /// The crop the reference's landmarks define (`None`: the whole frame).
    pub fn from_reference(
        landmarks: Option<&FaceLandmarks>,
        framing: &FramingCalibration,
        width: u32,
        height: u32,
    ) -> Result<Self> {
        let Some(lm) = landmarks else {
            return Self::whole_frame(width, height);
        };
        let head = framing
            .head_box(lm)
            .map_err(|e| input_err("reference landmarks", e.to_string()))?;
        let window = CropWindow::from_head_box(&head)
            .map_err(|e| input_err("reference landmarks", e.to_string()))?;
        Ok(Self {
            window,
            from_landmarks: true,
        })
    }

    /// Finds the reference's landmarks and returns its crop.
    pub fn detect(
        mesh: &FaceMesh,
        framing: &FramingCalibration,
        reference: &RgbImage,
    ) -> Result<Self> {
        let lm = detect_landmarks(mesh, reference)?;
        Self::from_reference(lm.as_ref(), framing, reference.width(), reference.height())
    }

    /// `img` (the reference, or a result at any size showing the reference's frame) cut to the
    /// shared crop, `REALIGN_SIZE` square. `reference_size` is the reference's `(width,
    /// height)`.
    pub fn apply(&self, img: &RgbImage, reference_size: (u32, u32)) -> Result<RgbImage> {
        let (rw, rh) = reference_size;
        if img.width() == 0 || img.height() == 0 || rw == 0 || rh == 0 {
            return Err(input_err(
                "image",
                format!(
                    "{}x{} image or {rw}x{rh} reference is empty",
                    img.width(),
                    img.height()
                ),
            ));
        }
        let resized;
        let img = if (img.width(), img.height()) == (rw, rh) {
            img
        } else {
            resized = image::imageops::resize(img, rw, rh, image::imageops::FilterType::Triangle);
            &resized
        };
        crop_image(img, &self.window).map_err(|e| input_err("realignment", e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: u32, h: u32) -> RgbImage {
        RgbImage::from_fn(w, h, |x, y| {
            image::Rgb([(x % 256) as u8, (y % 256) as u8, 7])
        })
    }

    #[test]
    fn whole_frame_resizes_to_512_and_keeps_a_512_frame() {
        let img = ramp(512, 512);
        let r = Realignment::whole_frame(512, 512).unwrap();
        assert!(!r.from_landmarks);
        let out = r.apply(&img, (512, 512)).unwrap();
        assert_eq!(out.dimensions(), (REALIGN_SIZE, REALIGN_SIZE));
        assert_eq!(
            out.as_raw(),
            img.as_raw(),
            "identity window must copy the frame"
        );
        let small = r.apply(&ramp(64, 64), (512, 512)).unwrap();
        assert_eq!(small.dimensions(), (512, 512));
    }

    #[test]
    fn empty_inputs_are_errors() {
        assert!(Realignment::whole_frame(0, 4).is_err());
        let r = Realignment::whole_frame(4, 4).unwrap();
        assert!(r.apply(&RgbImage::new(0, 0), (4, 4)).is_err());
        assert!(r.apply(&RgbImage::new(4, 4), (0, 4)).is_err());
    }

    #[test]
    fn no_landmarks_means_whole_frame() {
        let r = Realignment::from_reference(None, &FramingCalibration::default(), 30, 20).unwrap();
        assert_eq!(r.window.as_array(), [0, 0, 30, 20]);
    }
}
