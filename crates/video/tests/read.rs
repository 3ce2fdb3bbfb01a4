//! The video reader against ffmpeg's own answers, on clips of every common kind made with ffmpeg
//! at test time: the frame count and every timestamp equal `ffprobe -show_frames`, and every
//! frame is within [`MAX_MEAN_ABS_DIFF`] of ffmpeg's PNG decode of the same frame.

mod common;

use std::path::{Path, PathBuf};

use common::fixtures::*;
use common::scratch;
use gagavatar_video::read::{
    probe, DecoderChoice, Frame, ReadOptions, Start, VideoMeta, VideoReader,
};
use gagavatar_video::VideoError;

/// The bound: 1/255 of the range, one code value, on average over a frame. The ffmpeg
/// path is the same conversion as the reference and measures 0; the built-in path rounds its
/// own YUV -> RGB and measures up to ~0.5.
const MAX_MEAN_ABS_DIFF: f64 = 1.0;
/// ffprobe prints times with 6 decimals.
const PTS_TOL: f64 = 1e-6;

fn read_all(path: &Path, opts: &ReadOptions) -> (VideoMeta, Vec<Frame>) {
    let reader =
        VideoReader::open(path, opts).unwrap_or_else(|e| panic!("opening {}: {e}", path.display()));
    let meta = reader.meta().clone();
    let frames = reader
        .collect::<Result<Vec<_>, _>>()
        .unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
    (meta, frames)
}

/// Reads `path` with `opts` and compares with ffprobe's timestamps and ffmpeg's PNG decode.
fn check_against_ffmpeg(name: &str, path: &Path, opts: &ReadOptions) -> (VideoMeta, Vec<Frame>) {
    let (meta, frames) = read_all(path, opts);
    let times = probe_frame_times(path);
    assert_eq!(
        frames.len(),
        times.len(),
        "{name}: frame count: ffprobe decodes {}, we read {}",
        times.len(),
        frames.len()
    );
    if let Some(n) = meta.frames {
        assert_eq!(n as usize, times.len(), "{name}: container frame count");
    }
    for (i, (f, &t)) in frames.iter().zip(&times).enumerate() {
        assert_eq!(f.index, i as u64, "{name}: index");
        assert!(
            (f.pts - t).abs() <= PTS_TOL,
            "{name}: frame {i}: pts expected {t} (ffprobe), got {}",
            f.pts
        );
    }
    let dir = path.with_extension("ref");
    let refs = reference_frames(path, &dir);
    assert_eq!(
        refs.len(),
        frames.len(),
        "{name}: ffmpeg's PNG decode count"
    );
    let mut worst = 0.0f64;
    for (i, (f, r)) in frames.iter().zip(&refs).enumerate() {
        assert_eq!(
            (f.rgb.width(), f.rgb.height()),
            (meta.width, meta.height),
            "{name}: frame {i} size vs metadata"
        );
        let d = mean_abs_diff(&f.rgb, r);
        worst = worst.max(d);
        assert!(
            d <= MAX_MEAN_ABS_DIFF,
            "{name}: frame {i}: mean |ours - ffmpeg PNG| = {d:.3} > {MAX_MEAN_ABS_DIFF}"
        );
    }
    println!(
        "{name}: {} frames, {}x{}, codec {}, decoder {}, worst mean abs diff {worst:.3}",
        frames.len(),
        meta.width,
        meta.height,
        meta.codec,
        meta.decoder.as_str()
    );
    (meta, frames)
}

fn clip(name: &str, file: &str, input: Vec<String>, extra: &[&str]) -> PathBuf {
    let dir = scratch(&format!("read-{name}"));
    make_clip(&dir.join(file), &input, extra)
}

#[test]
fn x264_high_with_b_frames() {
    if !ffmpeg_with("x264_high_with_b_frames", &["libx264"]) {
        return;
    }
    // The kind of clip the built-in decoder stopped on after 8-9 frames.
    let path = clip(
        "x264-high",
        "high.mp4",
        testsrc(160, 120, "25", 40),
        &[
            "-c:v",
            "libx264",
            "-profile:v",
            "high",
            "-bf",
            "3",
            "-pix_fmt",
            "yuv420p",
            "-g",
            "12",
        ],
    );
    assert_eq!(probe_stream(&path)["has_b_frames"].as_i64(), Some(2));
    let (meta, _) = check_against_ffmpeg("x264 High", &path, &ReadOptions::default());
    assert_eq!(
        (meta.codec.as_str(), meta.profile.as_deref()),
        ("h264", Some("High"))
    );
    assert_eq!((meta.width, meta.height, meta.rotation), (160, 120, 0));
    assert!((meta.fps - 25.0).abs() < 1e-9, "fps {}", meta.fps);
    // A name ffmpeg would take for a protocol ("odd:") is still a file.
    let odd = path.with_file_name("odd:name.mp4");
    std::fs::copy(&path, &odd).unwrap();
    assert_eq!(read_all(&odd, &ReadOptions::default()).1.len(), 40);
}

#[test]
fn x264_high_10_bit() {
    if !ffmpeg_with("x264_high_10_bit", &["libx264"]) {
        return;
    }
    let path = clip(
        "x264-10bit",
        "ten.mp4",
        testsrc(160, 120, "30", 20),
        &["-c:v", "libx264", "-pix_fmt", "yuv420p10le", "-bf", "2"],
    );
    assert_eq!(probe_stream(&path)["pix_fmt"], "yuv420p10le");
    let (meta, _) = check_against_ffmpeg("x264 10-bit", &path, &ReadOptions::default());
    assert_eq!(meta.profile.as_deref(), Some("High 10"));
}

#[test]
fn hevc() {
    if !ffmpeg_with("hevc", &["libx265"]) {
        return;
    }
    let path = clip(
        "hevc",
        "hevc.mp4",
        testsrc(160, 120, "25", 20),
        &[
            "-c:v",
            "libx265",
            "-x265-params",
            "log-level=error",
            "-tag:v",
            "hvc1",
        ],
    );
    let (meta, _) = check_against_ffmpeg("HEVC", &path, &ReadOptions::default());
    assert_eq!(meta.codec, "hevc");
}

#[test]
fn vp9_webm() {
    if !ffmpeg_with("vp9_webm", &["libvpx-vp9"]) {
        return;
    }
    let path = clip(
        "vp9",
        "vp9.webm",
        testsrc(160, 120, "25", 20),
        &[
            "-c:v",
            "libvpx-vp9",
            "-deadline",
            "realtime",
            "-cpu-used",
            "8",
            "-b:v",
            "200k",
        ],
    );
    let (meta, _) = check_against_ffmpeg("VP9 webm", &path, &ReadOptions::default());
    assert_eq!(meta.codec, "vp9");
}

#[test]
fn av1() {
    if !ffmpeg_or_skip("av1") {
        return;
    }
    let Some(enc) = first_encoder("av1", &["libsvtav1", "libaom-av1", "librav1e"]) else {
        return;
    };
    let speed: &[&str] = match enc {
        "libsvtav1" => &["-preset", "12"],
        "libaom-av1" => &["-cpu-used", "8", "-row-mt", "1"],
        _ => &["-speed", "10"],
    };
    let mut extra = vec!["-c:v", enc];
    extra.extend_from_slice(speed);
    let path = clip("av1", "av1.mkv", testsrc(160, 128, "25", 12), &extra);
    let (meta, _) = check_against_ffmpeg(&format!("AV1 ({enc})"), &path, &ReadOptions::default());
    assert_eq!(meta.codec, "av1");
}

#[test]
fn prores_mov_and_mpeg4_avi() {
    if !ffmpeg_or_skip("prores_mov_and_mpeg4_avi") {
        return;
    }
    let path = clip(
        "prores",
        "prores.mov",
        testsrc(160, 120, "24000/1001", 10),
        &["-c:v", "prores_ks", "-profile:v", "1"],
    );
    let (meta, _) = check_against_ffmpeg("ProRes mov", &path, &ReadOptions::default());
    assert_eq!(meta.codec, "prores");
    assert!(
        (meta.fps - 24000.0 / 1001.0).abs() < 1e-9,
        "fps {}",
        meta.fps
    );
    let path = clip(
        "avi",
        "mpeg4.avi",
        testsrc(160, 120, "25", 15),
        &["-c:v", "mpeg4", "-q:v", "3"],
    );
    let (meta, _) = check_against_ffmpeg("MPEG-4 avi", &path, &ReadOptions::default());
    assert_eq!(meta.codec, "mpeg4");
}

#[test]
fn rotated_phone_mov_comes_out_upright() {
    if !ffmpeg_with("rotated_phone_mov_comes_out_upright", &["libx264"]) {
        return;
    }
    let dir = scratch("read-rotated");
    let plain = make_clip(
        &dir.join("plain.mov"),
        &testsrc(160, 96, "30", 15),
        &["-c:v", "libx264", "-profile:v", "main"],
    );
    // A phone held upright stores landscape pictures with a display matrix that turns them 90
    // degrees clockwise (ffprobe: rotation -90).
    let rotated = dir.join("phone.mov");
    let (p, r) = (plain.to_str().unwrap(), rotated.to_str().unwrap());
    if ffmpeg_version() >= (6, 0) {
        ffmpeg(&["-display_rotation", "-90", "-i", p, "-c", "copy", r]);
    } else {
        // ffmpeg 5.x writes the `rotate` tag as a counter-clockwise display matrix.
        ffmpeg(&["-i", p, "-c", "copy", "-metadata:s:v:0", "rotate=270", r]);
    }
    let s = probe_stream(&rotated);
    let ccw = s["side_data_list"][0]["rotation"].as_f64();
    assert_eq!(ccw, Some(-90.0), "the fixture's rotation: {s}");
    let (meta, frames) = check_against_ffmpeg("rotated mov", &rotated, &ReadOptions::default());
    assert_eq!((meta.width, meta.height, meta.rotation), (96, 160, 90));
    // Upright = the stored picture turned clockwise.
    let (_, stored) = read_all(&plain, &ReadOptions::default());
    let turned = image::imageops::rotate90(&stored[3].rgb);
    assert_eq!(mean_abs_diff(&frames[3].rgb, &turned), 0.0);
}

#[test]
fn variable_frame_rate_keeps_every_frame_at_its_time() {
    if !ffmpeg_with(
        "variable_frame_rate_keeps_every_frame_at_its_time",
        &["libx264"],
    ) {
        return;
    }
    // 30 fps for a third of a second, then every third frame (10 fps).
    let vfr: [&str; 2] = if ffmpeg_version() >= (5, 1) {
        ["-fps_mode", "vfr"]
    } else {
        ["-vsync", "vfr"]
    };
    let mut extra = vec!["-vf", "select='lt(n\\,10)+not(mod(n\\,3))'"];
    extra.extend(vfr);
    extra.extend(["-c:v", "libx264", "-bf", "2"]);
    let path = clip("vfr", "vfr.mp4", testsrc(160, 120, "30", 45), &extra);
    let times = probe_frame_times(&path);
    let gaps: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).collect();
    assert!(
        gaps.iter().any(|g| (g - 1.0 / 30.0).abs() < 1e-3)
            && gaps.iter().any(|g| (g - 0.1).abs() < 1e-3),
        "the fixture is not variable-rate: gaps {gaps:?}"
    );
    let (_, frames) = check_against_ffmpeg("VFR", &path, &ReadOptions::default());

    // Resampled to 20 fps: each output time shows the last frame at or before it.
    let opts = ReadOptions {
        fps: Some(20.0),
        ..ReadOptions::default()
    };
    let (_, resampled) = read_all(&path, &opts);
    let t0 = times[0];
    let last_gap = gaps.last().copied().unwrap();
    let end = times.last().unwrap() + last_gap;
    let expected_n = ((end - t0) * 20.0 - 1e-6).ceil() as usize;
    assert_eq!(resampled.len(), expected_n, "resampled count");
    for (k, f) in resampled.iter().enumerate() {
        let t = t0 + k as f64 / 20.0;
        assert!((f.pts - t).abs() < 1e-9, "output {k}: pts {} vs {t}", f.pts);
        let src = times.iter().rposition(|&p| p <= t + 1e-6).unwrap();
        assert!(
            (f.source_pts - times[src]).abs() <= PTS_TOL,
            "output {k} at {t}: shows {} expected {}",
            f.source_pts,
            times[src]
        );
        assert_eq!(
            f.rgb, frames[src].rgb,
            "output {k}: pixels of source frame {src}"
        );
    }
}

#[test]
fn start_and_max_frames_select_the_same_frames() {
    if !ffmpeg_with("start_and_max_frames_select_the_same_frames", &["libx264"]) {
        return;
    }
    let path = clip(
        "start",
        "start.mp4",
        testsrc(128, 96, "25", 60),
        &["-c:v", "libx264", "-bf", "3", "-g", "20"],
    );
    let (_, all) = read_all(&path, &ReadOptions::default());
    let (_, part) = read_all(
        &path,
        &ReadOptions {
            start: Start::Frame(17),
            max_frames: Some(5),
            ..ReadOptions::default()
        },
    );
    assert_eq!(part.len(), 5);
    for (k, f) in part.iter().enumerate() {
        assert_eq!(f.index, k as u64);
        assert_eq!(f.pts, all[17 + k].pts);
        assert_eq!(f.rgb, all[17 + k].rgb, "frame {}", 17 + k);
    }
    // 1.3 s after the start: the first frame at or after it is frame 33 (1.32 s), reached by a
    // keyframe seek (frame 20) and exact dropping.
    let (_, part) = read_all(
        &path,
        &ReadOptions {
            start: Start::Seconds(1.3),
            max_frames: Some(3),
            ..ReadOptions::default()
        },
    );
    assert_eq!(part.len(), 3);
    assert!((part[0].pts - 1.32).abs() < PTS_TOL, "pts {}", part[0].pts);
    assert_eq!(part[0].rgb, all[33].rgb);
    // A start past the end is an error, not an empty success.
    for start in [Start::Frame(60), Start::Seconds(30.0)] {
        let r = VideoReader::open(
            &path,
            &ReadOptions {
                start,
                ..ReadOptions::default()
            },
        )
        .and_then(|r| r.collect::<Result<Vec<_>, _>>());
        assert!(
            matches!(r, Err(VideoError::NoVideoFrames { .. })),
            "start {start}: {r:?}"
        );
    }
}

#[test]
fn dropping_a_reader_stops_ffmpeg() {
    if !ffmpeg_or_skip("dropping_a_reader_stops_ffmpeg") {
        return;
    }
    // An endless source: ffmpeg would run forever if not stopped.
    let dir = scratch("read-drop");
    let path = make_clip(
        &dir.join("long.mkv"),
        &testsrc(160, 120, "25", 300),
        &["-c:v", "mpeg4", "-q:v", "10"],
    );
    let mut reader = VideoReader::open(&path, &ReadOptions::default()).unwrap();
    let pid = reader.ffmpeg_pid().expect("an ffmpeg child");
    for _ in 0..3 {
        reader.next().unwrap().unwrap();
    }
    drop(reader);
    #[cfg(target_os = "linux")]
    assert!(
        !Path::new(&format!("/proc/{pid}")).exists(),
        "ffmpeg {pid} still exists (running or unreaped) after the reader was dropped"
    );
    let _ = pid;
}

#[test]
fn our_own_mp4_reads_the_same_with_both_decoders() {
    if !ffmpeg_with("our_own_mp4_reads_the_same_with_both_decoders", &[]) {
        return;
    }
    let dir = scratch("read-own");
    let path = dir.join("own.mp4");
    common::write_video(&path, 96, 64, 12, common::no_watermark(25.0));
    let (meta, ours) = check_against_ffmpeg(
        "own mp4, OpenH264",
        &path,
        &ReadOptions {
            decoder: DecoderChoice::OpenH264,
            ..ReadOptions::default()
        },
    );
    assert_eq!(meta.decoder.as_str(), "openh264");
    assert_eq!(meta.profile.as_deref(), Some("Constrained Baseline"));
    let (meta2, theirs) = read_all(&path, &ReadOptions::default());
    assert_eq!(meta2.decoder.as_str(), "ffmpeg");
    assert_eq!(
        (meta.width, meta.height, meta.frames),
        (meta2.width, meta2.height, meta2.frames)
    );
    for (a, b) in ours.iter().zip(&theirs) {
        assert_eq!(a.pts, b.pts);
    }
    // Keyframe seeking in the built-in path lands on the same frames.
    let (_, part) = read_all(
        &path,
        &ReadOptions {
            decoder: DecoderChoice::OpenH264,
            start: Start::Frame(7),
            ..ReadOptions::default()
        },
    );
    assert_eq!(part.len(), 5);
    assert_eq!(part[0].rgb, ours[7].rgb);
}

#[test]
fn third_party_baseline_reads_with_openh264_including_cropping() {
    if !ffmpeg_with(
        "third_party_baseline_reads_with_openh264_including_cropping",
        &["libx264"],
    ) {
        return;
    }
    // 98x74 is coded as 112x80 macroblocks and cropped: the decoder must crop.
    let path = clip(
        "baseline",
        "baseline.mp4",
        testsrc(98, 74, "25", 20),
        &[
            "-c:v",
            "libx264",
            "-profile:v",
            "baseline",
            "-pix_fmt",
            "yuv420p",
        ],
    );
    let (meta, _) = check_against_ffmpeg(
        "x264 Baseline, OpenH264",
        &path,
        &ReadOptions {
            decoder: DecoderChoice::OpenH264,
            ..ReadOptions::default()
        },
    );
    assert_eq!((meta.width, meta.height), (98, 74));
    // A stream that says BT.709 is converted with BT.709 (as ffmpeg does).
    let path = clip(
        "baseline709",
        "bt709.mp4",
        testsrc(96, 64, "25", 8),
        &[
            "-vf",
            "scale=out_color_matrix=bt709",
            "-c:v",
            "libx264",
            "-profile:v",
            "baseline",
            "-colorspace",
            "bt709",
            "-pix_fmt",
            "yuv420p",
        ],
    );
    assert_eq!(probe_stream(&path)["color_space"], "bt709");
    check_against_ffmpeg(
        "x264 Baseline BT.709, OpenH264",
        &path,
        &ReadOptions {
            decoder: DecoderChoice::OpenH264,
            ..ReadOptions::default()
        },
    );
}

#[test]
fn openh264_refuses_what_it_cannot_decode_before_decoding() {
    if !ffmpeg_with(
        "openh264_refuses_what_it_cannot_decode_before_decoding",
        &["libx264", "libvpx-vp9"],
    ) {
        return;
    }
    let dir = scratch("read-refuse");
    let high = make_clip(
        &dir.join("high.mp4"),
        &testsrc(96, 64, "25", 5),
        &["-c:v", "libx264", "-profile:v", "high"],
    );
    let main_no_b = make_clip(
        &dir.join("main.mp4"),
        &testsrc(96, 64, "25", 5),
        &["-c:v", "libx264", "-profile:v", "main", "-bf", "0"],
    );
    let webm = make_clip(
        &dir.join("v.webm"),
        &testsrc(96, 64, "25", 5),
        &[
            "-c:v",
            "libvpx-vp9",
            "-deadline",
            "realtime",
            "-cpu-used",
            "8",
        ],
    );
    let full_range = make_clip(
        &dir.join("full.mp4"),
        &testsrc(96, 64, "25", 5),
        &[
            "-vf",
            "scale=out_range=pc",
            "-c:v",
            "libx264",
            "-profile:v",
            "baseline",
            "-color_range",
            "pc",
            "-pix_fmt",
            "yuv420p",
        ],
    );
    let builtin = ReadOptions {
        decoder: DecoderChoice::OpenH264,
        ..ReadOptions::default()
    };
    for (path, what) in [
        (&high, "H.264 High profile"),
        (&main_no_b, "H.264 Main profile"),
        (&webm, "Matroska / WebM"),
        (&full_range, "full-range H.264"),
    ] {
        let err = VideoReader::open(path, &builtin).err().expect("refused");
        let msg = err.to_string();
        assert!(
            matches!(err, VideoError::NeedsFfmpeg { .. }) && msg.contains(what),
            "{}: {msg}",
            path.display()
        );
        assert!(!msg.contains('\n'), "one line: {msg}");
    }
}

#[test]
fn bad_inputs_are_one_clear_error() {
    if !ffmpeg_with("bad_inputs_are_one_clear_error", &["libx264"]) {
        return;
    }
    let dir = scratch("read-bad");
    let faststart = make_clip(
        &dir.join("fs.mp4"),
        &testsrc(160, 120, "25", 50),
        &["-c:v", "libx264", "-movflags", "+faststart"],
    );
    let moov_last = make_clip(
        &dir.join("late.mp4"),
        &testsrc(160, 120, "25", 50),
        &["-c:v", "libx264"],
    );
    let cut = |src: &Path, name: &str| {
        let bytes = std::fs::read(src).unwrap();
        let out = dir.join(name);
        std::fs::write(&out, &bytes[..bytes.len() * 2 / 3]).unwrap();
        out
    };
    let cut_fs = cut(&faststart, "cut_fs.mp4");
    let cut_late = cut(&moov_last, "cut_late.mp4");
    let text = dir.join("notes.mp4");
    std::fs::write(&text, "this is not a video\n").unwrap();
    let empty = dir.join("empty.mp4");
    std::fs::write(&empty, b"").unwrap();
    let zero = dir.join("zero.mp4");
    let mut args: Vec<String> = testsrc(160, 120, "25", 0);
    args.extend(["-c:v".into(), "libx264".into()]);
    make_clip(&zero, &args, &[]);
    let audio = dir.join("audio.m4a");
    ffmpeg(&["-f", "lavfi", "-i", "sine=d=0.5", audio.to_str().unwrap()]);

    let cases: [(&Path, &str); 6] = [
        (&cut_fs, "truncated or damaged: only"),
        (&cut_late, "not a video ffmpeg can read"),
        (&text, "not a video ffmpeg can read"),
        (&empty, "the file is empty"),
        (&zero, "no video frames"),
        (&audio, "no video stream"),
    ];
    for decoder in [DecoderChoice::Auto, DecoderChoice::OpenH264] {
        for (path, expected) in cases {
            let opts = ReadOptions {
                decoder,
                ..ReadOptions::default()
            };
            let result =
                VideoReader::open(path, &opts).and_then(|r| r.collect::<Result<Vec<_>, _>>());
            let err = match result {
                Ok(frames) => panic!("{}: read {} frames", path.display(), frames.len()),
                Err(e) => e.to_string(),
            };
            println!("{decoder:?} {}: {err}", path.display());
            assert!(!err.contains('\n'), "one line: {err}");
            assert!(
                err.contains(&*path.display().to_string()),
                "names the file: {err}"
            );
            if decoder == DecoderChoice::Auto {
                assert!(
                    err.contains(expected),
                    "{}: expected `{expected}` in: {err}",
                    path.display()
                );
            }
        }
    }
    // Metadata alone does not decode, so a truncated-at-the-end file still has its metadata;
    // the frames are what fail.
    assert!(probe(&cut_fs, &ReadOptions::default(), false).is_ok());
}

#[test]
fn image_folders_and_single_images() {
    let dir = scratch("read-images");
    let folder = dir.join("frames");
    std::fs::create_dir_all(&folder).unwrap();
    let frame = |i: u8| image::RgbImage::from_fn(8, 6, |x, y| image::Rgb([i, x as u8, y as u8]));
    for i in [1u8, 2, 10, 0] {
        frame(i).save(folder.join(format!("img{i}.png"))).unwrap();
    }
    std::fs::write(folder.join("notes.txt"), "ignored").unwrap();
    std::fs::write(folder.join(".hidden.png"), "ignored").unwrap();
    let (meta, frames) = read_all(&folder, &ReadOptions::default());
    assert_eq!((meta.width, meta.height, meta.frames), (8, 6, Some(4)));
    assert_eq!(meta.fps, 25.0);
    assert_eq!(meta.decoder.as_str(), "image");
    // Natural order: img0, img1, img2, img10.
    let firsts: Vec<u8> = frames.iter().map(|f| f.rgb.as_raw()[0]).collect();
    assert_eq!(firsts, vec![0, 1, 2, 10]);
    let pts: Vec<f64> = frames.iter().map(|f| f.pts).collect();
    assert_eq!(pts, vec![0.0, 0.04, 0.08, 0.12]);

    let (meta, frames) = read_all(
        &folder,
        &ReadOptions {
            fps: Some(10.0),
            start: Start::Seconds(0.15),
            ..ReadOptions::default()
        },
    );
    assert_eq!(meta.fps, 10.0);
    assert_eq!(frames.len(), 2, "frames at 0.2 and 0.3 s");
    assert_eq!(frames[0].rgb.as_raw()[0], 2);

    let single = folder.join("img2.png");
    let (meta, frames) = read_all(&single, &ReadOptions::default());
    assert_eq!(
        (meta.frames, frames.len(), meta.codec.as_str()),
        (Some(1), 1, "png")
    );
    assert_eq!(frames[0].rgb, frame(2));

    // A frame of another size, and an empty folder, are clear errors.
    image::RgbImage::new(4, 4)
        .save(folder.join("img11.png"))
        .unwrap();
    let r = VideoReader::open(&folder, &ReadOptions::default())
        .unwrap()
        .collect::<Result<Vec<_>, _>>();
    let err = r.unwrap_err().to_string();
    assert!(err.contains("img11.png") && err.contains("4x4"), "{err}");
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let err = VideoReader::open(&empty, &ReadOptions::default())
        .err()
        .unwrap();
    assert!(matches!(err, VideoError::NoVideoFrames { .. }), "{err}");
}

/// The release tracker's demo clips (xg-chu/GAGAvatar_track `demos/obama.mp4`: H.264 High,
/// B-frames, 241 frames per ffprobe; `demos/track_obama.gif`: 30 frames), which are not part of
/// this repository: `GAGAVATAR_DEMO_VIDEOS=obama.mp4:track_obama.gif cargo test -p
/// gagavatar-video --test read -- --ignored`.
#[test]
#[ignore = "needs GAGAVATAR_DEMO_VIDEOS (release demo clips, PATH syntax) and ffmpeg"]
fn the_release_demo_videos_decode_fully() {
    let paths =
        std::env::var_os("GAGAVATAR_DEMO_VIDEOS").expect("GAGAVATAR_DEMO_VIDEOS=a.mp4:b.gif");
    assert!(
        ffmpeg_or_skip("the_release_demo_videos_decode_fully"),
        "needs ffmpeg"
    );
    for path in std::env::split_paths(&paths) {
        check_against_ffmpeg(&path.display().to_string(), &path, &ReadOptions::default());
    }
}

#[test]
fn writer_and_reader_agree_without_ffmpeg() {
    // Needs no ffmpeg: the built-in path reads what the writer wrote, at its timestamps.
    let dir = scratch("read-builtin");
    let path = dir.join("own.mp4");
    let inputs = common::write_video(&path, 64, 48, 6, common::no_watermark(12.5));
    let (meta, frames) = read_all(
        &path,
        &ReadOptions {
            decoder: DecoderChoice::OpenH264,
            ..ReadOptions::default()
        },
    );
    assert_eq!((meta.width, meta.height, meta.frames), (64, 48, Some(6)));
    assert!((meta.fps - 12.5).abs() < 1e-9);
    assert_eq!(frames.len(), 6);
    for (i, (f, input)) in frames.iter().zip(&inputs).enumerate() {
        assert_eq!(f.pts, i as f64 / 12.5);
        let p = common::psnr(f.rgb.as_raw(), input);
        assert!(p > 30.0, "frame {i}: PSNR {p:.1} dB");
    }
}
