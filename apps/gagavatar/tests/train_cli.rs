//! End to end: `synth-data`, then `train` (new run, resume), `eval` and `train-bench` on the
//! tiny preset; and the refusals (an existing run, nothing to resume).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const BIN: &str = env!("CARGO_BIN_EXE_gagavatar");

fn run(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .output()
        .expect("running the gagavatar binary")
}

fn text(o: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

fn ok(args: &[&str]) -> (String, String) {
    let o = run(args);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{args:?} failed:\n{out}\n{err}");
    (out, err)
}

fn fails(args: &[&str], needle: &str) {
    let o = run(args);
    let (out, err) = text(&o);
    assert!(!o.status.success(), "{args:?} succeeded:\n{out}\n{err}");
    assert!(
        err.contains(needle),
        "{args:?}: stderr lacks `{needle}`:\n{err}"
    );
}

fn metric_steps(run: &Path) -> Vec<u64> {
    std::fs::read_to_string(run.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            assert!(v["loss"].as_f64().unwrap().is_finite(), "{l}");
            v["step"].as_u64().unwrap()
        })
        .collect()
}

#[test]
fn train_resume_eval_and_bench() {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("cli_train");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let s = |p: &Path| p.display().to_string();
    let data = dir.join("data");
    let run_dir = dir.join("run");
    ok(&[
        "synth-data",
        "-o",
        &s(&data),
        "--identities",
        "3",
        "--frames",
        "3",
        "--size",
        "64",
        "--holdout",
        "1",
    ]);
    let (_, err) = ok(&[
        "train",
        "--preset",
        "tiny",
        "--data",
        &s(&data),
        "--steps",
        "3",
        "--seed",
        "1",
        "--out",
        &s(&run_dir),
        "--val-every",
        "2",
        "--threads",
        "2",
    ]);
    assert!(err.contains("perceptual term is off"), "{err}");
    assert!(err.contains("trained steps 0..3"), "{err}");
    for f in [
        "config.toml",
        "checkpoint.safetensors",
        "weights.safetensors",
        "val/step_0000002.png",
    ] {
        assert!(run_dir.join(f).exists(), "{f} missing");
    }
    assert_eq!(metric_steps(&run_dir), [1, 2, 3]);

    fails(
        &[
            "train",
            "--preset",
            "tiny",
            "--data",
            &s(&data),
            "--steps",
            "3",
            "--out",
            &s(&run_dir),
        ],
        "--resume",
    );
    let (_, err) = ok(&["train", "--resume", &s(&run_dir), "--steps", "5"]);
    assert!(err.contains("trained steps 3..5"), "{err}");
    assert_eq!(metric_steps(&run_dir), [1, 2, 3, 4, 5]);
    let cfg = std::fs::read_to_string(run_dir.join("config.toml")).unwrap();
    assert!(
        cfg.contains("steps = 5") && cfg.contains("preset = \"tiny\""),
        "{cfg}"
    );
    fails(
        &["train", "--resume", &s(&dir.join("none"))],
        "checkpoint.safetensors",
    );

    let json = dir.join("eval.json");
    let (out, _) = ok(&[
        "eval",
        "--ckpt",
        &s(&run_dir.join("weights.safetensors")),
        "--data",
        &s(&data),
        "--split",
        "test",
        "--json",
        &s(&json),
    ]);
    for row in [
        "fine (neural renderer)",
        "coarse (splatted RGB)",
        "copy the source image",
    ] {
        assert!(out.contains(row), "{out}");
    }
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(v["n_pairs"], 2, "one held-out identity of 3 frames");
    fails(
        &[
            "eval",
            "--ckpt",
            &s(&run_dir.join("weights.safetensors")),
            "--data",
            &s(&data),
            "--split",
            "nope",
        ],
        "--split must be",
    );

    let (out, _) = ok(&[
        "train-bench",
        "--preset",
        "tiny",
        "--runs",
        "1",
        "--threads",
        "2",
    ]);
    assert!(out.contains("train step, model `tiny` batch 1"), "{out}");
}
