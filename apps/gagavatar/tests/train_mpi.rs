//! Data-parallel training through MPI (built with `--features mpi`, run under `mpirun`):
//! two ranks at one pair each follow one process at batch 2, rank 0 alone writes the run,
//! and a run resumes with another rank count. Skipped with a printed reason when `mpirun` is
//! missing, unless GAGAVATAR_REQUIRE_MPI is set (CI sets it).
#![cfg(feature = "mpi")]

mod common;

use common::{strs, BIN};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The first steps' losses and gradient norms: the same sums in another order (each rank's
/// gradient of its own pair, then MPI's sum), so f32 rounding apart.
const STEP_RTOL: f64 = 1e-5;
/// Weights after `STEPS` steps. Adam (betas (0, 0.99)) divides each gradient by its running
/// RMS, so a parameter whose gradient is rounding noise moves by up to the learning rate
/// either way on each step: the bound is 2 x lr x steps (lr 1.5e-4 at most in the tiny
/// preset); the median must stay at rounding level.
const STEPS: u64 = 20;
const WEIGHT_TOL: f64 = 2.0 * 1.5e-4 * STEPS as f64;
const WEIGHT_MEDIAN_TOL: f64 = 1e-4;

fn mpirun() -> Option<&'static str> {
    let found = Command::new("mpirun").arg("--version").output().is_ok();
    if !found {
        assert!(
            std::env::var_os("GAGAVATAR_REQUIRE_MPI").is_none(),
            "GAGAVATAR_REQUIRE_MPI is set but mpirun is missing"
        );
        eprintln!("skipping: no mpirun (Debian: openmpi-bin)");
        return None;
    }
    Some("mpirun")
}

fn check(o: Output, what: &str) -> String {
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(
        o.status.success(),
        "{what} failed:\n{}\n{err}",
        String::from_utf8_lossy(&o.stdout)
    );
    err
}

/// `mpirun [-q] -n RANKS gagavatar train`, allowed to run as root and to oversubscribe.
fn mpirun_train(ranks: usize, quiet: bool) -> Command {
    let mut c = Command::new("mpirun");
    if quiet {
        c.arg("-q");
    }
    c.args(["--oversubscribe", "-n", &ranks.to_string(), BIN, "train"])
        // OpenMPI refuses root (CI containers) unless told.
        .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        .env("OMPI_MCA_rmaps_base_oversubscribe", "1");
    c
}

fn train(ranks: usize, args: &[&str]) -> String {
    let mut c = if ranks == 1 {
        let mut c = Command::new(BIN);
        c.arg("train");
        c
    } else {
        mpirun_train(ranks, false)
    };
    let o = c.args(args).args(["--threads", "1"]).output().unwrap();
    check(o, &format!("{ranks} rank(s): train {args:?}"))
}

/// A fresh folder `name` under the test's scratch space with a small synthetic dataset in
/// `data/` (3 identities of 3 frames at 64x64, one held out); returns both paths.
fn fresh_dataset(name: &str) -> (PathBuf, PathBuf) {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let data = dir.join("data");
    check(
        Command::new(BIN)
            .arg("synth-data")
            .arg("-o")
            .arg(&data)
            .args(["--identities", "3", "--frames", "3"])
            .args(["--size", "64", "--holdout", "1"])
            .output()
            .unwrap(),
        "synth-data",
    );
    (dir, data)
}

fn metrics(run: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(run.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

fn weights(run: &Path) -> Vec<(String, Vec<f32>)> {
    let mut w: Vec<(String, Vec<f32>)> =
        gagavatar_net::checkpoint::read_weights(&run.join("weights.safetensors"))
            .unwrap()
            .tensors
            .into_iter()
            .map(|(k, t)| (k, t.flatten_all().unwrap().to_vec1::<f32>().unwrap()))
            .collect();
    w.sort_by(|a, b| a.0.cmp(&b.0));
    w
}

fn compare(what: &str, a: &Path, b: &Path) {
    let (ma, mb) = (metrics(a), metrics(b));
    for (x, y) in ma.iter().zip(&mb).take(3) {
        for key in ["loss", "grad_norm", "img", "box"] {
            let (u, v) = (x[key].as_f64().unwrap(), y[key].as_f64().unwrap());
            let rel = (u - v).abs() / u.abs().max(1e-12);
            assert!(
                rel <= STEP_RTOL,
                "{what}: step {}: {key} {u} vs {v} (relative {rel:e} > {STEP_RTOL:e})",
                x["step"]
            );
        }
    }
    let mut diffs: Vec<f64> = Vec::new();
    let mut worst = (0f64, String::new(), 0usize);
    for ((ka, va), (kb, vb)) in weights(a).iter().zip(&weights(b)) {
        assert_eq!(ka, kb, "{what}: keys differ");
        for (i, (x, y)) in va.iter().zip(vb).enumerate() {
            let d = (x - y).abs() as f64;
            if d > worst.0 {
                worst = (d, ka.clone(), i);
            }
            diffs.push(d);
        }
    }
    diffs.sort_by(f64::total_cmp);
    let median = diffs[diffs.len() / 2];
    eprintln!(
        "{what}: weights after {STEPS} steps: max abs {:e} ({}[{}]), median {median:e}",
        worst.0, worst.1, worst.2
    );
    assert!(
        worst.0 <= WEIGHT_TOL,
        "{what}: {}[{}] differs by {:e} > {WEIGHT_TOL:e}",
        worst.1,
        worst.2,
        worst.0
    );
    assert!(
        median <= WEIGHT_MEDIAN_TOL,
        "{what}: median difference {median:e}"
    );
}

#[test]
fn two_ranks_follow_one_process_and_resume_with_another_count() {
    if mpirun().is_none() {
        return;
    }
    let (dir, data) = fresh_dataset("train_mpi");
    let s = |p: &Path| p.display().to_string();
    let steps = STEPS.to_string();
    let common = |out: &Path, steps: &str| -> Vec<String> {
        [
            "--preset",
            "tiny",
            "--data",
            &s(&data),
            "--steps",
            steps,
            "--seed",
            "1",
            "--batch",
            "2",
            "--val-every",
            "0",
            "--out",
            &s(out),
        ]
        .map(String::from)
        .to_vec()
    };
    let run = |ranks: usize, v: Vec<String>| train(ranks, &strs(&v));

    let one = dir.join("one");
    run(1, common(&one, &steps));
    let two = dir.join("two");
    let err = run(2, common(&two, &steps));
    assert!(err.contains("data-parallel: 2 ranks"), "{err}");
    // Rank 0 alone reports and writes: one header, one metrics line per logged step.
    assert_eq!(err.matches("model `tiny`").count(), 1, "{err}");
    let logged: Vec<u64> = metrics(&two)
        .iter()
        .map(|m| m["step"].as_u64().unwrap())
        .collect();
    let mut unique = logged.clone();
    unique.dedup();
    assert_eq!(logged, unique, "metrics lines repeated");
    assert_eq!(logged.last(), Some(&STEPS));
    compare("2 ranks vs 1 process at batch 2", &one, &two);

    // Half the steps on two ranks, resumed for the rest on one, against the same split run
    // on one process (a run started for 10 steps decays its learning rate over 10).
    let half = |name: &str, first: usize| {
        let d = dir.join(name);
        run(first, common(&d, &(STEPS / 2).to_string()));
        train(1, &["--resume", &s(&d), "--steps", &steps]);
        d
    };
    let (a, b) = (half("half_one", 1), half("half_two", 2));
    compare("10 steps on 2 ranks + 10 resumed on 1, vs all on 1", &a, &b);

    // A batch that does not split over the ranks is refused by every rank, before writing.
    let bad = dir.join("bad");
    let mut v = common(&bad, "2");
    let i = v.iter().position(|a| a == "--batch").unwrap();
    v[i + 1] = "3".into();
    let o = mpirun_train(2, false).args(strs(&v)).output().unwrap();
    assert!(!o.status.success(), "batch 3 over 2 ranks succeeded");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("does not split into 2 equal shares"), "{err}");
    assert!(!bad.join("checkpoint.safetensors").exists());
}

/// `train --device gpu` (the rendering half on Mesa's CPU Vulkan here) against the CPU: the
/// first step's loss terms and gradient norm (the GPU's sums in another order; measured
/// within 1e-6), then later steps'. Adam with beta1 = 0 moves every parameter by about the
/// learning rate on its first step whatever its gradient's size, so rounding differences grow
/// step by step (two CPU runs on 1 and 2 threads differ by 1e-3 in the gradient norm at step
/// 5, the GPU run by 4e-3).
const GPU_FIRST_RTOL: f64 = 1e-4;
const GPU_LATER_RTOL: f64 = 2e-2;

fn compare_steps(what: &str, a: &Path, b: &Path, steps: usize) {
    let (ma, mb) = (metrics(a), metrics(b));
    assert!(
        ma.len() >= steps && mb.len() >= steps,
        "{what}: too few steps logged"
    );
    for (i, (x, y)) in ma.iter().zip(&mb).take(steps).enumerate() {
        assert_eq!(x["step"], y["step"], "{what}: steps differ");
        let tol = if i == 0 {
            GPU_FIRST_RTOL
        } else {
            GPU_LATER_RTOL
        };
        for key in ["loss", "grad_norm", "img", "box", "percep", "point"] {
            let (Some(u), Some(v)) = (x[key].as_f64(), y[key].as_f64()) else {
                assert_eq!(x[key], y[key], "{what}: step {}: {key}", x["step"]);
                continue;
            };
            let rel = (u - v).abs() / u.abs().max(1e-12);
            eprintln!(
                "{what}: step {}: {key} {u} vs {v} (relative {rel:e})",
                x["step"]
            );
            assert!(
                rel <= tol,
                "{what}: step {}: {key} {u} vs {v} (relative {rel:e} > {tol:e})",
                x["step"]
            );
        }
    }
}

/// Two ranks, each with the rendering half on its GPU, follow one CPU process at batch 2; the
/// run then resumes on the CPU (a GPU checkpoint is an ordinary one).
#[test]
fn two_gpu_ranks_follow_one_cpu_process_and_resume_on_the_cpu() {
    if mpirun().is_none() {
        return;
    }
    let (dir, data) = fresh_dataset("train_mpi_gpu");
    let s = |p: &Path| p.display().to_string();
    let args = |out: &Path, device: &str| -> Vec<String> {
        [
            "--preset",
            "tiny",
            "--data",
            &s(&data),
            "--steps",
            "2",
            "--seed",
            "4",
            "--batch",
            "2",
            "--val-every",
            "0",
            "--device",
            device,
            "--out",
            &s(out),
        ]
        .map(String::from)
        .to_vec()
    };
    let cpu = dir.join("cpu");
    train(1, &strs(&args(&cpu, "cpu")));
    let gpu = dir.join("gpu");
    let err = train(2, &strs(&args(&gpu, "gpu")));
    assert!(
        err.contains("training's splatting, renderer and lifting generators on"),
        "{err}"
    );
    compare_steps("2 GPU ranks vs 1 CPU process", &cpu, &gpu, 2);
    for d in [&cpu, &gpu] {
        train(1, &["--resume", &s(d), "--steps", "3", "--device", "cpu"]);
    }
    compare_steps("then resumed on the CPU", &cpu, &gpu, 3);
}

/// The process of rank `rank` that the launcher `launcher` started (`/proc`: its parent and
/// OpenMPI's rank variable).
fn rank_pid(launcher: u32, rank: usize) -> Option<u32> {
    let want = format!("OMPI_COMM_WORLD_RANK={rank}");
    for entry in std::fs::read_dir("/proc").ok()?.flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            continue;
        };
        // The parent is the second field after the parenthesised command name.
        let parent = stat
            .rsplit_once(')')
            .and_then(|(_, rest)| rest.split_whitespace().nth(1))
            .and_then(|p| p.parse::<u32>().ok());
        if parent != Some(launcher) {
            continue;
        }
        let Ok(env) = std::fs::read(format!("/proc/{pid}/environ")) else {
            continue;
        };
        if env.split(|&b| b == 0).any(|v| v == want.as_bytes()) {
            return Some(pid);
        }
    }
    None
}

fn wait_until(what: &str, seconds: u64, mut ready: impl FnMut() -> bool) {
    let end = std::time::Instant::now() + std::time::Duration::from_secs(seconds);
    while !ready() {
        assert!(
            std::time::Instant::now() < end,
            "{what}: not within {seconds} s"
        );
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
}

/// `kill -9` of one rank mid-run: the job ends, failing, with our one line (and, under
/// `mpirun -q`, nothing of the launcher's), the last checkpoint is whole, and the run resumes
/// from it on one process.
#[test]
fn a_killed_rank_ends_the_job_in_one_line_and_the_run_resumes() {
    if mpirun().is_none() {
        return;
    }
    let (dir, data) = fresh_dataset("train_mpi_kill");
    let s = |p: &Path| p.display().to_string();
    // The tiny preset, checkpointing every 5 steps, long enough to be killed mid-run.
    let preset = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../crates/train/configs/tiny.toml"
    ))
    .unwrap();
    let config = dir.join("config.toml");
    let edited = preset
        .replace("checkpoint_every = 500", "checkpoint_every = 5")
        .replace("steps = 2000", "steps = 5000");
    assert_ne!(edited, preset, "the tiny preset's keys moved");
    std::fs::write(&config, edited).unwrap();
    let run = dir.join("run");
    let log = dir.join("stderr.txt");
    let mut job = mpirun_train(2, true)
        .args(["--config", &s(&config), "--data", &s(&data), "--batch", "2"])
        .args(["--val-every", "0", "--out", &s(&run), "--threads", "1"])
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let logged = || {
        std::fs::read_to_string(run.join("metrics.jsonl"))
            .map(|m| m.lines().count())
            .unwrap_or(0)
    };
    wait_until("12 logged steps", 300, || logged() >= 12);
    let victim = rank_pid(job.id(), 1).expect("rank 1's process");
    let killed = Command::new("kill")
        .args(["-9", &victim.to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let mut status = None;
    wait_until("the job's end after kill -9", 60, || {
        status = job.try_wait().unwrap();
        status.is_some()
    });
    assert!(!status.unwrap().success(), "the job succeeded");
    let err = std::fs::read_to_string(&log).unwrap();
    let ours: Vec<&str> = err
        .lines()
        .filter(|l| l.contains("mpirun ended this job (a rank died"))
        .collect();
    assert_eq!(ours.len(), 1, "{err}");
    assert!(ours[0].contains("gagavatar train --resume"), "{err}");
    assert!(
        !err.contains("----"),
        "the launcher's banner under -q:\n{err}"
    );

    // The checkpoint left behind resumes; the run then reaches its new total.
    let last = metrics(&run).last().unwrap()["step"].as_u64().unwrap();
    let total = (last + 3).to_string();
    let out = train(1, &["--resume", &s(&run), "--steps", &total]);
    assert!(out.contains("trained steps"), "{out}");
    let end = metrics(&run).last().unwrap()["step"].as_u64().unwrap();
    assert_eq!(end, last + 3);
}
