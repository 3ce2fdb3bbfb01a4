//! `gagavatar video info` / `video frames` on clips made with ffmpeg at test time, bad inputs
//! (one line, non-zero exit, no partial output) and a machine without ffmpeg (PATH emptied).

#[path = "../../../crates/video/tests/common/fixtures.rs"]
mod fixtures;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use fixtures::*;
use gagavatar_video::read::{ReadOptions, VideoReader};

const BIN: &str = env!("CARGO_BIN_EXE_gagavatar");

fn scratch(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("video-cli-{name}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn run(args: &[&str], path_var: Option<&Path>) -> Output {
    let mut cmd = Command::new(BIN);
    cmd.args(args);
    if let Some(p) = path_var {
        cmd.env("PATH", p);
    }
    cmd.output().expect("running gagavatar")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A failure: non-zero exit, exactly one line on stderr (`error: ...`), no panic.
fn assert_one_line_error(o: &Output, what: &str, expected: &str) -> String {
    let err = stderr(o);
    assert!(!o.status.success(), "{what}: succeeded\n{err}");
    assert!(!err.contains("panicked"), "{what}: panicked\n{err}");
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "{what}: one line expected, got\n{err}");
    assert!(lines[0].starts_with("error: "), "{what}: {err}");
    assert!(
        lines[0].contains(expected),
        "{what}: expected `{expected}` in\n{err}"
    );
    err
}

fn png_names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".png"))
        .collect();
    v.sort();
    v
}

#[test]
fn info_prints_the_metadata_as_json() {
    if !ffmpeg_with("info_prints_the_metadata_as_json", &["libx264"]) {
        return;
    }
    let dir = scratch("info");
    let clip = make_clip(
        &dir.join("clip.mp4"),
        &testsrc(160, 120, "25", 20),
        &["-c:v", "libx264", "-profile:v", "high", "-bf", "2"],
    );
    let o = run(&["video", "info", clip.to_str().unwrap()], None);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8(o.stdout).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(v["width"], 160);
    assert_eq!(v["height"], 120);
    assert_eq!(v["fps"], 25.0);
    assert_eq!(v["frames"], 20);
    assert_eq!(v["duration"], 0.8);
    assert_eq!(v["codec"], "h264");
    assert_eq!(v["rotation"], 0);
    assert_eq!(v["decoder"], "ffmpeg");
    // The fields first, in its order.
    let keys: Vec<usize> = [
        "width", "height", "fps", "frames", "duration", "codec", "rotation", "decoder",
    ]
    .iter()
    .map(|k| text.find(&format!("\"{k}\"")).unwrap())
    .collect();
    assert!(keys.windows(2).all(|w| w[0] < w[1]), "field order: {text}");

    // Matroska stores no frame count; info counts the packets.
    let mkv = make_clip(
        &dir.join("clip.mkv"),
        &testsrc(160, 120, "25", 13),
        &["-c:v", "libx264"],
    );
    let o = run(&["video", "info", mkv.to_str().unwrap()], None);
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["frames"], 13, "{}", stderr(&o));

    // A folder of images is a video too.
    let frames = dir.join("imgs");
    std::fs::create_dir_all(&frames).unwrap();
    for i in 0..3 {
        image::RgbImage::new(10, 8)
            .save(frames.join(format!("{i}.png")))
            .unwrap();
    }
    let o = run(
        &["video", "info", frames.to_str().unwrap(), "--fps", "10"],
        None,
    );
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        (v["frames"].as_u64(), v["fps"].as_f64()),
        (Some(3), Some(10.0))
    );
    assert_eq!(v["decoder"], "image");
}

#[test]
fn frames_writes_what_the_reader_reads() {
    if !ffmpeg_with("frames_writes_what_the_reader_reads", &["libx264"]) {
        return;
    }
    let dir = scratch("frames");
    let clip = make_clip(
        &dir.join("clip.mp4"),
        &testsrc(96, 64, "25", 20),
        &["-c:v", "libx264", "-bf", "3"],
    );
    let c = clip.to_str().unwrap();
    let out = dir.join("all");
    let o = run(&["video", "frames", c, "-o", out.to_str().unwrap()], None);
    assert!(o.status.success(), "{}", stderr(&o));
    let names = png_names(&out);
    assert_eq!(names.len(), 20);
    assert_eq!(names[0], "frame_000000.png");
    assert_eq!(names[19], "frame_000019.png");
    let reader: Vec<_> = VideoReader::open(&clip, &ReadOptions::default())
        .unwrap()
        .map(|f| f.unwrap())
        .collect();
    for (i, f) in reader.iter().enumerate() {
        let png = image::open(out.join(&names[i])).unwrap().to_rgb8();
        assert_eq!(png, f.rgb, "frame {i}");
    }
    let index: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("frames.json")).unwrap()).unwrap();
    assert_eq!(index["frames"][7]["pts"].as_f64(), Some(reader[7].pts));

    let part = dir.join("part");
    let o = run(
        &[
            "video",
            "frames",
            c,
            "-o",
            part.to_str().unwrap(),
            "--start",
            "5",
            "--max-frames",
            "4",
        ],
        None,
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let names = png_names(&part);
    assert_eq!(names.len(), 4);
    for (k, n) in names.iter().enumerate() {
        let png = image::open(part.join(n)).unwrap().to_rgb8();
        assert_eq!(png, reader[5 + k].rgb, "frame {}", 5 + k);
    }

    // 25 -> 12.5 fps keeps every other frame.
    let half = dir.join("half");
    let o = run(
        &[
            "video",
            "frames",
            c,
            "-o",
            half.to_str().unwrap(),
            "--fps",
            "12.5",
        ],
        None,
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(png_names(&half).len(), 10);

    // An existing non-empty folder is refused and left as it was.
    let o = run(&["video", "frames", c, "-o", half.to_str().unwrap()], None);
    assert_one_line_error(&o, "non-empty output", "not empty");
    assert_eq!(png_names(&half).len(), 10);
}

#[test]
fn bad_inputs_fail_in_one_line_and_write_nothing() {
    if !ffmpeg_with(
        "bad_inputs_fail_in_one_line_and_write_nothing",
        &["libx264"],
    ) {
        return;
    }
    let dir = scratch("bad");
    let good = make_clip(
        &dir.join("good.mp4"),
        &testsrc(160, 120, "25", 40),
        &["-c:v", "libx264", "-movflags", "+faststart"],
    );
    let bytes = std::fs::read(&good).unwrap();
    let truncated = dir.join("truncated.mp4");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let text = dir.join("text.mp4");
    std::fs::write(&text, "just some words\n").unwrap();
    let zero = dir.join("zero.mp4");
    make_clip(&zero, &testsrc(160, 120, "25", 0), &["-c:v", "libx264"]);
    let missing = dir.join("missing.mp4");
    let cases = [
        (&truncated, "truncated or damaged"),
        (&text, "not a video"),
        (&zero, "no video frames"),
        (&missing, "missing.mp4"),
    ];
    for (input, expected) in cases {
        let out = dir.join("out");
        let o = run(
            &[
                "video",
                "frames",
                input.to_str().unwrap(),
                "-o",
                out.to_str().unwrap(),
            ],
            None,
        );
        assert_one_line_error(&o, &format!("frames {}", input.display()), expected);
        assert!(!out.exists(), "{}: partial output left", input.display());
        let leftovers: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with('.'))
            .collect();
        assert!(leftovers.is_empty(), "temporary files left: {leftovers:?}");
        if input != &truncated {
            let o = run(&["video", "info", input.to_str().unwrap()], None);
            assert_one_line_error(&o, &format!("info {}", input.display()), expected);
        }
    }
    // Bad options are refused before anything is read.
    let o = run(
        &[
            "video",
            "frames",
            good.to_str().unwrap(),
            "-o",
            "x",
            "--fps",
            "0",
        ],
        None,
    );
    assert_one_line_error(&o, "--fps 0", "frame rate");
    let o = run(
        &[
            "video",
            "frames",
            good.to_str().unwrap(),
            "-o",
            "x",
            "--start",
            "soon",
        ],
        None,
    );
    assert!(
        !o.status.success() && stderr(&o).contains("not a start"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn without_ffmpeg_our_mp4_reads_and_others_say_how_to_install_it() {
    let dir = scratch("no-ffmpeg");
    let empty_path = dir.join("empty-path");
    std::fs::create_dir_all(&empty_path).unwrap();
    // Our own mp4 (H.264 Constrained Baseline) needs no ffmpeg.
    let own = dir.join("own.mp4");
    let mut w = gagavatar_video::VideoWriter::create(
        &own,
        64,
        48,
        gagavatar_video::VideoOptions {
            fps: 25.0,
            watermark: false,
        },
    )
    .unwrap();
    for i in 0..5u8 {
        w.push_rgb(&vec![40 * i; 64 * 48 * 3]).unwrap();
    }
    w.finish().unwrap();
    let o = run(&["video", "info", own.to_str().unwrap()], Some(&empty_path));
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        (v["decoder"].as_str(), v["frames"].as_u64()),
        (Some("openh264"), Some(5))
    );
    let out = dir.join("own_frames");
    let o = run(
        &[
            "video",
            "frames",
            own.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ],
        Some(&empty_path),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(png_names(&out).len(), 5);

    if !ffmpeg_with(
        "without_ffmpeg_our_mp4_reads_and_others_say_how_to_install_it",
        &["libx264", "libvpx-vp9"],
    ) {
        return;
    }
    let high = make_clip(
        &dir.join("phone.mp4"),
        &testsrc(96, 64, "30", 10),
        &["-c:v", "libx264", "-profile:v", "high", "-bf", "2"],
    );
    let webm = make_clip(
        &dir.join("clip.webm"),
        &testsrc(96, 64, "30", 5),
        &[
            "-c:v",
            "libvpx-vp9",
            "-deadline",
            "realtime",
            "-cpu-used",
            "8",
        ],
    );
    for (input, what) in [(&high, "H.264 High profile"), (&webm, "Matroska / WebM")] {
        for sub in ["info", "frames"] {
            let out = dir.join("out");
            let mut args = vec!["video", sub, input.to_str().unwrap()];
            if sub == "frames" {
                args.extend(["-o", out.to_str().unwrap()]);
            }
            let o = run(&args, Some(&empty_path));
            let err = assert_one_line_error(&o, &format!("{sub} {}", input.display()), what);
            for needed in [
                "needs ffmpeg",
                "not on PATH",
                "apt install ffmpeg",
                "brew install ffmpeg",
                "winget install",
            ] {
                assert!(err.contains(needed), "`{needed}` missing: {err}");
            }
            assert!(!out.exists());
        }
    }
}
