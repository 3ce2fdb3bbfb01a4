//! Face perception with Google MediaPipe's Apache-2.0 face models, natively in Rust: find
//! faces, place 478 landmarks (468-point mesh plus irises), track them through a video, and
//! matte the person. The results match MediaPipe 0.10.21's Python solutions (`FaceDetection`,
//! `FaceMesh(refine_landmarks=True)`, `SelfieSegmentation`) to float rounding (see the tests
//! and `tools/reference/face_reference.py`), and run faster than them on the CPU.
//!
//! # Using it
//!
//! ```no_run
//! use gagavatar_face::{DetectorModel, FaceDetector, FaceMesh, FaceTracker, SelfieSegmenter};
//! # fn main() -> Result<(), gagavatar_face::FaceError> {
//! # let photo = image::RgbImage::new(640, 480);
//! # let frames: Vec<image::RgbImage> = Vec::new();
//! // A photo: every face (up to 4), best first, with its detection and 478 landmarks.
//! let mesh = FaceMesh::new()?;
//! for face in mesh.process(&photo, 4)? {
//!     let det = face.detection.as_ref().expect("photos always detect");
//!     let [x0, y0, x1, y1] = det.box_pixels(photo.width(), photo.height());
//!     let points = face.landmarks_pixels(photo.width(), photo.height()); // 478 x [x, y, z]
//!     println!("face {:.2} at [{x0}, {y0}, {x1}, {y1}], nose tip {:?}", det.score, points[1]);
//! }
//!
//! // A video: one face, the landmark ROI carried from frame to frame.
//! let mut tracker = FaceTracker::new()?;
//! for frame in &frames {
//!     match tracker.process(frame)? {
//!         Some(face) => { /* face.landmarks: 478 normalised points */ }
//!         None => { /* no face; the next frame runs the detector again */ }
//!     }
//! }
//!
//! // Only boxes and keypoints (faces up to ~5 m with the full-range model).
//! let far = FaceDetector::new(DetectorModel::FullRange)?.detect(&photo)?;
//!
//! // The person matte: an H x W map of probabilities in [0, 1] at the photo's size.
//! let matte = SelfieSegmenter::new()?.matte(&photo)?;
//! # let _ = (far, matte);
//! # Ok(())
//! # }
//! ```
//!
//! Coordinates: normalised landmarks and detections are fractions of the image width (x,
//! right) and height (y, down), as MediaPipe reports them; `z` is in the unit of x, negative
//! toward the camera. The `*_pixels` helpers multiply by the size (x and z by the width, y by
//! the height). Keypoint and landmark sides are the subject's: keypoint 0 and landmarks 33 /
//! 468 are the subject's right eye and iris (image left in an unmirrored photo).
//!
//! [`pool::set_threads`] sets how many threads the networks use (default: all cores).
//!
//! # What is inside
//!
//! | module | job |
//! |---|---|
//! | [`detection`] | the detector pipeline: letterbox, network, SSD decoding, weighted NMS, projection |
//! | [`face_mesh`] | [`FaceLandmarker`] (one ROI), [`FaceMesh`] (photos), [`FaceTracker`] (video) |
//! | [`matte`] | [`SelfieSegmenter`]: the 256x256 segmentation resized to the image |
//! | [`roi`] | the landmark crop from a detection or from the previous landmarks |
//! | [`detection_net`], [`mesh_net`], [`selfie_net`] | the four networks, one struct each, weights by TFLite layer name |
//! | [`anchors`] | the detectors' SSD anchors |
//! | [`warp`] | image to tensor exactly as MediaPipe (OpenCV's fixed-point bilinear warp) |
//! | [`layers`], [`kernels`], [`simd`], [`tensor`], [`pool`] | a small NHWC f32 inference engine: fused 1x1 / depthwise / full convolutions on AVX-512 or portable lanes, recycled buffers, a spinning thread pool |
//! | [`weights`] | the shipped weights (compiled in) and strict loading through candle's `VarBuilder` |
//! | [`overlay`] | drawing boxes, keypoints and landmarks for inspection |
//!
//! # Weights
//!
//! `weights/*.safetensors` hold the models of the PyPI wheel `mediapipe==0.10.21`
//! (face_detection_short_range, face_detection_full_range_sparse densified,
//! face_landmark_with_attention, selfie_segmentation), converted by
//! `tools/convert_mediapipe_face.py`, which checks every source file's sha256; each file's
//! metadata records the source, version, hashes and licence, and `weights/NOTICE` and
//! `weights/LICENSE` carry the Apache-2.0 terms. They are compiled into the library (3.9 MB):
//! nothing is downloaded or read at run time. [`weights::WeightsFile`] loads other files and
//! refuses one whose keys or shapes differ from the network's.

pub mod anchors;
pub mod detection;
pub mod detection_net;
pub mod error;
pub mod face_mesh;
pub mod kernels;
pub mod layers;
pub mod matte;
pub mod mesh_net;
pub mod overlay;
pub mod pool;
pub mod roi;
pub mod selfie_net;
pub mod simd;
pub mod tensor;
pub mod warp;
pub mod weights;

pub use detection::{Detection, DetectorModel, FaceDetector};
pub use error::FaceError;
pub use face_mesh::{Face, FaceLandmarker, FaceMesh, FaceTracker, Landmarks, NUM_LANDMARKS};
pub use matte::{Matte, SelfieSegmenter};
