//! Byte-level goldens of our writers' output (LMDB, records pickle, torch zip).
//!
//! A test writes a small fixed input with one of our writers and compares the file byte for
//! byte with a committed golden, and the values it wrote with a committed expected JSON beside
//! it (which `tools/reference/writer_goldens_check.py` reads the golden against, with the real
//! Python libraries). With `GAGAVATAR_BLESS=1` the test rewrites both instead; the Python check
//! must then be run again before committing them.
#![allow(dead_code)]

use std::path::Path;

/// Set (to anything but `0`) to rewrite the goldens instead of comparing with them.
pub const BLESS_VAR: &str = "GAGAVATAR_BLESS";
/// The Python check of the committed goldens (run after blessing).
pub const PYTHON_CHECK: &str = "python3 tools/reference/writer_goldens_check.py";

/// Whether this run rewrites the goldens.
pub fn blessing() -> bool {
    std::env::var_os(BLESS_VAR).is_some_and(|v| !v.is_empty() && v != "0")
}

fn show_byte(b: Option<&u8>) -> String {
    match b {
        Some(b) => format!("0x{b:02x}"),
        None => "end of file".to_owned(),
    }
}

/// The first offset at which `expected` and `actual` differ (a length difference counts at
/// the shorter one's end), or None when they are equal.
pub fn first_differing_byte(expected: &[u8], actual: &[u8]) -> Option<usize> {
    match expected.iter().zip(actual).position(|(e, a)| e != a) {
        Some(i) => Some(i),
        None => (expected.len() != actual.len()).then_some(expected.len().min(actual.len())),
    }
}

/// Compares the bytes a writer produced with the committed golden `golden` (or, when blessing,
/// writes them there). `regenerate` is the command that rewrites it, named on a mismatch.
pub fn check_bytes(golden: &Path, actual: &[u8], regenerate: &str) {
    if blessing() {
        if let Some(dir) = golden.parent() {
            std::fs::create_dir_all(dir).unwrap();
        }
        std::fs::write(golden, actual).unwrap();
        eprintln!(
            "blessed {} ({} bytes); now run {PYTHON_CHECK}",
            golden.display(),
            actual.len()
        );
        return;
    }
    let expected = std::fs::read(golden).unwrap_or_else(|e| {
        panic!(
            "{}: cannot read the golden ({e}); write it with: {regenerate}",
            golden.display()
        )
    });
    if let Some(message) = mismatch(golden, &expected, actual, regenerate) {
        panic!("{message}");
    }
}

/// The failure message when `actual` differs from the golden's bytes `expected`.
pub fn mismatch(golden: &Path, expected: &[u8], actual: &[u8], regenerate: &str) -> Option<String> {
    let at = first_differing_byte(expected, actual)?;
    Some(format!(
        "{}: the writer's output differs from the golden at byte {at} (0x{at:x}): expected {}, \
         actual {} (golden {} bytes, written {} bytes). If the change is intended, regenerate \
         with `{regenerate}`, then run `{PYTHON_CHECK}` and commit both.",
        golden.display(),
        show_byte(expected.get(at)),
        show_byte(actual.get(at)),
        expected.len(),
        actual.len()
    ))
}

/// Compares the values a test wrote with the committed expected JSON `path`, as text (numbers
/// in their shortest round-trip form, so equal text is equal values: serde_json's own parser
/// may be a unit in the last place off, which a comparison of parsed values would trip over),
/// or writes it there when blessing.
pub fn check_json(path: &Path, actual: &serde_json::Value, regenerate: &str) {
    let text = json_text(actual);
    if blessing() {
        check_bytes(path, text.as_bytes(), regenerate);
        return;
    }
    let committed = std::fs::read_to_string(path).unwrap_or_else(|e| {
        panic!(
            "{}: cannot read ({e}); write it with: {regenerate}",
            path.display()
        )
    });
    let mut want = committed.lines();
    let mut got = text.lines();
    for line in 1.. {
        match (want.next(), got.next()) {
            (None, None) => return,
            (w, g) if w == g => continue,
            (w, g) => panic!(
                "{}: the test's values differ from the committed ones at line {line}: \
                 expected {:?}, actual {:?}; if the test input changed on purpose, regenerate \
                 with `{regenerate}` and run `{PYTHON_CHECK}`",
                path.display(),
                w.unwrap_or("<end>"),
                g.unwrap_or("<end>")
            ),
        }
    }
}

/// The expected-JSON form of `v`, ending in a newline.
pub fn json_text(v: &serde_json::Value) -> String {
    let mut text = String::new();
    write_json(&mut text, v, 0);
    text.push('\n');
    text
}

/// Indentation step of the expected JSON files.
const INDENT: usize = 2;

/// JSON with objects one member a line, keys sorted (whatever order serde_json keeps), and
/// arrays of scalars on one line (short, readable diffs); arrays holding arrays or objects put
/// one item a line.
fn write_json(out: &mut String, v: &serde_json::Value, depth: usize) {
    use serde_json::Value as Json;
    let pad = |n: usize| " ".repeat(n * INDENT);
    match v {
        Json::Object(members) if !members.is_empty() => {
            let mut sorted: Vec<(&String, &Json)> = members.iter().collect();
            sorted.sort_by(|a, b| a.0.cmp(b.0));
            out.push_str("{\n");
            for (i, (k, item)) in sorted.into_iter().enumerate() {
                out.push_str(&pad(depth + 1));
                out.push_str(&Json::String(k.clone()).to_string());
                out.push_str(": ");
                write_json(out, item, depth + 1);
                out.push_str(if i + 1 < members.len() { ",\n" } else { "\n" });
            }
            out.push_str(&pad(depth));
            out.push('}');
        }
        Json::Array(items) if items.iter().any(|x| x.is_array() || x.is_object()) => {
            out.push_str("[\n");
            for (i, item) in items.iter().enumerate() {
                out.push_str(&pad(depth + 1));
                write_json(out, item, depth + 1);
                out.push_str(if i + 1 < items.len() { ",\n" } else { "\n" });
            }
            out.push_str(&pad(depth));
            out.push(']');
        }
        Json::Array(items) => {
            let inner: Vec<String> = items.iter().map(|x| x.to_string()).collect();
            out.push('[');
            out.push_str(&inner.join(", "));
            out.push(']');
        }
        other => out.push_str(&other.to_string()),
    }
}

#[test]
fn golden_mismatches_name_the_byte_and_the_command() {
    assert_eq!(first_differing_byte(b"abc", b"abc"), None);
    assert_eq!(first_differing_byte(b"", b"x"), Some(0));
    assert_eq!(first_differing_byte(b"ab", b"abc"), Some(2));
    let g = Path::new("g.bin");
    assert!(mismatch(g, b"abc", b"abc", "cmd").is_none());
    let m = mismatch(g, b"abcd", b"abXd", "REGEN").unwrap();
    assert!(
        m.contains("at byte 2 (0x2): expected 0x63, actual 0x58") && m.contains("`REGEN`"),
        "{m}"
    );
    let m = mismatch(g, b"abc", b"ab", "REGEN").unwrap();
    assert!(m.contains("expected 0x63, actual end of file"), "{m}");
    let v = serde_json::json!({"b": [1, 2.5], "a": {"x": [[0.1]]}, "c": []});
    assert_eq!(
        json_text(&v),
        "{\n  \"a\": {\n    \"x\": [\n      [0.1]\n    ]\n  },\n  \"b\": [1, 2.5],\n  \"c\": []\n}\n"
    );
}
