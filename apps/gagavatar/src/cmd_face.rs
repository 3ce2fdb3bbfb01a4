//! `gagavatar face`: find faces in a photo, their 478 landmarks, and the person matte.

use anyhow::{Context, Result};
use clap::Args;
use gagavatar_face::detection::{DetectorModel, FaceDetector};
use gagavatar_face::face_mesh::FaceMesh;
use gagavatar_face::matte::{resize_linear, SelfieSegmenter};
use gagavatar_face::overlay::{self, FaceDrawing};
use gagavatar_formats::atomic::write_atomic;
use gagavatar_formats::image::{read_image, DecodeOptions};
use serde::Serialize;
use std::path::PathBuf;

/// Photos larger than this (long side, pixels) are processed downscaled; coordinates are still
/// reported in the original's pixels. The networks see 128 to 256 px inputs, so nothing is lost.
const WORK_SIDE: u32 = 4096;
/// Smaller images are refused: no face fits in them.
const MIN_SIDE: u32 = 16;

#[derive(Debug, Args)]
#[command(
    after_help = "Prints one line per face (or \"no face found\"). Coordinates are pixels of the \
photo as displayed (its EXIF orientation applied): x right, y down, z in the unit of x (negative \
toward the camera). The overlay is written at the processed size (photos over 4096 px are downscaled), \
the matte at the photo's size.\n\nExamples:\n  gagavatar face me.jpg --json me.json -o me_overlay.png --matte me_matte.png\n  \
gagavatar face group.png --max-faces 8 --full-range --json group.json"
)]
pub struct FaceArgs {
    /// The photo (PNG, JPEG, WebP or BMP; the format is read from the content).
    pub image: PathBuf,
    /// Write the faces as JSON: {"width", "height", "faces": [{"score", "box": [x0,y0,x1,y1],
    /// "keypoints": [[x,y] x6], "presence", "landmarks": [[x,y,z] x478]}]}.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write a PNG with the boxes, keypoints and landmarks drawn on the photo.
    #[arg(short = 'o', long = "overlay")]
    pub overlay: Option<PathBuf>,
    /// Write the person matte (selfie segmentation) as an 8-bit grey PNG at the photo's size.
    #[arg(long)]
    pub matte: Option<PathBuf>,
    /// Landmark at most this many faces (best scores first).
    #[arg(long, default_value_t = 4)]
    pub max_faces: usize,
    /// Detect with the full-range model (faces up to about 5 m away) instead of short range.
    #[arg(long)]
    pub full_range: bool,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
}

#[derive(Serialize)]
struct FaceJson {
    score: f32,
    #[serde(rename = "box")]
    bbox: [f32; 4],
    keypoints: Vec<[f32; 2]>,
    /// The landmark model's face presence (sigmoid of its flag).
    presence: f32,
    landmarks: Vec<[f32; 3]>,
}

#[derive(Serialize)]
struct OutputJson {
    width: u32,
    height: u32,
    faces: Vec<FaceJson>,
}

pub fn run(args: FaceArgs) -> Result<()> {
    if let Some(t) = args.threads {
        gagavatar_face::pool::set_threads(t);
    }
    let opts = DecodeOptions {
        min_side: MIN_SIDE,
        fit_within: Some(WORK_SIDE),
    };
    let decoded = read_image(&args.image, &opts)?;
    let img = &decoded.rgb;
    let (ow, oh) = (decoded.original_width, decoded.original_height);

    let mesh = FaceMesh::new().context("loading the face models")?;
    let detector = if args.full_range {
        FaceDetector::new(DetectorModel::FullRange).context("loading the full-range detector")?
    } else {
        mesh.detector.clone()
    };
    let detections = detector.detect(img)?;
    let faces = mesh.landmark_detections(img, detections, args.max_faces);

    // Normalised coordinates times the original size: pixels of the photo as stored.
    let (fw, fh) = (ow as f32, oh as f32);
    let out = OutputJson {
        width: ow,
        height: oh,
        faces: faces
            .iter()
            .map(|f| {
                let d = f.detection.as_ref();
                FaceJson {
                    score: d.map_or(f.presence, |d| d.score),
                    bbox: d.map_or([0.0; 4], |d| d.box_pixels(ow, oh)),
                    keypoints: d.map_or(Vec::new(), |d| d.keypoints_pixels(ow, oh).to_vec()),
                    presence: f.presence,
                    landmarks: f
                        .landmarks
                        .iter()
                        .map(|p| [p[0] * fw, p[1] * fh, p[2] * fw])
                        .collect(),
                }
            })
            .collect(),
    };
    if out.faces.is_empty() {
        println!("no face found");
    }
    for (i, f) in out.faces.iter().enumerate() {
        println!(
            "face {i}: score {:.3}, box [{:.1}, {:.1}, {:.1}, {:.1}], {} landmarks",
            f.score,
            f.bbox[0],
            f.bbox[1],
            f.bbox[2],
            f.bbox[3],
            f.landmarks.len()
        );
    }

    if let Some(path) = &args.json {
        let text = serde_json::to_string(&out)?;
        write_atomic(path, text.as_bytes())?;
    }
    if let Some(path) = &args.overlay {
        let (w, h) = (img.width() as f32, img.height() as f32);
        let pts: Vec<Vec<[f32; 2]>> = faces
            .iter()
            .map(|f| f.landmarks.iter().map(|p| [p[0] * w, p[1] * h]).collect())
            .collect();
        let drawings: Vec<FaceDrawing> = faces
            .iter()
            .zip(&pts)
            .map(|(f, p)| FaceDrawing {
                detection: f.detection.as_ref(),
                landmarks: p,
            })
            .collect();
        let pic = overlay::draw(img, &drawings);
        write_png(path, &image::DynamicImage::ImageRgb8(pic))?;
    }
    if let Some(path) = &args.matte {
        let seg = SelfieSegmenter::new().context("loading the segmentation model")?;
        let m = seg.mask256(img)?;
        let full = resize_linear(&m.data, m.w, m.h, ow as usize, oh as usize);
        let grey = image::GrayImage::from_fn(ow, oh, |x, y| {
            image::Luma([(full[(y * ow + x) as usize].clamp(0.0, 1.0) * 255.0).round() as u8])
        });
        write_png(path, &image::DynamicImage::ImageLuma8(grey))?;
    }
    Ok(())
}

fn write_png(path: &std::path::Path, img: &image::DynamicImage) -> Result<()> {
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )
    .with_context(|| format!("encoding {}", path.display()))?;
    write_atomic(path, &bytes)?;
    Ok(())
}
