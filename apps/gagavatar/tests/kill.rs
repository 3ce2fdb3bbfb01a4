//! A `kill -9` in the middle of writing leaves no partial output: every command writes under a
//! hidden temporary name and renames into place only when complete, so after SIGKILL the output
//! path does not exist (only hidden temp siblings may remain, which the next run ignores).

mod common;

use common::{kill_mid_write, record, strs, Fixture};

#[test]
fn kill_9_during_reenact_leaves_no_video() {
    let f = Fixture::new("kill_reenact");
    // Several frames; the child pauses before its rename, so the kill lands inside the write
    // however fast the frames come.
    let frames: Vec<_> = (0..12).map(|i| record(0.1 * i as f64)).collect();
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
        // The finished temporary waits before its rename (a 12-frame 64x64 mp4 is ~3 KB).
        let k = kill_mid_write(&args, &out, 1);
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
    // The whole .ply in its temporary, held before the rename: the kill lands there.
    let k = kill_mid_write(&args, &out, 1);
    assert!(k.mid_write, "export-ply finished before the kill");
    assert!(!out.exists(), "a partial .ply exists after kill -9");
    assert!(!k.leftovers.is_empty(), "no temp file seen");
    for p in &k.leftovers {
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        assert!(name.starts_with(".avatar.ply."), "visible leftover {name}");
    }
    // The leftover does not stop the next run, whose output is complete.
    common::ok(&strs(&args));
    let ply = gagavatar_formats::ply::read_ply(&out).unwrap();
    assert!(ply.rows > 1000 && ply.values.len() == ply.rows * ply.names.len());
}
