//! A `kill -9` in the middle of writing leaves no partial output: every command writes under a
//! hidden temporary name and renames into place only when complete, so after SIGKILL the output
//! path does not exist (only hidden temp siblings may remain, which the next run ignores).

mod common;

use common::{kill_mid_write, record, strs, Fixture};

#[test]
fn kill_9_during_reenact_leaves_no_video() {
    let f = Fixture::new("kill_reenact");
    // A driver long enough that the kill lands while frames are being encoded.
    let frames: Vec<_> = (0..200).map(|i| record(0.02 * i as f64)).collect();
    let driver = f.path("driver.json");
    std::fs::write(
        &driver,
        serde_json::json!({"fps": 25, "frames": frames}).to_string(),
    )
    .unwrap();
    for name in ["out.mp4", "out.gif", "frames"] {
        let out = f.path(name);
        let args = f.avatar_args(
            "reenact",
            &[],
            &[
                "--driver",
                &driver.display().to_string(),
                "-o",
                &out.display().to_string(),
            ],
        );
        // Some frames already written into the temporary file.
        let k = kill_mid_write(&args, &out, 4096);
        assert!(k.mid_write, "{name}: reenact finished before the kill");
        assert!(
            !out.exists(),
            "{name}: a partial output exists after kill -9"
        );
        assert!(!k.leftovers.is_empty(), "{name}: no temp file seen");
        for p in &k.leftovers {
            let file = p.file_name().unwrap().to_string_lossy().into_owned();
            assert!(file.starts_with('.'), "{name}: visible leftover {file}");
        }
        // The leftovers do not stop the next run from writing the output.
        if name == "out.mp4" {
            let a = f.avatar_args(
                "reenact",
                &[],
                &[
                    "--driver",
                    &driver.display().to_string(),
                    "--max-frames",
                    "2",
                    "-o",
                    &out.display().to_string(),
                ],
            );
            common::ok(&strs(&a));
            assert_eq!(gagavatar_video::mp4::read_mp4_info(&out).unwrap().frames, 2);
        }
    }
}

#[test]
fn kill_9_during_export_ply_leaves_no_ply() {
    let f = Fixture::new("kill_ply");
    let out = f.path("avatar.ply");
    let args = f.avatar_args("export-ply", &[], &["-o", &out.display().to_string()]);
    // The write (data, then fsync, then rename) is short: try until a kill lands inside it.
    // When the command wins the race its output must be complete.
    let mut caught = 0;
    for attempt in 0..12 {
        let _ = std::fs::remove_file(&out);
        let k = kill_mid_write(&args, &out, 1);
        if k.mid_write {
            caught += 1;
            assert!(
                !out.exists(),
                "attempt {attempt}: a partial .ply exists after kill -9"
            );
            for p in &k.leftovers {
                assert!(p
                    .file_name()
                    .unwrap()
                    .to_string_lossy()
                    .starts_with(".avatar.ply."));
                let _ = std::fs::remove_file(p);
            }
            if caught == 3 {
                break;
            }
        } else if out.exists() {
            let ply = gagavatar_formats::ply::read_ply(&out)
                .unwrap_or_else(|e| panic!("attempt {attempt}: {e}"));
            assert!(ply.rows > 1000 && ply.values.len() == ply.rows * ply.names.len());
        }
    }
    assert!(
        caught > 0,
        "no kill landed during the .ply write in 12 attempts"
    );
}
