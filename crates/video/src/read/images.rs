//! A folder of images, or one image, read as a video: files in natural name order (`frame2`
//! before `frame10`), each decoded by its content with its EXIF orientation
//! ([`gagavatar_formats::image::read_image`]), at a frame rate the caller gives.

use std::cmp::Ordering;
use std::path::{Path, PathBuf};

use gagavatar_formats::image::{read_image, DecodeOptions, DecodedImage};

use super::source::{Decoder, RawFrame, Source, Start, VideoMeta, PTS_EPS};
use crate::VideoError;

/// File extensions taken from a folder (any case); other files (a `frames.json`, hidden files)
/// are ignored.
pub const IMAGE_EXTENSIONS: [&str; 5] = ["png", "jpg", "jpeg", "webp", "bmp"];

/// Compares names as a person would: runs of digits by their value, the rest by character
/// (`frame2` < `frame10`, `a01` < `a1b`); ties fall back to plain byte order.
pub fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (mut x, mut y) = (a.as_bytes(), b.as_bytes());
    loop {
        match (x.first(), y.first()) {
            (None, None) => return a.cmp(b),
            (None, Some(_)) => return Ordering::Less,
            (Some(_), None) => return Ordering::Greater,
            (Some(c), Some(d)) if c.is_ascii_digit() && d.is_ascii_digit() => {
                let n = x.iter().take_while(|c| c.is_ascii_digit()).count();
                let m = y.iter().take_while(|c| c.is_ascii_digit()).count();
                let (dx, dy) = (&x[..n], &y[..m]);
                // Compare values without parsing (runs may be longer than any integer type).
                let tx = trim_zeros(dx);
                let ty = trim_zeros(dy);
                let ord = tx.len().cmp(&ty.len()).then_with(|| tx.cmp(ty));
                if ord != Ordering::Equal {
                    return ord;
                }
                x = &x[n..];
                y = &y[m..];
            }
            (Some(c), Some(d)) => {
                if c != d {
                    return c.cmp(d);
                }
                x = &x[1..];
                y = &y[1..];
            }
        }
    }
}

fn trim_zeros(d: &[u8]) -> &[u8] {
    let z = d.iter().take_while(|&&c| c == b'0').count();
    &d[z..]
}

/// The image files of a folder in natural name order.
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>, VideoError> {
    let entries = std::fs::read_dir(dir).map_err(|e| VideoError::io(dir, e))?;
    let mut files = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| VideoError::io(dir, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') {
            continue;
        }
        let ext_ok = Path::new(&name)
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| IMAGE_EXTENSIONS.iter().any(|x| x.eq_ignore_ascii_case(e)));
        let path = entry.path();
        if ext_ok && path.is_file() {
            files.push((name, path));
        }
    }
    files.sort_by(|a, b| natural_cmp(&a.0, &b.0));
    Ok(files.into_iter().map(|(_, p)| p).collect())
}

fn decode(path: &Path) -> Result<DecodedImage, VideoError> {
    // The formats crate's messages already name the file.
    read_image(path, &DecodeOptions::default()).map_err(|e| VideoError::NotVideo {
        path: path.to_path_buf(),
        reason: match e {
            gagavatar_formats::FormatError::Image { reason, .. } => reason,
            other => other.to_string(),
        },
    })
}

pub(crate) struct ImagesSource {
    files: Vec<PathBuf>,
    next: usize,
    fps: f64,
    /// The first image, decoded to learn the size; handed out as frame 0.
    first: Option<DecodedImage>,
    size: (u32, u32),
}

impl ImagesSource {
    /// `files` in order (at least one), shown at `fps`.
    pub(crate) fn open(
        what: &Path,
        files: Vec<PathBuf>,
        fps: f64,
        start: Start,
    ) -> Result<(Self, VideoMeta), VideoError> {
        let Some(first_path) = files.first() else {
            return Err(VideoError::NoVideoFrames {
                path: what.to_path_buf(),
                reason: format!(
                    "the folder holds no images ({})",
                    IMAGE_EXTENSIONS.join(", ")
                ),
            });
        };
        let first = decode(first_path)?;
        let size = (first.rgb.width(), first.rgb.height());
        let n = files.len();
        let meta = VideoMeta {
            width: size.0,
            height: size.1,
            fps,
            frames: Some(n as u64),
            duration: Some(n as f64 / fps),
            codec: first.kind.name().to_ascii_lowercase(),
            profile: None,
            rotation: 0,
            start_time: 0.0,
            decoder: Decoder::Image,
        };
        let skip = match start {
            Start::Frame(i) => usize::try_from(i).unwrap_or(usize::MAX),
            Start::Seconds(t) => (t * fps - PTS_EPS * fps).ceil().max(0.0) as usize,
        };
        let next = skip.min(n);
        Ok((
            ImagesSource {
                files,
                next,
                fps,
                first: (next == 0).then_some(first),
                size,
            },
            meta,
        ))
    }
}

impl Source for ImagesSource {
    fn next_frame(&mut self) -> Option<Result<RawFrame, VideoError>> {
        let i = self.next;
        let path = self.files.get(i)?;
        self.next += 1;
        let img = match self.first.take() {
            Some(img) => img,
            None => match decode(path) {
                Ok(img) => img,
                Err(e) => return Some(Err(e)),
            },
        };
        if (img.rgb.width(), img.rgb.height()) != self.size {
            return Some(Err(VideoError::NotVideo {
                path: path.clone(),
                reason: format!(
                    "is {}x{}, but the first image is {}x{}; the frames of a video share one size",
                    img.rgb.width(),
                    img.rgb.height(),
                    self.size.0,
                    self.size.1
                ),
            }));
        }
        Some(Ok(RawFrame {
            pts: i as f64 / self.fps,
            rgb: img.rgb,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn natural_order() {
        let mut v = vec![
            "frame10.png",
            "frame2.png",
            "frame1.png",
            "frame002.png",
            "a.png",
        ];
        v.sort_by(|a, b| natural_cmp(a, b));
        assert_eq!(
            v,
            vec![
                "a.png",
                "frame1.png",
                "frame002.png",
                "frame2.png",
                "frame10.png"
            ]
        );
        assert_eq!(
            natural_cmp("x99999999999999999999999", "x100000000000000000000000"),
            Ordering::Less
        );
        assert_eq!(natural_cmp("img_000010", "img_000009"), Ordering::Greater);
    }
}
