//! End to end: `reenact`, `orbit` and `export-ply` on seeded `tiny` weights and the synthetic
//! FLAME asset, plus every bad-input case of the issue (one clear error line, non-zero exit, no
//! output or temp file left behind).

use std::path::Path;
use std::process::Command;
use std::sync::OnceLock;

use gagavatar_splat::scene::covariance;
use gagavatar_splat::GaussianScene;

mod common;

use common::{ok, record_turned as record, run, strs, Fixture, BIN};

/// The tiny preset renders 64x64 frames.
const SIZE: usize = common::SIZE as usize;
/// Opacities go through a logit and back in f32: a few ulps of 1.
const OPACITY_TOL: f64 = 1e-5;
/// Covariances from the unit-quaternion form, relative to the largest entry: f32 storage.
const COV_REL_TOL: f64 = 1e-4;

/// The common fixture plus `src_100x80.png`, `expr.json` and a 5-frame `driver.json`; made once
/// and shared by every test here.
fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let f = Fixture::new("animate");
        let big = image::RgbImage::from_fn(100, 80, |x, y| image::Rgb([x as u8, y as u8, 7]));
        big.save(f.path("src_100x80.png")).unwrap();
        std::fs::write(f.path("expr.json"), record(0.8, 0.0).to_string()).unwrap();
        let frames: Vec<_> = (0..5)
            .map(|i| record(0.4 * i as f64, 0.1 * i as f64))
            .collect();
        std::fs::write(
            f.path("driver.json"),
            serde_json::json!({"fps": 10, "frames": frames}).to_string(),
        )
        .unwrap();
        f
    })
}

/// `gagavatar <sub> <source args> <extra>`.
fn avatar_cmd(f: &Fixture, sub: &str, extra: &[&str]) -> Vec<String> {
    f.avatar_args(sub, &[], extra)
}

fn release_small() -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../crates/data/tests/data/release_small")
        .display()
        .to_string()
}

/// Names in `dir` (to prove a failed command left nothing behind, temp files included).
fn listing(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn reenact_json_driver_writes_a_decodable_mp4() {
    let f = fixture();
    let out = f.s("reenact.mp4");
    let args = avatar_cmd(f, "reenact", &["--driver", &f.s("driver.json"), "-o", &out]);
    let res = ok(&strs(&args));
    let log = String::from_utf8_lossy(&res.stderr);
    for stage in [
        "FLAME",
        "splatting",
        "neural renderer",
        "video encoding",
        "total wall",
    ] {
        assert!(log.contains(stage), "time split lacks `{stage}`:\n{log}");
    }
    let info = gagavatar_video::mp4::read_mp4_info(Path::new(&out)).unwrap();
    assert_eq!((info.frames, info.width, info.height), (5, SIZE, SIZE));
    assert!((info.fps - 10.0).abs() < 1e-9, "fps {}", info.fps);
    let frames = gagavatar_video::mp4::decode_mp4(Path::new(&out)).unwrap();
    assert_eq!(frames.len(), 5);
    assert!(frames.iter().all(|fr| fr.len() == SIZE * SIZE * 3));
    // Different expressions and cameras give different frames.
    assert_ne!(frames[0], frames[4]);
}

#[test]
fn reenact_release_folder_side_by_side_range_batch_and_png_output() {
    let f = fixture();
    let out = f.s("sbs.mp4");
    let driver = release_small();
    let args = avatar_cmd(
        f,
        "reenact",
        &[
            "--driver",
            &driver,
            "--side-by-side",
            "--start",
            "1",
            "--max-frames",
            "4",
            "--batch",
            "3",
            "--fps",
            "12.5",
            "-o",
            &out,
        ],
    );
    ok(&strs(&args));
    let info = gagavatar_video::mp4::read_mp4_info(Path::new(&out)).unwrap();
    assert_eq!((info.frames, info.width, info.height), (4, 2 * SIZE, SIZE));
    assert!((info.fps - 12.5).abs() < 1e-9);

    // The same frames one at a time into PNGs, without the watermark: batching must not change
    // a pixel (the fixed noise buffers make each frame deterministic).
    let dir_b1 = f.s("pngs_b1/");
    let dir_b3 = f.s("pngs_b3/");
    for (dir, batch) in [(&dir_b1, "1"), (&dir_b3, "3")] {
        let args = avatar_cmd(
            f,
            "reenact",
            &[
                "--driver",
                &driver,
                "--max-frames",
                "3",
                "--batch",
                batch,
                "--no-watermark",
                "-o",
                dir,
            ],
        );
        ok(&strs(&args));
    }
    for k in 0..3 {
        let name = format!("frame_{k:05}.png");
        let a = image::open(Path::new(&dir_b1).join(&name))
            .unwrap()
            .to_rgb8();
        let b = image::open(Path::new(&dir_b3).join(&name))
            .unwrap()
            .to_rgb8();
        assert_eq!(a.dimensions(), (SIZE as u32, SIZE as u32));
        let worst = a
            .as_raw()
            .iter()
            .zip(b.as_raw())
            .map(|(x, y)| (*x as i32 - *y as i32).abs())
            .max()
            .unwrap();
        // Batched GEMMs may sum in another order: at most one level of 8-bit rounding.
        assert!(
            worst <= 1,
            "frame {k}: batch 1 vs 3 differ by {worst} levels"
        );
    }
    assert_eq!(listing(Path::new(&dir_b1)).len(), 3);
}

#[test]
fn orbit_writes_gif_and_png_frames() {
    let f = fixture();
    let gif_path = f.s("orbit.gif");
    let args = avatar_cmd(
        f,
        "orbit",
        &["--frames", "6", "--yaw", "25", "-o", &gif_path],
    );
    ok(&strs(&args));
    let file = std::fs::File::open(&gif_path).unwrap();
    let mut opts = gif::DecodeOptions::new();
    opts.set_color_output(gif::ColorOutput::RGBA);
    let mut dec = opts.read_info(file).unwrap();
    assert_eq!((dec.width() as usize, dec.height() as usize), (SIZE, SIZE));
    let mut n = 0;
    while dec.read_next_frame().unwrap().is_some() {
        n += 1;
    }
    assert_eq!(n, 6);

    let dir = f.s("orbit_pngs");
    let args = avatar_cmd(
        f,
        "orbit",
        &[
            "--frames",
            "4",
            "--expression",
            &f.s("expr.json"),
            "--no-watermark",
            "-o",
            &dir,
        ],
    );
    ok(&strs(&args));
    let names = listing(Path::new(&dir));
    assert_eq!(
        names,
        [
            "frame_00000.png",
            "frame_00001.png",
            "frame_00002.png",
            "frame_00003.png"
        ]
    );
    let a = image::open(Path::new(&dir).join(&names[0]))
        .unwrap()
        .to_rgb8();
    let b = image::open(Path::new(&dir).join(&names[1]))
        .unwrap()
        .to_rgb8();
    assert_ne!(a, b, "the camera moved, the frames must differ");
}

#[test]
fn export_ply_holds_the_dumped_gaussians() {
    let f = fixture();
    let ply = f.s("avatar.ply");
    let args = avatar_cmd(
        f,
        "export-ply",
        &["--expression", &f.s("expr.json"), "-o", &ply],
    );
    ok(&strs(&args));
    let dump = f.s("dump.safetensors");
    let args = avatar_cmd(
        f,
        "dump",
        &["--target-record", &f.s("expr.json"), "-o", &dump],
    );
    ok(&strs(&args));
    let scene = GaussianScene::load(Path::new(&ply)).unwrap();
    let t = candle_core::safetensors::load(&dump, &candle_core::Device::Cpu).unwrap();
    let get = |k: &str| -> Vec<f32> { t[k].flatten_all().unwrap().to_vec1().unwrap() };
    let (xyz, col, op, sc, rot) = (
        get("gs_xyz"),
        get("gs_colors"),
        get("gs_opacities"),
        get("gs_scales"),
        get("gs_rotations"),
    );
    let n = op.len();
    assert_eq!(scene.len(), n);
    assert_eq!(scene.channels, 32);
    assert_eq!(scene.means, xyz, "positions");
    assert_eq!(scene.features, col, "features");
    for i in 0..n {
        let (a, b) = (op[i] as f64, scene.opacities[i] as f64);
        assert!(
            (a - b).abs() <= OPACITY_TOL,
            "opacity {i}: expected {a} got {b}"
        );
        let q = |v: &[f32]| -> [f64; 4] { std::array::from_fn(|k| v[4 * i + k] as f64) };
        let s = |v: &[f32]| -> [f64; 3] { std::array::from_fn(|k| v[3 * i + k] as f64) };
        let want = covariance(q(&rot), s(&sc));
        let got = covariance(q(&scene.rotations), s(&scene.scales));
        let unit: f64 = q(&scene.rotations)
            .iter()
            .map(|x| x * x)
            .sum::<f64>()
            .sqrt();
        assert!((unit - 1.0).abs() < 1e-5, "rotation {i} not unit: {unit}");
        let big = want.iter().flatten().fold(1e-30f64, |m, x| m.max(x.abs()));
        for r in 0..3 {
            for c in 0..3 {
                assert!(
                    (want[r][c] - got[r][c]).abs() <= COV_REL_TOL * big,
                    "covariance {i} [{r}][{c}]: expected {} got {}",
                    want[r][c],
                    got[r][c]
                );
            }
        }
    }
    // And the splat command reads it back.
    let cam = f.path("cam.json");
    std::fs::write(
        &cam,
        r#"{"transform_matrix": [[-1,0,0,0],[0,1,0,0],[0,0,-1,9]], "width": 64, "height": 64}"#,
    )
    .unwrap();
    ok(&[
        "splat",
        "--scene",
        &ply,
        "--camera",
        &cam.display().to_string(),
        "-o",
        &f.s("ply.png"),
    ]);
}

#[test]
fn wrong_image_size_is_resized_with_a_notice() {
    let f = fixture();
    let mut args = avatar_cmd(f, "orbit", &["--frames", "2", "-o", &f.s("resized.gif")]);
    let i = args.iter().position(|a| a == "--source").unwrap();
    args[i + 1] = f.s("src_100x80.png");
    let res = ok(&strs(&args));
    let log = String::from_utf8_lossy(&res.stderr);
    assert!(log.contains("resizing"), "no resize notice:\n{log}");
}

/// `--fresh-noise` draws the renderer's noise anew: two runs differ, while two runs with the
/// fixed buffers are identical.
#[test]
fn fresh_noise_changes_the_frames_and_fixed_noise_repeats_them() {
    let f = fixture();
    let render = |tag: &str, fresh: bool| -> image::RgbImage {
        let dir = f.s(&format!("noise_{tag}/"));
        let mut extra = vec!["--frames", "1", "--no-watermark", "-o", &dir];
        if fresh {
            extra.push("--fresh-noise");
        }
        ok(&strs(&avatar_cmd(f, "orbit", &extra)));
        image::open(Path::new(&dir).join("frame_00000.png"))
            .unwrap()
            .to_rgb8()
    };
    assert!(
        render("fixed_1", false) == render("fixed_2", false),
        "fixed noise: two runs differ"
    );
    let (a, b) = (render("fresh_1", true), render("fresh_2", true));
    let changed = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .filter(|(x, y)| x != y)
        .count();
    assert!(changed > 0, "--fresh-noise: two runs gave the same frame");
    eprintln!(
        "--fresh-noise: {changed} of {} channel values changed",
        a.as_raw().len()
    );
}

/// Runs a command that must fail: non-zero exit, an `error:` line naming `needle`, no panic, and
/// nothing new in the output directory.
fn fails(args: &[String], out_dir: &Path, needle: &str) {
    let before = listing(out_dir);
    let res = run(&strs(args));
    let log = String::from_utf8_lossy(&res.stderr);
    assert!(!res.status.success(), "{args:?} succeeded");
    assert!(!log.contains("panicked"), "{args:?} panicked:\n{log}");
    let last = log.lines().last().unwrap_or("");
    assert!(
        last.starts_with("error: "),
        "{args:?}: last line is not an error:\n{log}"
    );
    assert!(
        last.contains(needle),
        "{args:?}: error does not mention `{needle}`:\n{log}"
    );
    assert_eq!(listing(out_dir), before, "{args:?} left files behind");
}

#[test]
fn bad_inputs_fail_cleanly() {
    let f = fixture();
    let bad = f.path("bad");
    std::fs::create_dir_all(&bad).unwrap();
    let b = |name: &str| bad.join(name).display().to_string();
    let out = b("out.mp4");
    let driver = f.s("driver.json");

    // Corrupt and wrong files.
    std::fs::write(bad.join("garbage.safetensors"), b"not a checkpoint").unwrap();
    std::fs::write(bad.join("garbage.png"), b"\x89PNG but not really").unwrap();
    std::fs::write(bad.join("garbage.json"), b"{\"fps\": 25, \"frames\": [").unwrap();
    let frames = |edit: &dyn Fn(&mut serde_json::Value)| {
        let mut frames: Vec<_> = (0..3).map(|i| record(0.1 * i as f64, 0.0)).collect();
        edit(&mut frames[2]);
        serde_json::json!({"fps": 25, "frames": frames}).to_string()
    };
    std::fs::write(
        bad.join("missing_field.json"),
        frames(&|r| {
            r.as_object_mut().unwrap().remove("expcode");
        }),
    )
    .unwrap();
    std::fs::write(
        bad.join("misshapen.json"),
        frames(&|r| r["expcode"] = serde_json::json!(vec![0.1; 150])),
    )
    .unwrap();
    std::fs::write(
        bad.join("no_camera.json"),
        frames(&|r| {
            r.as_object_mut().unwrap().remove("transform_matrix");
        }),
    )
    .unwrap();
    std::fs::write(
        bad.join("nan.json"),
        frames(&|r| r["posecode"] = serde_json::json!([0, 0, 0, "NaN", 0, 0])),
    )
    .unwrap();

    let set = |args: &mut Vec<String>, flag: &str, value: String| {
        let i = args.iter().position(|a| a == flag).unwrap();
        args[i + 1] = value;
    };
    let reenact = |driver: &str| avatar_cmd(f, "reenact", &["--driver", driver, "-o", &out]);

    let mut a = reenact(&driver);
    set(&mut a, "--ckpt", b("missing.safetensors"));
    fails(&a, &bad, "missing.safetensors");

    let mut a = reenact(&driver);
    set(&mut a, "--ckpt", b("garbage.safetensors"));
    fails(&a, &bad, "garbage.safetensors");

    // Tiny weights read as the small architecture: wrong keys and shapes.
    let mut a = reenact(&driver);
    a.extend(["--preset".to_string(), "small".to_string()]);
    fails(&a, &bad, "tiny.safetensors");

    let mut a = reenact(&driver);
    set(&mut a, "--flame", b("missing_flame.pt"));
    fails(&a, &bad, "missing_flame.pt");

    let mut a = reenact(&driver);
    set(&mut a, "--source", b("garbage.png"));
    fails(&a, &bad, "garbage.png");

    let mut a = reenact(&driver);
    set(&mut a, "--source-record", b("missing_field.json"));
    fails(&a, &bad, "missing_field.json");

    fails(&reenact(&b("garbage.json")), &bad, "garbage.json");
    fails(&reenact(&b("missing_field.json")), &bad, "expcode");
    fails(&reenact(&b("misshapen.json")), &bad, "expcode");
    fails(&reenact(&b("no_camera.json")), &bad, "transform_matrix");
    fails(&reenact(&b("nan.json")), &bad, "posecode");
    fails(&reenact(&b("no_such_driver")), &bad, "no_such_driver");

    // A .pkl source record needs a frame name; a wrong one is named.
    let pkl = format!("{}/optim.pkl", release_small());
    let mut a = reenact(&driver);
    set(&mut a, "--source-record", pkl.clone());
    fails(&a, &bad, "source-key");
    a.extend(["--source-key".to_string(), "nobody_7".to_string()]);
    fails(&a, &bad, "nobody_7");

    // Side by side without driver images, and a range past the end.
    let mut a = reenact(&driver);
    a.push("--side-by-side".into());
    fails(&a, &bad, "side-by-side");
    let mut a = reenact(&driver);
    a.extend(["--start".to_string(), "9".to_string()]);
    fails(&a, &bad, "--start");

    // An output folder that does not exist.
    let a = avatar_cmd(
        f,
        "reenact",
        &["--driver", &driver, "-o", &b("no/such/dir/out.mp4")],
    );
    fails(&a, &bad, "no/such/dir");
}

/// The release's record `key` of `release_small/expected.json` (float32 values stored as
/// little-endian hex, CPython's view of `optim.pkl`) as a JSON record with the same numbers.
fn expected_record_json(key: &str) -> serde_json::Value {
    let path = format!("{}/expected.json", release_small());
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let rec = &v["records"][key];
    let values = |field: &str| -> Vec<f64> {
        let hex = rec[field]["hex"].as_str().unwrap();
        let bytes: Vec<u8> = (0..hex.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).unwrap())
            .collect();
        bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64)
            .collect()
    };
    let tm = values("transform_matrix");
    serde_json::json!({
        "shapecode": values("shapecode"),
        "expcode": values("expcode"),
        "posecode": values("posecode"),
        "eyecode": values("eyecode"),
        "transform_matrix": tm.chunks(4).map(|r| r.to_vec()).collect::<Vec<_>>(),
    })
}

/// PNG frames of `reenact` (no watermark) into `dir`, with the source record replaced.
fn reenact_pngs(f: &Fixture, record: &str, extra: &[&str], dir: &str) -> Vec<image::RgbImage> {
    let driver = f.s("driver.json");
    let mut tail = vec![
        "--driver",
        driver.as_str(),
        "--max-frames",
        "2",
        "--no-watermark",
        "-o",
        dir,
    ];
    tail.extend_from_slice(extra);
    let args = f.avatar_args("reenact", &[("--source-record", record.to_string())], &tail);
    ok(&strs(&args));
    (0..2)
        .map(|k| {
            image::open(Path::new(dir).join(format!("frame_{k:05}.png")))
                .unwrap()
                .to_rgb8()
        })
        .collect()
}

#[test]
fn reenact_with_a_release_pkl_source_record() {
    let f = fixture();
    let pkl = format!("{}/optim.pkl", release_small());
    // The pickle's `spk_a_1` gives the very frames its numbers give as a JSON record...
    let from_pkl = reenact_pngs(f, &pkl, &["--source-key", "spk_a_1"], &f.s("pkl_a1/"));
    std::fs::write(
        f.path("spk_a_1.json"),
        expected_record_json("spk_a_1").to_string(),
    )
    .unwrap();
    let from_json = reenact_pngs(f, &f.s("spk_a_1.json"), &[], &f.s("json_a1/"));
    for (k, (a, b)) in from_pkl.iter().zip(&from_json).enumerate() {
        assert!(
            a == b,
            "frame {k}: the .pkl record and its JSON copy render differently"
        );
    }
    // ...and another key of the same pickle gives other frames: the key picks the record.
    let other = reenact_pngs(f, &pkl, &["--source-key", "spk_a_0"], &f.s("pkl_a0/"));
    assert!(
        other[0] != from_pkl[0],
        "spk_a_0 and spk_a_1 render the same frame"
    );
}

#[test]
fn demo_uses_only_shipped_files() {
    let out = std::env::temp_dir().join(format!("gagavatar_demo_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    // Run from a directory without assets/: the binary finds the checkout's assets itself.
    let res = Command::new(BIN)
        .args(["demo", "-o", &out.display().to_string()])
        .current_dir(std::env::temp_dir())
        .output()
        .expect("running the demo");
    assert!(
        res.status.success(),
        "demo failed:\n{}",
        String::from_utf8_lossy(&res.stderr)
    );
    let re = gagavatar_video::mp4::read_mp4_info(&out.join("reenact.mp4")).unwrap();
    let driver: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo/driver.json"),
        )
        .unwrap(),
    )
    .unwrap();
    let n = driver["frames"].as_array().unwrap().len();
    assert_eq!((re.frames, re.width, re.height), (n, 2 * SIZE, SIZE));
    let orbit = gagavatar_video::mp4::read_mp4_info(&out.join("orbit.mp4")).unwrap();
    assert_eq!((orbit.width, orbit.height), (SIZE, SIZE));
    assert!(orbit.frames > 10);
    let scene = GaussianScene::load(&out.join("avatar.ply")).unwrap();
    assert_eq!(scene.channels, 32);
    assert!(!scene.is_empty());
    // The real photo's tracking and its overlay.
    assert!(out.join("astronaut_track/optim.pkl").is_file());
    assert!(out.join("astronaut_track/img_lmdb").exists());
    let overlay = image::open(out.join("astronaut_overlay.png")).unwrap();
    assert_eq!((overlay.width(), overlay.height()), (512, 512));
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn reenact_shows_the_driving_video_beside_the_result() {
    let f = fixture();
    // A 5-frame driving video of flat colours, 96x64 (not square: it is fitted with bars), read
    // by the built-in path, so no ffmpeg is needed.
    let video = f.path("driving.mp4");
    let colours: Vec<[u8; 3]> = (0..5u8).map(|i| [40 * i + 20, 200 - 30 * i, 90]).collect();
    let mut w = gagavatar_video::VideoWriter::create(
        &video,
        96,
        64,
        gagavatar_video::VideoOptions {
            fps: 10.0,
            watermark: false,
        },
    )
    .unwrap();
    for c in &colours {
        w.push_rgb(&c.repeat(96 * 64)).unwrap();
    }
    w.finish().unwrap();
    let out = f.s("driving_sbs/");
    let args = avatar_cmd(
        f,
        "reenact",
        &[
            "--driver",
            &f.s("driver.json"),
            "--driver-video",
            &video.display().to_string(),
            "--start",
            "1",
            "--max-frames",
            "3",
            "--no-watermark",
            "-o",
            &out,
        ],
    );
    ok(&strs(&args));
    for k in 0..3 {
        let img = image::open(Path::new(&out).join(format!("frame_{k:05}.png")))
            .unwrap()
            .to_rgb8();
        assert_eq!(img.dimensions(), (2 * SIZE as u32, SIZE as u32));
        // The left half's centre shows video frame 1 + k; the 96x64 frame fills the width and
        // leaves black bars above and below.
        let c = img.get_pixel(SIZE as u32 / 2, SIZE as u32 / 2).0;
        let e = colours[1 + k];
        let diff = c
            .iter()
            .zip(e)
            .map(|(a, b)| (*a as i32 - b as i32).abs())
            .max();
        assert!(diff <= Some(4), "frame {k}: {c:?} vs {e:?}");
        assert_eq!(img.get_pixel(SIZE as u32 / 2, 2).0, [0, 0, 0], "bar");
    }
    // A video shorter than the driver is refused before rendering.
    let short = f.path("short.mp4");
    let mut w = gagavatar_video::VideoWriter::create(
        &short,
        96,
        64,
        gagavatar_video::VideoOptions::default(),
    )
    .unwrap();
    for c in &colours[..3] {
        w.push_rgb(&c.repeat(96 * 64)).unwrap();
    }
    w.finish().unwrap();
    let args = avatar_cmd(
        f,
        "reenact",
        &[
            "--driver",
            &f.s("driver.json"),
            "--driver-video",
            &short.display().to_string(),
            "--start",
            "1",
            "-o",
            &f.s("never.mp4"),
        ],
    );
    let o = run(&strs(&args));
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--driver-video") && err.contains("has 2 frames"),
        "{err}"
    );
    assert!(!f.path("never.mp4").exists());
}
