//! The tracker's input: per frame, the image size and the face landmarks found in it (or none).
//!
//! Landmarks are MediaPipe Face Mesh points (TRACKING.md section 10): 478 with the attention
//! model's irises (468 = iris centre of the image-left eye, 473 of the other), or the plain 468
//! (then the pupils are not fitted and the eyes stay at their prior). Coordinates are frame
//! pixels in the corner convention (MediaPipe's normalised x, y times width, height). A
//! detector only has to fill this type, so the face crate plugs in without the tracker
//! changing.

use crate::error::{input, Result};

/// Face Mesh with irises (refined / attention model).
pub const MESH_WITH_IRISES: usize = 478;
/// Face Mesh without irises.
pub const MESH_POINTS: usize = 468;

/// Validated face landmarks: 478 or 468 finite points in frame pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct FaceLandmarks {
    points: Vec<[f64; 2]>,
}

impl FaceLandmarks {
    pub fn new(points: Vec<[f64; 2]>) -> Result<Self> {
        if points.len() != MESH_WITH_IRISES && points.len() != MESH_POINTS {
            return Err(input(
                "face landmarks",
                format!(
                    "{} points; expected MediaPipe's {MESH_WITH_IRISES} (with irises) or \
                     {MESH_POINTS}",
                    points.len()
                ),
            ));
        }
        if let Some((i, p)) = points
            .iter()
            .enumerate()
            .find(|(_, p)| !(p[0].is_finite() && p[1].is_finite()))
        {
            return Err(input(
                "face landmarks",
                format!("point {i} is not finite ({}, {})", p[0], p[1]),
            ));
        }
        Ok(Self { points })
    }

    /// From MediaPipe's normalised coordinates (x, y in [0, 1] of the width and height).
    pub fn from_normalized(points: &[[f64; 2]], width: u32, height: u32) -> Result<Self> {
        let (w, h) = (width as f64, height as f64);
        Self::new(points.iter().map(|p| [p[0] * w, p[1] * h]).collect())
    }

    pub fn points(&self) -> &[[f64; 2]] {
        &self.points
    }

    pub fn has_irises(&self) -> bool {
        self.points.len() == MESH_WITH_IRISES
    }

    /// The 468 mesh points (without the iris points).
    pub fn mesh(&self) -> &[[f64; 2]] {
        &self.points[..MESH_POINTS]
    }
}

/// One frame (or photo) as the tracker sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct Observation {
    pub width: u32,
    pub height: u32,
    /// `None`: no face found in this frame.
    pub landmarks: Option<FaceLandmarks>,
}

impl Observation {
    pub fn new(width: u32, height: u32, landmarks: Option<FaceLandmarks>) -> Result<Self> {
        if width == 0 || height == 0 {
            return Err(input(
                "observation",
                format!("image size {width}x{height}: both sides must be positive"),
            ));
        }
        Ok(Self {
            width,
            height,
            landmarks,
        })
    }

    /// A frame in which no face was found.
    pub fn no_face(width: u32, height: u32) -> Result<Self> {
        Self::new(width, height, None)
    }
}
