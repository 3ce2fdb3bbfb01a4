//! The rough edges a new user hit, each with its fix checked through the command line:
//! photos named by the wrong extension, errors that printed their cause twice, record errors
//! that did not name the file, absurd but finite inputs that passed silently, and a FLAME
//! asset that does not fit the weights.

mod common;

use common::{fails, fails_log, ok, record, run, strs, Fixture};

/// "3 of 22 real photos are PNG data named `.jpg` and fail with `Illegal start bytes`".
#[test]
fn a_png_named_jpg_is_read_by_its_content() {
    let f = Fixture::new("png_as_jpg");
    std::fs::copy(f.path("src.png"), f.path("photo.jpg")).unwrap();
    let out = f.s("a.ply");
    let args = f.avatar_args(
        "export-ply",
        &[("--source", f.s("photo.jpg"))],
        &["-o", &out],
    );
    let res = ok(&strs(&args));
    let log = String::from_utf8_lossy(&res.stderr);
    assert!(!log.contains("Illegal start bytes"), "{log}");
    assert!(std::path::Path::new(&out).is_file());
}

/// Splits an error line into its `: `-separated parts and checks none is repeated (the cause
/// printed once by the message and again by the error chain).
fn assert_cause_once(line: &str) {
    let parts: Vec<&str> = line.split(": ").map(str::trim).collect();
    for (i, p) in parts.iter().enumerate() {
        if p.len() < 8 {
            continue;
        }
        assert!(
            !parts[i + 1..].contains(p),
            "`{p}` appears twice in the error:\n{line}"
        );
    }
}

/// "Errors print their cause twice".
#[test]
fn errors_print_their_cause_once() {
    let f = Fixture::new("cause_once");
    std::fs::write(
        f.path("garbage.png"),
        b"\x89PNG\r\n\x1a\nthis is not a PNG at all",
    )
    .unwrap();
    let out = f.s("x.ply");
    for (flag, value, needle) in [
        ("--source", f.s("missing.png"), "No such file or directory"),
        ("--source", f.s("garbage.png"), "PNG"),
        (
            "--ckpt",
            f.s("missing.safetensors"),
            "No such file or directory",
        ),
        (
            "--flame",
            f.s("missing_flame.pt"),
            "No such file or directory",
        ),
        (
            "--source-record",
            f.s("missing.json"),
            "No such file or directory",
        ),
    ] {
        let args = f.avatar_args("export-ply", &[(flag, value.clone())], &["-o", &out]);
        let line = fails(&strs(&args));
        assert!(line.contains(needle), "{flag}: {line}");
        assert!(
            line.contains(&value),
            "{flag}: the file is not named: {line}"
        );
        assert_eq!(line.matches(needle).count(), 1, "{flag}: {line}");
        assert_cause_once(&line);
    }
    // A training config that does not exist.
    let line = fails(&["train", "--config", &f.s("nope.toml"), "--out", &f.s("run")]);
    assert_eq!(
        line.matches("No such file or directory").count(),
        1,
        "{line}"
    );
}

/// "Record errors from `flame mesh` and `dump --target-record` do not name the file; a photo
/// given as `--source-record` says `unknown opcode 0xff`".
#[test]
fn record_errors_name_the_file_and_a_photo_is_not_a_record() {
    let f = Fixture::new("record_errors");
    let mut bad = record(0.0);
    bad["expcode"] = serde_json::json!("oops");
    std::fs::write(f.path("bad_params.json"), bad.to_string()).unwrap();

    let mesh_error = |params: &str| {
        fails(&[
            "flame",
            "mesh",
            "--flame",
            "synthetic",
            "--params",
            &f.s(params),
            "-o",
            &f.s("m.obj"),
        ])
    };
    let line = mesh_error("bad_params.json");
    assert!(
        line.contains("bad_params.json") && line.contains("expcode"),
        "{line}"
    );

    let args = f.avatar_args(
        "dump",
        &[],
        &[
            "--target-record",
            &f.s("bad_params.json"),
            "-o",
            &f.s("d.safetensors"),
        ],
    );
    let line = fails(&strs(&args));
    assert!(
        line.contains("bad_params.json") && line.contains("expcode"),
        "{line}"
    );

    // A photo where the tracking record goes, JPEG and PNG, whatever its name.
    let img = image::RgbImage::from_pixel(8, 8, image::Rgb([9, 9, 9]));
    img.save(f.path("photo.jpg")).unwrap();
    std::fs::copy(f.path("src.png"), f.path("photo_as.json")).unwrap();
    for (name, kind) in [("photo.jpg", "JPEG image"), ("photo_as.json", "PNG image")] {
        let args = f.avatar_args(
            "export-ply",
            &[("--source-record", f.s(name))],
            &["-o", &f.s("y.ply")],
        );
        let line = fails(&strs(&args));
        assert!(
            line.contains(name) && line.contains(kind) && line.contains("not a tracking record"),
            "{line}"
        );
        assert!(!line.contains("opcode"), "{line}");
    }
    // `flame mesh --params` given a photo says so too.
    let line = mesh_error("photo.jpg");
    assert!(
        line.contains("photo.jpg") && line.contains("JPEG image"),
        "{line}"
    );
}

/// "A shape code of 1e30 writes an all-black video with exit 0".
#[test]
fn absurd_codes_are_refused_with_the_record_and_key() {
    let f = Fixture::new("absurd");
    let mut frames: Vec<_> = (0..3).map(|i| record(0.1 * i as f64)).collect();
    frames[1]["shapecode"] = serde_json::json!([1e30]);
    std::fs::write(
        f.path("driver.json"),
        serde_json::json!({"fps": 25, "frames": frames}).to_string(),
    )
    .unwrap();
    let out = f.path("out.mp4");
    let args = f.avatar_args(
        "reenact",
        &[],
        &[
            "--driver",
            &f.s("driver.json"),
            "-o",
            &out.display().to_string(),
        ],
    );
    let line = fails(&strs(&args));
    assert!(
        line.contains("driver.json") && line.contains("#1") && line.contains("shapecode"),
        "{line}"
    );
    assert!(!out.exists());

    let mut src = record(0.0);
    src["expcode"] = serde_json::json!([0.5, -2e4]);
    std::fs::write(f.path("huge_src.json"), src.to_string()).unwrap();
    let args = f.avatar_args(
        "export-ply",
        &[("--source-record", f.s("huge_src.json"))],
        &["-o", &f.s("z.ply")],
    );
    let line = fails(&strs(&args));
    assert!(
        line.contains("huge_src.json") && line.contains("expcode") && line.contains("element 1"),
        "{line}"
    );
}

/// "A FLAME asset that does not match the weights runs without a warning".
#[test]
fn a_flame_asset_that_does_not_fit_the_weights_is_reported() {
    let f = Fixture::new("flame_mismatch");
    ok(&[
        "flame",
        "synth",
        "--seed",
        "7",
        "-o",
        &f.s("other_flame.safetensors"),
    ]);
    let args = f.avatar_args(
        "export-ply",
        &[("--flame", f.s("other_flame.safetensors"))],
        &["-o", &f.s("a.ply")],
    );
    let res = ok(&strs(&args));
    let log = String::from_utf8_lossy(&res.stderr);
    assert!(
        log.contains("warning:")
            && log.contains("other_flame.safetensors")
            && log.contains("synthetic"),
        "{log}"
    );
    // The asset the tiny weights go with: no warning.
    let args = f.avatar_args("export-ply", &[], &["-o", &f.s("b.ply")]);
    let res = ok(&strs(&args));
    let log = String::from_utf8_lossy(&res.stderr);
    assert!(!log.contains("warning:"), "{log}");
}

/// "An empty training config silently trains the release-size model".
#[test]
fn an_empty_training_config_names_the_missing_keys() {
    let f = Fixture::new("empty_config");
    std::fs::write(f.path("empty.toml"), "").unwrap();
    std::fs::write(f.path("partial.toml"), "[optim]\nlr = 1e-3\n").unwrap();
    for name in ["empty.toml", "partial.toml"] {
        let log = fails_log(&[
            "train",
            "--config",
            &f.s(name),
            "--data",
            &f.s("no_data"),
            "--out",
            &f.s("run"),
        ]);
        assert!(
            log.contains(name) && log.contains("[model] preset") && log.contains("[train] steps"),
            "{log}"
        );
        // Refused before anything is built: a run reads its data before it builds the model
        // (`Run::create`), and the data folder here does not exist, so an error that names the
        // config's keys rather than the data came before both; and nothing else was reported.
        assert_eq!(log.lines().count(), 1, "{log}");
        assert!(!log.contains("no_data"), "{log}");
        assert!(!f.path("run").exists());
    }
    // `--steps` stands in for the file's `[train] steps`; the model size still must be named.
    let line = fails(&[
        "train",
        "--config",
        &f.s("partial.toml"),
        "--steps",
        "2",
        "--data",
        &f.s("no_data"),
        "--out",
        &f.s("run"),
    ]);
    assert!(
        line.contains("[model] preset") && !line.contains("[train] steps"),
        "{line}"
    );
    let out = run(&["train", "--help"]);
    assert!(out.status.success());
}

/// `--precision bf16` on a CPU without AVX512-BF16 (simulated by `GAGAVATAR_NO_BF16`): one
/// line that names what is missing and the way out, before any weights load; where the CPU has
/// them, the same command writes its output.
#[test]
fn bf16_without_the_instructions_is_one_line() {
    let f = Fixture::new("bf16_line");
    let out = f.s("a.ply");
    let args = f.avatar_args("export-ply", &[], &["--precision", "bf16", "-o", &out]);
    let res = std::process::Command::new(env!("CARGO_BIN_EXE_gagavatar"))
        .args(&args)
        .env("GAGAVATAR_NO_BF16", "1")
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&res.stderr);
    assert!(!res.status.success(), "{log}");
    let lines: Vec<&str> = log.lines().collect();
    assert_eq!(lines.len(), 1, "{log}");
    assert!(
        lines[0].starts_with("error: ")
            && lines[0].contains("AVX512-BF16")
            && lines[0].contains("f32"),
        "{log}"
    );
    assert!(!std::path::Path::new(&out).exists());
    let bad = run(&strs(&f.avatar_args(
        "export-ply",
        &[],
        &["--precision", "fp8", "-o", &out],
    )));
    let log = String::from_utf8_lossy(&bad.stderr);
    assert!(
        !bad.status.success() && log.contains("`fp8` (f32 or bf16)"),
        "{log}"
    );
    if gagavatar_testkit::bf16_or_skip("bf16_without_the_instructions_is_one_line") {
        ok(&strs(&f.avatar_args(
            "export-ply",
            &[],
            &["--precision", "bf16", "-o", &out],
        )));
        assert!(std::path::Path::new(&out).is_file());
    }
}
