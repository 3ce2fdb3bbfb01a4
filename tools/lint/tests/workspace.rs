//! The checks over the whole workspace, so `cargo test --workspace` enforces them.

use gagavatar_lint::{errcheck, modgraph, repo_root, rust_files, workspace_crates};

#[test]
fn every_crates_modules_form_a_dag() {
    let mut problems = Vec::new();
    let crates = workspace_crates(&repo_root());
    assert!(crates.len() >= 10, "found only {crates:?}");
    for (name, src) in crates {
        let g = modgraph::crate_graph(&src).unwrap();
        for c in g.cycles() {
            problems.push(format!("{name}: {}", c.join(" <-> ")));
        }
    }
    assert!(
        problems.is_empty(),
        "module cycles (run `cargo run -p gagavatar-lint -- graph`):\n{}",
        problems.join("\n")
    );
}

#[test]
fn no_error_prints_its_cause_twice() {
    let mut findings = Vec::new();
    for (_, src) in workspace_crates(&repo_root()) {
        for f in rust_files(&src) {
            let text = std::fs::read_to_string(&f).unwrap();
            findings.extend(errcheck::check_text(&f, &text));
        }
    }
    let lines: Vec<String> = findings.iter().map(|f| f.to_string()).collect();
    assert!(lines.is_empty(), "{}", lines.join("\n"));
}
