//! The module import graph of a crate: module `a` depends on module `b` when code in `a` (tests
//! excluded) names something in `b`, directly (`crate::b::X`, `super::b`, `b::X` from `b`'s
//! parent) or through a re-export (`crate::X` where the crate root or a module re-exports `b`'s
//! `X`). The crate root (`lib.rs` / `main.rs`) is the entry point and is left out: it declares
//! and re-exports everything.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use crate::source::{tokenize, without_test_items, Tok};

/// A crate's modules and their dependencies, by module path (`pickle::read`).
#[derive(Debug, Default)]
pub struct ModuleGraph {
    pub edges: BTreeMap<String, BTreeSet<String>>,
}

/// One parsed module file.
struct Module {
    path: String,
    toks: Vec<Tok>,
}

fn module_path(src: &Path, file: &Path) -> Option<String> {
    let rel = file.strip_prefix(src).ok()?;
    let mut parts: Vec<String> = rel
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    let last = parts.pop()?;
    let stem = last.strip_suffix(".rs")?;
    match stem {
        "lib" | "main" if parts.is_empty() => {}
        "mod" => {}
        s => parts.push(s.to_string()),
    }
    Some(parts.join("::"))
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return;
    };
    let mut entries: Vec<PathBuf> = rd.filter_map(|e| e.ok().map(|e| e.path())).collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|e| e == "rs") {
            out.push(p);
        }
    }
}

/// Builds the graph of the crate whose sources are under `src` (its `src/` folder).
pub fn crate_graph(src: &Path) -> std::io::Result<ModuleGraph> {
    let mut files = Vec::new();
    rust_files(src, &mut files);
    let mut modules = Vec::new();
    let mut test_files: BTreeSet<String> = BTreeSet::new();
    for f in &files {
        let Some(path) = module_path(src, f) else {
            continue;
        };
        let text = std::fs::read_to_string(f)?;
        let (toks, test_mods) = without_test_items(&tokenize(&text));
        for m in test_mods {
            test_files.insert(join(&path, &m));
        }
        modules.push(Module { path, toks });
    }
    modules.retain(|m| !test_files.contains(&m.path));
    Ok(graph_of(&modules))
}

fn join(parent: &str, child: &str) -> String {
    if parent.is_empty() {
        child.to_string()
    } else {
        format!("{parent}::{child}")
    }
}

fn parent_of(path: &str) -> &str {
    path.rfind("::").map_or("", |i| &path[..i])
}

/// Paths named in `toks` (absolute, `crate::`-relative, without `crate`), with `super::` /
/// `self::` and child-relative paths resolved against module `here`.
fn named_paths(toks: &[Tok], here: &str, known: &BTreeSet<String>) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < toks.len() {
        let after_sep = i > 0 && toks[i - 1] == Tok::PathSep;
        if let Tok::Ident(first) = &toks[i] {
            if !after_sep && toks.get(i + 1) == Some(&Tok::PathSep) {
                // (base module, index where the rest of the path starts)
                let start: Option<(Vec<String>, usize)> = match first.as_str() {
                    "crate" => Some((Vec::new(), i + 2)),
                    "super" => {
                        // A chain of `super::super::...`.
                        let mut base = parent_of(here).to_string();
                        let mut j = i + 2;
                        while toks.get(j) == Some(&Tok::Ident("super".into()))
                            && toks.get(j + 1) == Some(&Tok::PathSep)
                        {
                            base = parent_of(&base).to_string();
                            j += 2;
                        }
                        Some((split(&base), j))
                    }
                    "self" => Some((split(here), i + 2)),
                    // A child module named without `self::`.
                    name if known.contains(&join(here, name)) => Some((split(here), i)),
                    _ => None,
                };
                if let Some((base, at)) = start {
                    let mut trees = Vec::new();
                    i = use_tree(toks, at, base, &mut trees);
                    out.extend(trees);
                    continue;
                }
            }
        }
        i += 1;
    }
    out
}

fn split(path: &str) -> Vec<String> {
    if path.is_empty() {
        Vec::new()
    } else {
        path.split("::").map(str::to_string).collect()
    }
}

/// Reads `a::b::{c, d::e}` from `i` (just after `prefix::`), pushing every complete path.
fn use_tree(
    toks: &[Tok],
    mut i: usize,
    mut prefix: Vec<String>,
    out: &mut Vec<Vec<String>>,
) -> usize {
    loop {
        match toks.get(i) {
            Some(Tok::Ident(s)) => {
                prefix.push(s.clone());
                if toks.get(i + 1) == Some(&Tok::PathSep) {
                    i += 2;
                    continue;
                }
                out.push(prefix);
                return i + 1;
            }
            Some(Tok::Punct('{')) => {
                i += 1;
                loop {
                    match toks.get(i) {
                        Some(Tok::Punct('}')) => return i + 1,
                        Some(Tok::Punct(',')) => i += 1,
                        Some(Tok::Ident(s)) if s == "as" => i += 2,
                        Some(_) => {
                            let next = use_tree(toks, i, prefix.clone(), out);
                            i = next.max(i + 1);
                        }
                        None => return i,
                    }
                }
            }
            Some(Tok::Punct('*')) => {
                out.push(prefix);
                return i + 1;
            }
            _ => {
                out.push(prefix);
                return i;
            }
        }
    }
}

/// `pub use` items of a module: exported name -> full path of what it names.
fn reexports(m: &Module, known: &BTreeSet<String>) -> BTreeMap<String, Vec<String>> {
    let mut out = BTreeMap::new();
    let t = &m.toks;
    let mut i = 0;
    while i < t.len() {
        if t[i] == Tok::Ident("pub".into()) {
            // `pub use`, `pub(crate) use`.
            let mut j = i + 1;
            if t.get(j) == Some(&Tok::Punct('(')) {
                while j < t.len() && t[j] != Tok::Punct(')') {
                    j += 1;
                }
                j += 1;
            }
            if t.get(j) == Some(&Tok::Ident("use".into())) {
                let end = (j..t.len())
                    .find(|&k| t[k] == Tok::Punct(';'))
                    .unwrap_or(t.len());
                let stmt = &t[j + 1..end];
                for p in named_paths(stmt, &m.path, known) {
                    if let Some(last) = p.last() {
                        out.insert(last.clone(), p.clone());
                    }
                }
                i = end;
            }
        }
        i += 1;
    }
    out
}

/// The module a path lands in: the longest known module prefix, followed through re-exports.
fn resolve(
    path: &[String],
    known: &BTreeSet<String>,
    exports: &BTreeMap<String, BTreeMap<String, Vec<String>>>,
    depth: usize,
) -> String {
    let mut best = String::new();
    let mut used = 0;
    for k in 1..=path.len() {
        let p = path[..k].join("::");
        if known.contains(&p) {
            best = p;
            used = k;
        }
    }
    if depth < 8 {
        if let Some(next) = path.get(used) {
            if let Some(target) = exports.get(&best).and_then(|e| e.get(next)) {
                if target.as_slice() != path {
                    return resolve(target, known, exports, depth + 1);
                }
            }
        }
    }
    best
}

fn graph_of(modules: &[Module]) -> ModuleGraph {
    let known: BTreeSet<String> = modules.iter().map(|m| m.path.clone()).collect();
    let exports: BTreeMap<String, BTreeMap<String, Vec<String>>> = modules
        .iter()
        .map(|m| (m.path.clone(), reexports(m, &known)))
        .collect();
    let mut g = ModuleGraph::default();
    for m in modules {
        if m.path.is_empty() {
            continue;
        }
        let deps = g.edges.entry(m.path.clone()).or_default();
        for p in named_paths(&m.toks, &m.path, &known) {
            let target = resolve(&p, &known, &exports, 0);
            if !target.is_empty() && target != m.path {
                deps.insert(target);
            }
        }
    }
    g
}

impl ModuleGraph {
    /// Every cycle as a strongly connected component of two or more modules.
    pub fn cycles(&self) -> Vec<Vec<String>> {
        // Tarjan's algorithm, iterative over a small graph.
        let nodes: Vec<&String> = self.edges.keys().collect();
        let index_of: BTreeMap<&String, usize> =
            nodes.iter().enumerate().map(|(i, n)| (*n, i)).collect();
        let adj: Vec<Vec<usize>> = nodes
            .iter()
            .map(|n| {
                self.edges[*n]
                    .iter()
                    .filter_map(|d| index_of.get(d).copied())
                    .collect()
            })
            .collect();
        let n = nodes.len();
        let mut index = vec![usize::MAX; n];
        let mut low = vec![0; n];
        let mut on_stack = vec![false; n];
        let mut stack = Vec::new();
        let mut next = 0;
        let mut out = Vec::new();
        for root in 0..n {
            if index[root] != usize::MAX {
                continue;
            }
            let mut work: Vec<(usize, usize)> = vec![(root, 0)];
            while let Some(&mut (v, ref mut child)) = work.last_mut() {
                if *child == 0 && index[v] == usize::MAX {
                    index[v] = next;
                    low[v] = next;
                    next += 1;
                    stack.push(v);
                    on_stack[v] = true;
                }
                if let Some(&w) = adj[v].get(*child) {
                    *child += 1;
                    if index[w] == usize::MAX {
                        work.push((w, 0));
                    } else if on_stack[w] {
                        low[v] = low[v].min(index[w]);
                    }
                    continue;
                }
                work.pop();
                if let Some(&(u, _)) = work.last() {
                    low[u] = low[u].min(low[v]);
                }
                if low[v] == index[v] {
                    let mut comp = Vec::new();
                    while let Some(w) = stack.pop() {
                        on_stack[w] = false;
                        comp.push(nodes[w].clone());
                        if w == v {
                            break;
                        }
                    }
                    if comp.len() > 1 {
                        comp.sort();
                        out.push(comp);
                    }
                }
            }
        }
        out.sort();
        out
    }

    /// One line per module: `module -> dep, dep`.
    pub fn render(&self) -> String {
        let mut s = String::new();
        for (m, deps) in &self.edges {
            let deps: Vec<&str> = deps.iter().map(String::as_str).collect();
            if deps.is_empty() {
                s.push_str(&format!("  {m}\n"));
            } else {
                s.push_str(&format!("  {m} -> {}\n", deps.join(", ")));
            }
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn graph(files: &[(&str, &str)]) -> ModuleGraph {
        let mods: Vec<Module> = files
            .iter()
            .map(|(p, text)| Module {
                path: p.to_string(),
                toks: without_test_items(&tokenize(text)).0,
            })
            .collect();
        graph_of(&mods)
    }

    #[test]
    fn edges_follow_paths_groups_super_and_reexports() {
        let g = graph(&[
            ("", "mod a; mod b; mod c; mod d; pub use c::Thing;"),
            ("a", "use crate::{b::X, Thing};"),
            ("b", "fn f() { super::d::g() }"),
            ("c", "pub struct Thing;"),
            ("d", "#[cfg(test)] mod tests { use crate::a::Y; }"),
        ]);
        let deps = |m: &str| g.edges[m].iter().cloned().collect::<Vec<_>>();
        assert_eq!(deps("a"), ["b", "c"]);
        assert_eq!(deps("b"), ["d"]);
        assert!(deps("d").is_empty());
        assert!(g.cycles().is_empty());
    }

    #[test]
    fn cycles_are_found() {
        let g = graph(&[
            ("a", "use crate::b::X;"),
            ("b", "use crate::c::Y;"),
            ("c", "fn f() { crate::a::z() }"),
            ("d", "use crate::a::W;"),
            ("p", "pub use q::Z; fn f() { q::g() }"),
            ("p::q", "use super::Other;"),
        ]);
        assert_eq!(
            g.cycles(),
            vec![
                vec!["a".to_string(), "b".into(), "c".into()],
                vec!["p".into(), "p::q".into()]
            ]
        );
    }
}
