//! Shared helpers: synthetic frames, PSNR, scratch folders, a raw MP4 box walker.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use gagavatar_video::{VideoOptions, VideoWriter};

pub mod fixtures;

/// A fresh empty folder for one test under cargo's per-target scratch space.
pub fn scratch(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("video-{name}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Names in a folder, sorted.
pub fn listing(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// Smooth moving colour waves plus a soft bright disc, like a lit face on a plain background:
/// the kind of content the renderer produces, with motion between frames.
pub fn smooth_frame(width: usize, height: usize, t: usize) -> Vec<u8> {
    let t = t as f64;
    let mut out = vec![0u8; width * height * 3];
    let (cx, cy) = (width as f64 * (0.45 + 0.02 * t), height as f64 * 0.5);
    let r0 = width.min(height) as f64 * 0.3;
    for y in 0..height {
        for x in 0..width {
            let (xf, yf) = (x as f64, y as f64);
            let d = ((xf - cx).powi(2) + (yf - cy).powi(2)).sqrt() / r0;
            let disc = 90.0 * (-d * d).exp();
            let r = 110.0 + 50.0 * (xf * 0.045 + t * 0.3).sin() + disc;
            let g = 100.0 + 45.0 * (yf * 0.038 - t * 0.2).cos() + 0.8 * disc;
            let b = 120.0 + 40.0 * ((xf + yf) * 0.03 + t * 0.1).sin() + 0.6 * disc;
            let o = (y * width + x) * 3;
            out[o] = r.clamp(0.0, 255.0) as u8;
            out[o + 1] = g.clamp(0.0, 255.0) as u8;
            out[o + 2] = b.clamp(0.0, 255.0) as u8;
        }
    }
    out
}

/// PSNR in dB over all RGB samples (infinite for identical inputs).
pub fn psnr(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len());
    let se: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
        .sum();
    let mse = se / a.len() as f64;
    10.0 * (255.0f64 * 255.0 / mse).log10()
}

/// The top-left `w` x `h` part of an RGB frame `stride_w` pixels wide.
pub fn crop(rgb: &[u8], stride_w: usize, w: usize, h: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        out.extend_from_slice(&rgb[y * stride_w * 3..][..w * 3]);
    }
    out
}

/// Writes `frames` with the given options and returns them (unwatermarked inputs).
pub fn write_video(
    path: &Path,
    width: usize,
    height: usize,
    n: usize,
    opts: VideoOptions,
) -> Vec<Vec<u8>> {
    let frames: Vec<Vec<u8>> = (0..n).map(|t| smooth_frame(width, height, t)).collect();
    let mut w = VideoWriter::create(path, width, height, opts).unwrap();
    for f in &frames {
        w.push_rgb(f).unwrap();
    }
    assert_eq!(w.frames(), n);
    w.finish().unwrap();
    frames
}

pub fn no_watermark(fps: f64) -> VideoOptions {
    VideoOptions {
        fps,
        watermark: false,
    }
}

/// Top-level or child boxes of `buf`: (type, offset of the box in `buf`, body). Written
/// independently of the crate's reader so the tests check the bytes themselves.
pub fn boxes(buf: &[u8]) -> Vec<([u8; 4], usize, &[u8])> {
    let mut out = Vec::new();
    let mut pos = 0;
    while pos + 8 <= buf.len() {
        let size = u32::from_be_bytes(buf[pos..pos + 4].try_into().unwrap()) as usize;
        let kind: [u8; 4] = buf[pos + 4..pos + 8].try_into().unwrap();
        let (hdr, size) = match size {
            1 => (
                16,
                u64::from_be_bytes(buf[pos + 8..pos + 16].try_into().unwrap()) as usize,
            ),
            0 => (8, buf.len() - pos),
            s => (8, s),
        };
        assert!(size >= hdr && pos + size <= buf.len(), "bad box at {pos}");
        out.push((kind, pos, &buf[pos + hdr..pos + size]));
        pos += size;
    }
    assert_eq!(pos, buf.len(), "trailing bytes after the last box");
    out
}

/// The body of the first box of type `kind` along a path of nested boxes, e.g.
/// `["moov", "trak", "mdia"]`. `skip` gives bytes to skip before the children of a box (full box
/// headers, sample entry fields).
pub fn find<'a>(buf: &'a [u8], path: &[(&str, usize)]) -> Option<&'a [u8]> {
    let mut cur = buf;
    for (kind, skip) in path {
        let body = boxes(cur)
            .into_iter()
            .find(|(k, _, _)| k == kind.as_bytes())?
            .2;
        cur = &body[*skip..];
    }
    Some(cur)
}
