//! `gagavatar-lint graph`: print every crate's module import graph, exit 1 on a cycle.
//! `gagavatar-lint errors`: list error variants that print their cause twice, exit 1 if any.
//! With no argument, both. A second argument names another checkout's root to check.

use gagavatar_lint::{errcheck, modgraph, repo_root, rust_files, workspace_crates};

fn main() {
    let what = std::env::args().nth(1).unwrap_or_default();
    let root = std::env::args()
        .nth(2)
        .map(std::path::PathBuf::from)
        .unwrap_or_else(repo_root);
    let mut failed = false;
    if what.is_empty() || what == "graph" {
        for (name, src) in workspace_crates(&root) {
            let g = match modgraph::crate_graph(&src) {
                Ok(g) => g,
                Err(e) => {
                    eprintln!("{name}: {e}");
                    failed = true;
                    continue;
                }
            };
            println!("{name}:");
            print!("{}", g.render());
            for c in g.cycles() {
                println!("  CYCLE: {}", c.join(" <-> "));
                failed = true;
            }
        }
    }
    if what.is_empty() || what == "errors" {
        let mut n = 0;
        for (_, src) in workspace_crates(&root) {
            for f in rust_files(&src) {
                let Ok(text) = std::fs::read_to_string(&f) else {
                    continue;
                };
                let rel = f.strip_prefix(&root).unwrap_or(&f);
                for finding in errcheck::check_text(rel, &text) {
                    println!("{finding}");
                    n += 1;
                }
            }
        }
        if n > 0 {
            failed = true;
        } else {
            println!("errors: no variant prints its cause twice");
        }
    }
    if !matches!(what.as_str(), "" | "graph" | "errors") {
        eprintln!("usage: gagavatar-lint [graph|errors] [REPO_ROOT]");
        std::process::exit(2);
    }
    std::process::exit(i32::from(failed));
}
