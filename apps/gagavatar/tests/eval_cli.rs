//! End to end: the paper's protocol (`eval --mode both`) on a small synthetic test split with
//! a seeded tiny model: pairs, CSV, summary, resume, the ground-truth sanity run, bad inputs.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_gagavatar"))
        .args(args)
        .output()
        .expect("gagavatar runs")
}

fn ok(args: &[&str]) -> (String, String) {
    let o = run(args);
    let (out, err) = (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    );
    assert!(o.status.success(), "{args:?} failed:\n{out}\n{err}");
    (out, err)
}

fn fails(args: &[&str], needle: &str) {
    let o = run(args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{args:?} should fail");
    assert!(err.contains(needle), "{args:?}: `{needle}` not in {err}");
}

fn csv_rows(path: &Path) -> Vec<Vec<String>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(str::to_string).collect())
        .collect()
}

#[test]
fn paper_protocol_on_a_synthetic_split() {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("cli_eval");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let s = |p: &Path| p.display().to_string();
    let data = dir.join("data");
    let ckpt = dir.join("tiny.safetensors");
    ok(&[
        "synth-data",
        "-o",
        &s(&data),
        "--identities",
        "5",
        "--frames",
        "3",
        "--size",
        "64",
        "--holdout",
        "4",
    ]);
    ok(&[
        "init-weights",
        "--preset",
        "tiny",
        "--seed",
        "3",
        "-o",
        &s(&ckpt),
    ]);

    let out = dir.join("eval");
    let args = [
        "eval",
        "--ckpt",
        &s(&ckpt),
        "--data",
        &s(&data),
        "--mode",
        "both",
        "-o",
        &s(&out),
        "--pairs",
        "3",
        "--seed",
        "5",
        "--threads",
        "2",
        "--batch",
        "2",
    ];
    let (table, err) = ok(&args);
    assert!(table.contains("self reenactment: 3 pairs"), "{table}");
    assert!(table.contains("cross reenactment: 3 pairs"), "{table}");
    for col in ["PSNR", "SSIM", "LPIPS", "CSIM", "AED", "APD", "AKD"] {
        assert!(table.contains(col), "{col} missing from\n{table}");
    }
    assert!(err.contains("6 pairs scored now (0 kept"), "{err}");
    let rows = csv_rows(&out.join("scores.csv"));
    assert_eq!(rows.len(), 6);
    let (selfs, cross): (Vec<_>, Vec<_>) = rows.iter().partition(|r| r[0] == "self");
    assert_eq!((selfs.len(), cross.len()), (3, 3));
    for r in &selfs {
        // PSNR and SSIM exist for every self pair, and a random model is no copy of the truth.
        let psnr: f64 = r[3].parse().unwrap();
        let ssim: f64 = r[4].parse().unwrap();
        assert!(psnr.is_finite() && psnr > 0.0 && psnr < 60.0, "{r:?}");
        assert!(ssim > -1.0 && ssim < 1.0, "{r:?}");
        assert!(r[5].is_empty(), "no LPIPS weights given: {r:?}");
    }
    for r in &cross {
        assert!(
            r[3].is_empty() && r[9].is_empty(),
            "cross pairs have no ground truth: {r:?}"
        );
        let video = |n: &str| n.rsplit_once('_').unwrap().0.to_string();
        assert_ne!(video(&r[1]), video(&r[2]), "{r:?}");
    }
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["modes"]["self"]["pairs"], 3);
    assert_eq!(
        summary["modes"]["cross"]["columns"],
        serde_json::json!(["csim", "aed", "apd"])
    );
    let pairs: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("pairs.json")).unwrap()).unwrap();
    assert_eq!(pairs["seed"], 5);
    assert_eq!(pairs["pairs"].as_array().unwrap().len(), 6);

    // A rerun keeps every finished pair and scores nothing.
    let before = std::fs::read_to_string(out.join("scores.csv")).unwrap();
    let (_, err) = ok(&args);
    assert!(err.contains("0 pairs scored now (6 kept"), "{err}");
    assert_eq!(
        std::fs::read_to_string(out.join("scores.csv")).unwrap(),
        before
    );
    // Other settings into the same folder are refused rather than mixed.
    let mut other = args.to_vec();
    let seed_at = other.len() - 5;
    other[seed_at] = "6";
    fails(&other, "use another -o");

    // The sanity run: the ground truth scored as the result.
    let gt = dir.join("gt");
    let (table, _) = ok(&[
        "eval",
        "--ground-truth-as-result",
        "--data",
        &s(&data),
        "--mode",
        "self",
        "-o",
        &s(&gt),
        "--threads",
        "2",
    ]);
    assert!(table.contains("self reenactment: 4 pairs"), "{table}");
    for r in csv_rows(&gt.join("scores.csv")) {
        assert_eq!(r[3], "inf", "PSNR of identical images: {r:?}");
        assert_eq!(r[4].parse::<f64>().unwrap(), 1.0, "{r:?}");
        if !r[9].is_empty() {
            assert_eq!(
                r[9].parse::<f64>().unwrap(),
                0.0,
                "AKD of identical images: {r:?}"
            );
        }
    }

    // The copy-the-source baseline: the source photo as every result.
    let src = dir.join("src");
    ok(&[
        "eval",
        "--source-as-result",
        "--data",
        &s(&data),
        "--mode",
        "self",
        "-o",
        &s(&src),
        "--threads",
        "2",
    ]);
    for r in csv_rows(&src.join("scores.csv")) {
        let psnr: f64 = r[3].parse().unwrap();
        assert!(
            psnr.is_finite(),
            "another frame is no copy of the target: {r:?}"
        );
    }

    // CSIM through a user's ArcFace ONNX model (the tiny golden network stands in for one).
    let onnx = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../crates/metrics/tests/golden/arcface_tiny.onnx");
    let arc = dir.join("arcface");
    ok(&[
        "eval",
        "--ground-truth-as-result",
        "--data",
        &s(&data),
        "--mode",
        "self",
        "-o",
        &s(&arc),
        "--arcface",
        &s(&onnx),
        "--threads",
        "2",
    ]);
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(arc.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["meta"]["identity"], "ArcFace (user ONNX model)");

    fails(
        &[
            "eval",
            "--ckpt",
            &s(&ckpt),
            "--data",
            &s(&data),
            "--mode",
            "sideways",
            "-o",
            &s(&out),
        ],
        "--mode must be",
    );
    fails(
        &[
            "eval",
            "--ckpt",
            &s(&ckpt),
            "--data",
            &s(&data),
            "--mode",
            "self",
        ],
        "-o OUT",
    );
    fails(
        &[
            "eval",
            "--data",
            &s(&data),
            "--mode",
            "self",
            "-o",
            &s(&dir.join("x")),
        ],
        "--ckpt is required",
    );
}
