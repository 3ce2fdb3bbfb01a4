//! GIF and PNG-folder outputs, the watermark, format choice, and what is (not) left on disk
//! after errors.

mod common;

use std::path::Path;

use common::*;
use gagavatar_video::{
    draw_watermark, watermark_rect, VideoError, VideoFormat, VideoOptions, VideoWriter,
    WATERMARK_TEXT,
};

/// A frame with few colours (GIF palettes are exact for up to 256), distinct per frame.
fn flat_frame(width: usize, height: usize, t: usize) -> Vec<u8> {
    let mut out = vec![0u8; width * height * 3];
    for y in 0..height {
        for x in 0..width {
            let band = ((x / 8 + y / 8 + t) % 6) as u8;
            let o = (y * width + x) * 3;
            out[o..o + 3].copy_from_slice(&[band * 40, 255 - band * 30, (t as u8) * 50]);
        }
    }
    out
}

/// Decodes a GIF with the gif crate: (width, height, frames as RGB, delays in cs, repeat).
fn read_gif(path: &Path) -> (usize, usize, Vec<Vec<u8>>, Vec<u16>, gif::Repeat) {
    let mut opts = gif::DecodeOptions::new();
    opts.set_color_output(gif::ColorOutput::RGBA);
    let mut dec = opts.read_info(std::fs::File::open(path).unwrap()).unwrap();
    let (w, h) = (dec.width() as usize, dec.height() as usize);
    let mut frames = Vec::new();
    let mut delays = Vec::new();
    while let Some(f) = dec.read_next_frame().unwrap() {
        assert_eq!((f.left, f.top), (0, 0));
        assert_eq!(
            (f.width as usize, f.height as usize),
            (w, h),
            "full-frame images"
        );
        frames.push(
            f.buffer
                .chunks_exact(4)
                .flat_map(|p| [p[0], p[1], p[2]])
                .collect(),
        );
        delays.push(f.delay);
    }
    let repeat = dec.repeat();
    (w, h, frames, delays, repeat)
}

#[test]
fn format_follows_the_extension() {
    for (p, f) in [
        ("a.mp4", VideoFormat::Mp4),
        ("dir/A.MP4", VideoFormat::Mp4),
        ("a.gif", VideoFormat::Gif),
        ("a.GiF", VideoFormat::Gif),
        ("frames", VideoFormat::PngDir),
        ("frames/", VideoFormat::PngDir),
        ("a.mp4/", VideoFormat::PngDir),
        ("a.png", VideoFormat::PngDir),
        ("a.mov", VideoFormat::PngDir),
    ] {
        assert_eq!(VideoFormat::from_path(Path::new(p)), f, "{p}");
    }
    let d = VideoOptions::default();
    assert_eq!((d.fps, d.watermark), (25.0, true));
}

#[test]
fn gif_round_trips_exactly_for_few_colours() {
    let dir = scratch("gif");
    let path = dir.join("a.gif");
    let (w, h) = (64, 48);
    let inputs: Vec<Vec<u8>> = (0..4).map(|t| flat_frame(w, h, t)).collect();
    let mut v = VideoWriter::create(&path, w, h, no_watermark(25.0)).unwrap();
    assert_eq!(v.format(), VideoFormat::Gif);
    for f in &inputs {
        v.push_rgb(f).unwrap();
    }
    v.finish().unwrap();
    assert_eq!(listing(&dir), vec!["a.gif"]);
    let (gw, gh, frames, delays, repeat) = read_gif(&path);
    assert_eq!((gw, gh), (w, h));
    assert_eq!(frames.len(), inputs.len());
    for (i, (a, e)) in frames.iter().zip(&inputs).enumerate() {
        if let Some(p) = a.iter().zip(e).position(|(x, y)| x != y) {
            panic!("frame {i} byte {p}: expected {}, got {}", e[p], a[p]);
        }
    }
    assert_eq!(delays, vec![4; 4], "25 fps = 4 cs");
    assert_eq!(repeat, gif::Repeat::Infinite);
}

#[test]
fn gif_delays_keep_the_average_rate() {
    let dir = scratch("gif_rate");
    let path = dir.join("r.gif");
    let mut v = VideoWriter::create(&path, 96, 64, no_watermark(30.0)).unwrap();
    for t in 0..6 {
        v.push_rgb(&smooth_frame(96, 64, t)).unwrap();
    }
    v.finish().unwrap();
    let (w, h, frames, delays, _) = read_gif(&path);
    assert_eq!((w, h, frames.len()), (96, 64, 6));
    // 30 fps: 3.33 cs per frame, so 3, 4, 3, 3, 4, 3 sums to 20 cs for 6 frames.
    assert_eq!(
        delays.iter().map(|&d| d as u32).sum::<u32>(),
        20,
        "{delays:?}"
    );
    assert!(delays.iter().all(|&d| d == 3 || d == 4), "{delays:?}");
    // NeuQuant on smooth content: close, not exact.
    for (i, (a, e)) in frames
        .iter()
        .zip((0..6).map(|t| smooth_frame(96, 64, t)))
        .enumerate()
    {
        let p = psnr(a, &e);
        assert!(p > 30.0, "frame {i}: GIF PSNR {p:.2} dB");
    }
}

#[test]
fn png_folder_holds_exact_frames() {
    let dir = scratch("png");
    let out = dir.join("frames");
    let (w, h) = (64, 48);
    let mut v = VideoWriter::create(&out, w, h, no_watermark(25.0)).unwrap();
    assert_eq!(v.format(), VideoFormat::PngDir);
    let inputs: Vec<Vec<u8>> = (0..3).map(|t| smooth_frame(w, h, t)).collect();
    for f in &inputs {
        v.push_rgb(f).unwrap();
    }
    // Nothing at the target until finish.
    assert!(!out.exists());
    v.finish().unwrap();
    assert_eq!(listing(&dir), vec!["frames"]);
    assert_eq!(
        listing(&out),
        vec!["frame_00000.png", "frame_00001.png", "frame_00002.png"]
    );
    for (i, e) in inputs.iter().enumerate() {
        let img = image::open(out.join(format!("frame_{i:05}.png")))
            .unwrap()
            .to_rgb8();
        assert_eq!(img.dimensions(), (w as u32, h as u32));
        assert!(img.as_raw() == e, "frame {i} differs from the input");
    }
}

#[test]
fn png_folder_path_may_end_in_a_slash() {
    let dir = scratch("png_slash");
    let out = format!("{}/shots/", dir.display());
    let mut v = VideoWriter::create(Path::new(&out), 8, 4, no_watermark(25.0)).unwrap();
    v.push_rgb(&[200; 8 * 4 * 3]).unwrap();
    v.push_rgb(&[100; 8 * 4 * 3]).unwrap();
    v.finish().unwrap();
    assert_eq!(listing(&dir), vec!["shots"]);
    assert_eq!(
        listing(&dir.join("shots")),
        vec!["frame_00000.png", "frame_00001.png"]
    );
}

#[test]
fn writer_can_move_to_another_thread() {
    fn send<T: Send>() {}
    send::<VideoWriter>();
}

#[test]
fn png_folder_refuses_non_empty_dir_and_reuses_empty_one() {
    let dir = scratch("png_exists");
    let full = dir.join("full");
    std::fs::create_dir(&full).unwrap();
    std::fs::write(full.join("keep.txt"), b"mine").unwrap();
    let err = VideoWriter::create(&full, 8, 8, VideoOptions::default());
    assert!(
        matches!(err, Err(VideoError::BadPath { .. })),
        "{:?}",
        err.err()
    );
    assert_eq!(listing(&full), vec!["keep.txt"]);

    let empty = dir.join("empty");
    std::fs::create_dir(&empty).unwrap();
    let mut v = VideoWriter::create(&empty, 8, 8, no_watermark(25.0)).unwrap();
    v.push_rgb(&[7; 8 * 8 * 3]).unwrap();
    v.finish().unwrap();
    assert_eq!(listing(&empty), vec!["frame_00000.png"]);
    assert_eq!(listing(&dir), vec!["empty", "full"]);
}

#[test]
fn watermark_marks_the_corner_only() {
    for (w, h) in [(64, 64), (96, 64), (512, 512), (1024, 512)] {
        let dir = scratch(&format!("wm_{w}x{h}"));
        let out = dir.join("frames");
        let input = smooth_frame(w, h, 0);
        let mut v = VideoWriter::create(&out, w, h, VideoOptions::default()).unwrap();
        v.push_rgb(&input).unwrap();
        v.finish().unwrap();
        let got = image::open(out.join("frame_00000.png"))
            .unwrap()
            .to_rgb8()
            .into_raw();

        let [x0, y0, x1, y1] = watermark_rect(w, h, WATERMARK_TEXT).unwrap();
        assert!(x1 <= w && y1 <= h && x0 < x1 && y0 < y1);
        // Bottom-right: the box reaches the right and bottom edges up to a small margin and
        // stays out of the top half and (from 256 wide) the left third.
        assert!(
            w - x1 <= w / 50 + 2 && h - y1 <= h / 50 + 2,
            "{w}x{h}: box {x0},{y0}-{x1},{y1}"
        );
        assert!(y0 >= h / 2, "{w}x{h}: box reaches the top half");
        if w >= 256 {
            assert!(x0 >= w / 3, "{w}x{h}: box reaches the left third");
        }
        let mut changed_inside = 0;
        for y in 0..h {
            for x in 0..w {
                let o = (y * w + x) * 3;
                let same = got[o..o + 3] == input[o..o + 3];
                let inside = (x0..x1).contains(&x) && (y0..y1).contains(&y);
                assert!(
                    inside || same,
                    "{w}x{h}: pixel ({x}, {y}) outside the box changed"
                );
                changed_inside += usize::from(!same);
            }
        }
        let area = (x1 - x0) * (y1 - y0);
        assert!(
            changed_inside * 10 >= area * 9,
            "{w}x{h}: only {changed_inside} of {area} box pixels changed"
        );
        // Legible: light text on a dark box means both very light and darkened pixels.
        let light = (y0..y1)
            .flat_map(|y| (x0..x1).map(move |x| (y * w + x) * 3))
            .filter(|&o| got[o] >= 240 && got[o + 1] >= 240 && got[o + 2] >= 240)
            .count();
        assert!(
            light * 20 >= area,
            "{w}x{h}: only {light} text pixels in a box of {area}"
        );

        // The caller's frame is not modified.
        assert_eq!(input, smooth_frame(w, h, 0));
    }
}

#[test]
fn watermark_off_leaves_frames_identical() {
    let dir = scratch("wm_off");
    let out = dir.join("frames");
    let input = smooth_frame(96, 64, 1);
    let mut v = VideoWriter::create(&out, 96, 64, no_watermark(25.0)).unwrap();
    v.push_rgb(&input).unwrap();
    v.finish().unwrap();
    let got = image::open(out.join("frame_00000.png"))
        .unwrap()
        .to_rgb8()
        .into_raw();
    assert!(got == input, "watermark off changed the frame");
}

#[test]
fn draw_watermark_ignores_wrong_lengths_and_blank_text() {
    let mut small = vec![9u8; 10];
    draw_watermark(&mut small, 64, 64, WATERMARK_TEXT);
    assert_eq!(small, vec![9u8; 10]);
    let mut frame = vec![9u8; 32 * 32 * 3];
    draw_watermark(&mut frame, 32, 32, "   ");
    assert!(frame.iter().all(|&v| v == 9));
    assert!(watermark_rect(32, 32, "").is_none());
}

#[test]
fn dropped_writer_leaves_nothing_behind() {
    for name in ["a.mp4", "a.gif", "frames"] {
        let dir = scratch(&format!("drop_{}", name.replace('.', "_")));
        let mut v = VideoWriter::create(&dir.join(name), 32, 32, VideoOptions::default()).unwrap();
        v.push_rgb(&smooth_frame(32, 32, 0)).unwrap();
        v.push_rgb(&smooth_frame(32, 32, 1)).unwrap();
        assert!(
            !listing(&dir).is_empty(),
            "{name}: temporary output exists while writing"
        );
        drop(v);
        assert!(listing(&dir).is_empty(), "{name}: left {:?}", listing(&dir));
    }
}

#[test]
fn wrong_frame_length_is_an_error() {
    let dir = scratch("bad_frame");
    for name in ["a.mp4", "a.gif", "frames"] {
        let mut v = VideoWriter::create(&dir.join(name), 32, 16, VideoOptions::default()).unwrap();
        match v.push_rgb(&[0; 32 * 16 * 3 - 1]) {
            Err(VideoError::BadFrame { expected, got }) => {
                assert_eq!((expected, got), (1536, 1535), "{name}")
            }
            other => panic!("{name}: expected BadFrame, got {other:?}"),
        }
        assert_eq!(v.frames(), 0);
        // The writer stays usable.
        v.push_rgb(&[0; 32 * 16 * 3]).unwrap();
        assert_eq!(v.frames(), 1);
    }
}

#[test]
fn finishing_without_frames_is_an_error_and_writes_nothing() {
    for name in ["a.mp4", "a.gif", "frames"] {
        let dir = scratch(&format!("empty_{}", name.replace('.', "_")));
        let v = VideoWriter::create(&dir.join(name), 32, 32, VideoOptions::default()).unwrap();
        assert!(
            matches!(v.finish(), Err(VideoError::NoFrames { .. })),
            "{name}"
        );
        assert!(listing(&dir).is_empty(), "{name}: left {:?}", listing(&dir));
    }
}

#[test]
fn bad_options_are_refused_before_anything_is_created() {
    let dir = scratch("bad_opts");
    for name in ["a.mp4", "a.gif", "frames"] {
        let path = dir.join(name);
        for fps in [f64::NAN, f64::INFINITY, 0.0, -25.0, 1e6] {
            let r = VideoWriter::create(
                &path,
                32,
                32,
                VideoOptions {
                    fps,
                    watermark: true,
                },
            );
            assert!(
                matches!(r, Err(VideoError::BadFps { .. })),
                "{name} fps {fps}"
            );
        }
        for (w, h) in [(0, 32), (32, 0), (0, 0)] {
            let r = VideoWriter::create(&path, w, h, VideoOptions::default());
            assert!(
                matches!(r, Err(VideoError::BadSize { .. })),
                "{name} {w}x{h}"
            );
        }
    }
    let r = VideoWriter::create(&dir.join("huge.gif"), 70000, 2, VideoOptions::default());
    assert!(matches!(r, Err(VideoError::BadSize { .. })));
    let r = VideoWriter::create(&dir.join("missing/a.mp4"), 32, 32, VideoOptions::default());
    assert!(
        matches!(r, Err(VideoError::Io { .. })),
        "missing parent folder"
    );
    assert!(listing(&dir).is_empty(), "left {:?}", listing(&dir));
}
