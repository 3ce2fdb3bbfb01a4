//! Source checks the compiler does not make, run over the workspace by the tests of this crate
//! (so `cargo test --workspace` enforces them) and printable with the `gagavatar-lint` binary:
//!
//! - [`modgraph`]: each crate's modules import each other without cycles, so the layers inside a
//!   crate read bottom-up like the crates do;
//! - [`errcheck`]: no error type prints its cause twice.

pub mod errcheck;
pub mod modgraph;
pub mod source;

use std::path::{Path, PathBuf};

/// The crates of the workspace under `root`: `(name, src dir)` for `crates/*`, `apps/*`,
/// `tools/*` and `fuzz`, sorted.
pub fn workspace_crates(root: &Path) -> Vec<(String, PathBuf)> {
    let mut out = Vec::new();
    for group in ["crates", "apps", "tools"] {
        let Ok(rd) = std::fs::read_dir(root.join(group)) else {
            continue;
        };
        for e in rd.flatten() {
            let src = e.path().join("src");
            if src.is_dir() {
                out.push((format!("{group}/{}", e.file_name().to_string_lossy()), src));
            }
        }
    }
    if root.join("fuzz/src").is_dir() {
        out.push(("fuzz".into(), root.join("fuzz/src")));
    }
    out.sort();
    out
}

/// Every `.rs` file under `dir`, sorted.
pub fn rust_files(dir: &Path) -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        let Ok(rd) = std::fs::read_dir(dir) else {
            return;
        };
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(&p, out);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, &mut out);
    out.sort();
    out
}

/// The repository root (two levels above this crate).
pub fn repo_root() -> PathBuf {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    p.canonicalize().unwrap_or(p)
}
