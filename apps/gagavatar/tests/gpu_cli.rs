//! `--device` end to end on seeded `tiny` weights: `reenact` and `orbit` on the GPU give the
//! CPU's frames, `bench drive` prints its per-stage report on both devices, and a missing
//! adapter is one clear line (`--device gpu`) or a fallback to the CPU (`--device auto`).
//!
//! The GPU here is whatever Vulkan device exists; in CI that is Mesa's lavapipe, which
//! `.ci/run` installs, setting GAGAVATAR_REQUIRE_GPU_TESTS=1 so that no device is a failure.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

mod common;

use common::{strs, Fixture, BIN};

/// Frames are 8-bit: the GPU's and the CPU's f32 images (within 1e-6 at this size, see
/// crates/gpu) can round to neighbouring levels where a value sits on a half step.
const RGB8_TOL: i32 = 1;
/// An adapter name no device has, to simulate a machine without one.
const NO_SUCH_ADAPTER: &str = "no-such-adapter-4c0e511";
/// One tiny-preset frame of `bench drive --device auto`: the GPU when one is found, else the CPU.
const AUTO_DRIVE: [&str; 10] = [
    "bench",
    "drive",
    "--device",
    "auto",
    "--preset",
    "tiny",
    "--frames",
    "1",
    "--threads",
    "1",
];

/// Mesa's window-system code prints a line on stderr when XDG_RUNTIME_DIR is unset (nothing
/// here opens a window); a private one keeps stderr to the program's own lines.
fn runtime_dir() -> &'static PathBuf {
    static D: OnceLock<PathBuf> = OnceLock::new();
    D.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("gagavatar_gpu_xdg_{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&d, std::fs::Permissions::from_mode(0o700)).unwrap();
        }
        d
    })
}

fn run(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut c = Command::new(BIN);
    c.args(args);
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        c.env("XDG_RUNTIME_DIR", runtime_dir());
    }
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().expect("running the gagavatar binary")
}

fn ok(args: &[&str]) -> Output {
    let out = run(args, &[]);
    assert!(
        out.status.success(),
        "gagavatar {args:?} failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Whether a GPU device exists; without one the GPU tests are skipped, unless CI requires
/// them.
fn have_gpu(out: &Output) -> bool {
    if out.status.success() {
        return true;
    }
    let err = String::from_utf8_lossy(&out.stderr);
    if err.contains("no GPU adapter found")
        && !std::env::var("GAGAVATAR_REQUIRE_GPU_TESTS").is_ok_and(|v| v != "0")
    {
        eprintln!("skipping GPU test: {err}");
        return false;
    }
    panic!("gagavatar --device gpu failed:\n{err}");
}

/// A driving record with the eyes turned a little, so that the eye path is compared too.
fn record(exp: f64, yaw: f64) -> serde_json::Value {
    let mut r = common::record_turned(exp, yaw);
    r["eyecode"] = serde_json::json!([0.01, 0, 0, 0, 0.02, 0]);
    r
}

/// The common fixture (tiny weights from seed 9) plus a 4-frame `driver.json`.
fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let f = Fixture::with_seed("gpu_cli", 9);
        let frames: Vec<_> = (0..4)
            .map(|i| record(0.5 * i as f64, 0.15 * i as f64))
            .collect();
        std::fs::write(
            f.path("driver.json"),
            serde_json::json!({"fps": 10, "frames": frames}).to_string(),
        )
        .unwrap();
        f
    })
}

fn avatar_cmd(f: &Fixture, sub: &str, extra: &[&str]) -> Vec<String> {
    f.avatar_args(sub, &[], extra)
}

fn pngs(dir: &Path) -> Vec<(String, image::RgbImage)> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
        .into_iter()
        .map(|n| {
            let img = image::open(dir.join(&n)).unwrap().to_rgb8();
            (n, img)
        })
        .collect()
}

/// The same frames, to within one 8-bit level.
fn assert_same_frames(what: &str, cpu: &Path, gpu: &Path) {
    let (a, b) = (pngs(cpu), pngs(gpu));
    assert_eq!(
        a.iter().map(|x| &x.0).collect::<Vec<_>>(),
        b.iter().map(|x| &x.0).collect::<Vec<_>>(),
        "{what}: frame names"
    );
    assert!(!a.is_empty(), "{what}: no frames");
    for ((name, x), (_, y)) in a.iter().zip(&b) {
        assert_eq!(x.dimensions(), y.dimensions(), "{what} {name}: size");
        let (mut worst, mut at) = (0, 0);
        for (i, (p, q)) in x.as_raw().iter().zip(y.as_raw()).enumerate() {
            let d = (*p as i32 - *q as i32).abs();
            if d > worst {
                (worst, at) = (d, i);
            }
        }
        assert!(
            worst <= RGB8_TOL,
            "{what} {name}: byte {at} differs by {worst} (cpu {}, gpu {})",
            x.as_raw()[at],
            y.as_raw()[at]
        );
        // Not all black: a frame that rendered nothing would pass trivially.
        assert!(
            x.as_raw().iter().any(|&v| v > 0),
            "{what} {name}: empty frame"
        );
    }
}

#[test]
fn reenact_and_orbit_on_the_gpu_match_the_cpu() {
    let f = fixture();
    for (sub, extra) in [
        ("reenact", vec!["--driver".to_string(), f.s("driver.json")]),
        (
            "orbit",
            vec!["--frames".into(), "3".into(), "--yaw".into(), "20".into()],
        ),
    ] {
        let mut outs = Vec::new();
        for device in ["cpu", "gpu"] {
            let dir = f.s(&format!("{sub}_{device}"));
            let mut e: Vec<&str> = extra.iter().map(String::as_str).collect();
            e.extend(["--device", device, "--no-watermark", "-o", &dir]);
            let args = avatar_cmd(f, sub, &e);
            let out = run(&strs(&args), &[]);
            if device == "gpu" && !have_gpu(&out) {
                return;
            }
            assert!(
                out.status.success(),
                "{sub} --device {device}:\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
            if device == "gpu" {
                let err = String::from_utf8_lossy(&out.stderr);
                assert!(
                    err.contains("rendering on"),
                    "{sub}: no device line in\n{err}"
                );
                assert!(err.contains("GPU drive"), "{sub}: no GPU timing in\n{err}");
            }
            outs.push(dir);
        }
        assert_same_frames(sub, Path::new(&outs[0]), Path::new(&outs[1]));
    }
}

/// A `.ply` export's header and its values (all f32 properties) after the header.
fn ply_values(path: &Path) -> (String, Vec<f32>) {
    let bytes = std::fs::read(path).unwrap();
    let end = b"end_header\n";
    let at = bytes
        .windows(end.len())
        .position(|w| w == end)
        .expect("a ply header")
        + end.len();
    let header = String::from_utf8_lossy(&bytes[..at]).into_owned();
    assert!(
        header
            .lines()
            .filter(|l| l.starts_with("property"))
            .all(|l| l.starts_with("property float ")),
        "every property is f32:\n{header}"
    );
    (header, bytemuck_f32(&bytes[at..]))
}

fn bytemuck_f32(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// Values of a `.ply` from the GPU's reconstruct against the CPU's: the Gaussians agree to
/// 1e-4 of each attribute's range (reconstruct's own test); the export's logit and log
/// transforms can stretch that where an opacity is near 0 or 1.
const PLY_TOL: f64 = 2e-3;

/// `export-ply --device gpu` reconstructs on the GPU (lavapipe here) and writes the Gaussians
/// the CPU's reconstruct writes.
#[test]
fn export_ply_on_the_gpu_matches_the_cpu() {
    let f = fixture();
    let mut files = Vec::new();
    for device in ["cpu", "gpu"] {
        let path = f.s(&format!("avatar_{device}.ply"));
        let args = avatar_cmd(f, "export-ply", &["--device", device, "-o", &path]);
        let out = run(&strs(&args), &[]);
        if device == "gpu" && !have_gpu(&out) {
            return;
        }
        assert!(
            out.status.success(),
            "export-ply --device {device}:\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        if device == "gpu" {
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(
                err.contains("reconstructing on"),
                "no device line in\n{err}"
            );
        }
        files.push(path);
    }
    let (ha, a) = ply_values(Path::new(&files[0]));
    let (hb, b) = ply_values(Path::new(&files[1]));
    assert_eq!(ha, hb, "headers");
    assert_eq!(a.len(), b.len());
    let (mut worst, mut at) = (0f64, 0);
    for (i, (x, y)) in a.iter().zip(&b).enumerate() {
        let d = (*x as f64 - *y as f64).abs() / (1.0 + (*x as f64).abs());
        if d > worst || d.is_nan() {
            worst = if d.is_nan() { f64::INFINITY } else { d };
            at = i;
        }
    }
    assert!(
        worst <= PLY_TOL,
        "value {at}: cpu {}, gpu {} (relative {worst:e} > {PLY_TOL:e})",
        a[at],
        b[at]
    );
}

#[test]
fn bench_drive_reports_stages_on_both_devices() {
    let out = run(
        &[
            "bench", "drive", "--device", "gpu", "--preset", "tiny", "--frames", "3",
        ],
        &[],
    );
    if !have_gpu(&out) {
        return;
    }
    let text = String::from_utf8_lossy(&out.stdout);
    for want in [
        "drive on the GPU",
        "FLAME",
        "splat: project + sort + bin",
        "splat: raster",
        "renderer: U-Net + SFT",
        "renderer: mapping + decoder",
        "frames/s",
        "streamed (frame i + 1 rendering while frame i is read back",
    ] {
        assert!(
            text.contains(want),
            "bench drive --device gpu: no `{want}` in\n{text}"
        );
    }
    let out = ok(&[
        "bench",
        "drive",
        "--device",
        "cpu",
        "--preset",
        "tiny",
        "--frames",
        "2",
        "--threads",
        "1",
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    for want in [
        "drive on the CPU (1 threads)",
        "FLAME",
        "splat",
        "renderer",
        "frames/s",
    ] {
        assert!(
            text.contains(want),
            "bench drive --device cpu: no `{want}` in\n{text}"
        );
    }
}

/// `bench renderer-grad` times the renderer's training step on the GPU (with its JSON) and on
/// the CPU.
#[test]
fn bench_renderer_grad_runs_on_both_devices() {
    let json = std::env::temp_dir().join(format!("gagavatar_grad_{}.json", std::process::id()));
    let json_arg = json.to_string_lossy().to_string();
    let out = run(
        &[
            "bench",
            "renderer-grad",
            "--device",
            "gpu",
            "--preset",
            "tiny",
            "--runs",
            "1",
            "--json",
            &json_arg,
        ],
        &[],
    );
    if !have_gpu(&out) {
        return;
    }
    let text = String::from_utf8_lossy(&out.stdout);
    for want in [
        "renderer forward + backward on the GPU",
        "backward dispatches",
        "median",
    ] {
        assert!(
            text.contains(want),
            "bench renderer-grad --device gpu: no `{want}` in\n{text}"
        );
    }
    // The training kernels are f32 whatever the adapter offers, and the device line says so.
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("(f32 convolutions)"), "{err}");
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&json).expect("the JSON")).expect("valid JSON");
    assert!(
        doc["step_ms"]["median"].as_f64().is_some_and(|v| v > 0.0),
        "{doc}"
    );
    let refused = run(
        &[
            "bench",
            "renderer-grad",
            "--device",
            "gpu",
            "--gpu-precision",
            "f16",
            "--preset",
            "tiny",
        ],
        &[],
    );
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(
        !refused.status.success() && err.contains("--gpu-precision f16 is for rendering"),
        "f16 training was not refused: {err}"
    );
    let out = ok(&[
        "bench",
        "renderer-grad",
        "--device",
        "cpu",
        "--preset",
        "tiny",
        "--runs",
        "1",
        "--threads",
        "1",
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("renderer forward + backward on the CPU (candle autograd): tiny (1 threads)"),
        "bench renderer-grad --device cpu:\n{text}"
    );
}

/// `bench dpt-grad` times the DPT head's training forward and backward on the GPU and on the
/// CPU.
#[test]
fn bench_dpt_grad_runs_on_both_devices() {
    let out = run(
        &[
            "bench", "dpt-grad", "--device", "gpu", "--preset", "tiny", "--runs", "1",
        ],
        &[],
    );
    if !have_gpu(&out) {
        return;
    }
    let text = String::from_utf8_lossy(&out.stdout);
    for want in [
        "DPT head forward + backward on the GPU",
        "tiny: 56 weight tensors, f32",
        "every DPT weight's gradient: median",
    ] {
        assert!(
            text.contains(want),
            "bench dpt-grad --device gpu: no `{want}` in\n{text}"
        );
    }
    let out = ok(&[
        "bench",
        "dpt-grad",
        "--device",
        "cpu",
        "--preset",
        "tiny",
        "--runs",
        "1",
        "--threads",
        "1",
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("DPT head forward + backward on the CPU (candle autograd): tiny (1 threads)"),
        "bench dpt-grad --device cpu:\n{text}"
    );
}

/// `train-bench --device gpu` with a frozen backbone (the release's setting, here on the tiny
/// model) runs the backbone and the DPT head on the GPU too, and says so.
#[test]
fn train_bench_with_a_frozen_backbone_runs_the_dpt_head_on_the_gpu() {
    let tiny = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../crates/train/configs/tiny.toml"),
    )
    .expect("the tiny preset");
    assert!(
        tiny.contains("\n[model]\n"),
        "no [model] table in the tiny preset"
    );
    let cfg = std::env::temp_dir().join(format!("gagavatar_frozen_{}.toml", std::process::id()));
    std::fs::write(
        &cfg,
        tiny.replace("\n[model]\n", "\n[model]\nfreeze_backbone = true\n"),
    )
    .unwrap();
    let out = run(
        &[
            "train-bench",
            "--config",
            &cfg.to_string_lossy(),
            "--batch",
            "1",
            "--runs",
            "1",
            "--device",
            "gpu",
        ],
        &[],
    );
    if !have_gpu(&out) {
        return;
    }
    let text = String::from_utf8_lossy(&out.stdout);
    for want in [
        "(backbone, DPT head, lifting generators, splatting and renderer on ",
        "(backbone frozen)",
        "split step medians",
    ] {
        assert!(
            text.contains(want),
            "train-bench --device gpu: no `{want}` in\n{text}"
        );
    }
}

/// `bench splat --device gpu` times the splatting's training forward and backward.
#[test]
fn bench_splat_runs_the_backward_on_the_gpu() {
    let out = run(
        &[
            "bench",
            "splat",
            "--device",
            "gpu",
            "--plane",
            "4",
            "--channels",
            "4",
            "--runs",
            "1",
            "--regime",
            "small",
        ],
        &[],
    );
    if !have_gpu(&out) {
        return;
    }
    let text = String::from_utf8_lossy(&out.stdout);
    for want in [
        "on the GPU",
        "training forward median",
        "backward median",
        "tile pairs",
    ] {
        assert!(
            text.contains(want),
            "bench splat --device gpu: no `{want}` in\n{text}"
        );
    }
}

#[test]
fn no_adapter_is_one_line_for_gpu_and_a_fallback_for_auto() {
    let env = [("GAGAVATAR_GPU_ADAPTER", NO_SUCH_ADAPTER)];
    let out = run(
        &[
            "bench", "drive", "--device", "gpu", "--preset", "tiny", "--frames", "1",
        ],
        &env,
    );
    assert!(
        !out.status.success(),
        "--device gpu without an adapter succeeded"
    );
    let err = String::from_utf8_lossy(&out.stderr);
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "expected one error line, got:\n{err}");
    assert!(lines[0].contains("no GPU adapter found"), "{err}");
    assert!(lines[0].contains(NO_SUCH_ADAPTER), "{err}");

    let out = run(&AUTO_DRIVE, &env);
    assert!(
        out.status.success(),
        "--device auto without an adapter failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("rendering on the CPU"),
        "no fallback note in\n{err}"
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("drive on the CPU"));
}

/// `bench drive --json` writes the figures it prints; `--gpu-precision f16` on a GPU without
/// tensor cores (lavapipe) is one clear line, and f32 / auto render there.
#[test]
fn bench_json_and_gpu_precision() {
    let dir = std::env::temp_dir().join(format!("gagavatar_bench_json_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("bench.json");
    let json_s = json.to_str().unwrap();
    let out = run(
        &[
            "bench",
            "drive",
            "--device",
            "gpu",
            "--preset",
            "tiny",
            "--frames",
            "2",
            "--json",
            json_s,
            "--dispatches",
        ],
        &[],
    );
    if !have_gpu(&out) {
        return;
    }
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&json).expect("bench.json written")).unwrap();
    for key in [
        "adapter",
        "stage_ms",
        "frame_ms",
        "frames_per_s",
        "gpu_buffers_mib",
    ] {
        assert!(doc.get(key).is_some(), "no `{key}` in {doc}");
    }
    assert_eq!(doc["frames"], 2);
    assert!(doc["frames_per_s"].as_f64().unwrap() > 0.0);
    let stages = doc["stage_ms"].as_object().unwrap();
    assert!(stages.contains_key("splat: raster"), "{doc}");
    let tensor_cores = doc["tensor_core_convs"].as_bool().unwrap();
    if doc["adapter"]["timestamps"].as_bool().unwrap() {
        let d = doc["dispatches"].as_array().unwrap();
        assert!(d.len() > 10, "{doc}");
        assert!(d.iter().all(|k| k["ms"].as_f64().unwrap() >= 0.0), "{doc}");
        assert!(
            d.iter()
                .any(|k| k["kernel"].as_str().unwrap().starts_with("conv")),
            "{doc}"
        );
    }

    let f16 = run(
        &[
            "bench",
            "drive",
            "--device",
            "gpu",
            "--preset",
            "tiny",
            "--frames",
            "1",
            "--gpu-precision",
            "f16",
        ],
        &[],
    );
    if tensor_cores {
        assert!(
            f16.status.success(),
            "{}",
            String::from_utf8_lossy(&f16.stderr)
        );
    } else {
        assert!(
            !f16.status.success(),
            "--gpu-precision f16 without tensor cores succeeded"
        );
        let err = String::from_utf8_lossy(&f16.stderr);
        let last = err.lines().rfind(|l| !l.trim().is_empty()).unwrap_or("");
        assert!(last.contains("tensor cores"), "{err}");
        assert_eq!(
            err.lines().filter(|l| l.starts_with("error")).count(),
            1,
            "{err}"
        );
    }
    ok(&[
        "bench",
        "drive",
        "--device",
        "gpu",
        "--preset",
        "tiny",
        "--frames",
        "1",
        "--gpu-precision",
        "f32",
    ]);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Without XDG_RUNTIME_DIR (a container, CI) probing the adapters prints nothing of Mesa's:
/// `--device auto` says in one line where frames render, and nothing else reaches stderr.
#[test]
fn probing_is_quiet_without_a_runtime_dir() {
    let out = Command::new(BIN)
        .args(AUTO_DRIVE)
        .env_remove("XDG_RUNTIME_DIR")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !err.contains("XDG_RUNTIME_DIR"),
        "Mesa's probe noise:\n{err}"
    );
    let device_lines: Vec<&str> = err.lines().filter(|l| l.contains("rendering on")).collect();
    assert_eq!(device_lines.len(), 1, "{err}");
}
