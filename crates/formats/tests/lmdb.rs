//! LMDB: environments written by Python's `lmdb` (liblmdb 0.9.31) read exactly; our writer's
//! environments read back and equal a byte-level golden (which Python's `lmdb` reads);
//! truncated and corrupted files end in errors, never panics.

mod common;
#[path = "common/golden.rs"]
mod golden;

use std::path::Path;

use common::{data, value_bytes, TempDir};
use gagavatar_formats::lmdb::{write_lmdb, LmdbReader};
use gagavatar_formats::FormatError;

fn expected_entries(fixture: &str) -> Vec<(Vec<u8>, Vec<u8>)> {
    let exp = common::read_json("lmdb_expected.json");
    let e = &exp[fixture];
    if let Some(entries) = e.get("entries") {
        entries
            .as_array()
            .unwrap()
            .iter()
            .map(|t| {
                let key = t[0].as_str().unwrap().as_bytes().to_vec();
                (
                    key,
                    value_bytes(t[1].as_u64().unwrap(), t[2].as_u64().unwrap() as usize),
                )
            })
            .collect()
    } else {
        // `lmdb_fixtures.py::deep_key`.
        (0..e["count"].as_u64().unwrap())
            .map(|i| {
                let key = format!("{i:05}{}", "k".repeat(495)).into_bytes();
                (key, value_bytes(i, 4))
            })
            .collect()
    }
}

fn assert_stat(env: &LmdbReader, fixture: &str) {
    let exp = common::read_json("lmdb_expected.json");
    let s = &exp[fixture]["stat"];
    let st = env.stat();
    assert_eq!(
        st.page_size as u64,
        s["psize"].as_u64().unwrap(),
        "{fixture}: psize"
    );
    assert_eq!(
        st.depth as u64,
        s["depth"].as_u64().unwrap(),
        "{fixture}: depth"
    );
    assert_eq!(
        st.branch_pages,
        s["branch_pages"].as_u64().unwrap(),
        "{fixture}: branch pages"
    );
    assert_eq!(
        st.leaf_pages,
        s["leaf_pages"].as_u64().unwrap(),
        "{fixture}: leaf pages"
    );
    assert_eq!(
        st.overflow_pages,
        s["overflow_pages"].as_u64().unwrap(),
        "{fixture}: overflow pages"
    );
    assert_eq!(
        st.entries,
        s["entries"].as_u64().unwrap(),
        "{fixture}: entries"
    );
}

/// keys() equals the sorted expected keys; get() of every key returns its exact value; keys
/// that are absent (before, between, after, prefixes) give None.
fn assert_content(env: &LmdbReader, want: &[(Vec<u8>, Vec<u8>)], what: &str) {
    let mut sorted = want.to_vec();
    sorted.sort();
    let keys = env.keys().unwrap_or_else(|e| panic!("{what}: {e}"));
    assert_eq!(keys.len(), sorted.len(), "{what}: key count");
    for (i, (k, (wk, _))) in keys.iter().zip(&sorted).enumerate() {
        assert_eq!(k, wk, "{what}: key {i}");
    }
    for (k, v) in &sorted {
        let got = env.get(k).unwrap_or_else(|e| panic!("{what}: {e}"));
        let got =
            got.unwrap_or_else(|| panic!("{what}: key {:?} not found", String::from_utf8_lossy(k)));
        if let Some(i) = got.iter().zip(v).position(|(a, b)| a != b) {
            panic!(
                "{what}: value of {:?} differs at byte {i}: expected {}, actual {}",
                String::from_utf8_lossy(k),
                v[i],
                got[i]
            );
        }
        assert_eq!(
            got.len(),
            v.len(),
            "{what}: value length of {:?}",
            String::from_utf8_lossy(k)
        );
        assert!(env.contains_key(k).unwrap());
    }
    let mut absent: Vec<Vec<u8>> = vec![b"\x00".to_vec(), b"\xff\xff".to_vec(), b"a".to_vec()];
    for (k, _) in sorted.iter().take(50) {
        let mut longer = k.clone();
        longer.push(0);
        absent.push(longer);
        absent.push(k[..k.len() - 1].to_vec());
    }
    for k in absent {
        if k.is_empty() || sorted.binary_search_by(|(x, _)| x.cmp(&k)).is_ok() {
            continue;
        }
        assert_eq!(
            env.get(&k).unwrap(),
            None,
            "{what}: absent key {:?}",
            String::from_utf8_lossy(&k)
        );
    }
}

#[test]
fn python_written_environments_read_exactly() {
    for fixture in ["lmdb_mixed", "lmdb_deep"] {
        let env = LmdbReader::open(&data(fixture)).unwrap_or_else(|e| panic!("{e}"));
        assert_stat(&env, fixture);
        assert_content(&env, &expected_entries(fixture), fixture);
        // The data file itself opens too.
        let env = LmdbReader::open(&data(fixture).join("data.mdb")).unwrap();
        assert_eq!(env.len(), expected_entries(fixture).len());
    }
    // Two commits: the newer meta page is page 0 (txnid 2) and must win over page 1.
    let env = LmdbReader::open(&data("lmdb_mixed")).unwrap();
    assert_eq!(env.stat().txnid, 2);
    assert!(env.stat().depth >= 2 && env.stat().overflow_pages > 0);
    assert_eq!(
        LmdbReader::open(&data("lmdb_deep")).unwrap().stat().depth,
        3
    );
}

#[test]
fn the_older_meta_page_loses() {
    // Make page 1 claim a newer txnid than page 0: the reader must then follow page 1's
    // (older) tree, which holds the first transaction only (200 keys, no big values).
    let mut bytes = std::fs::read(data("lmdb_mixed/data.mdb")).unwrap();
    bytes[4096 + 144..4096 + 152].copy_from_slice(&9u64.to_le_bytes());
    let env = LmdbReader::from_bytes(Path::new("swapped"), bytes).unwrap();
    assert_eq!(env.stat().txnid, 9);
    assert_eq!(env.len(), 200);
    assert_eq!(env.get(b"big_0").unwrap(), None);
}

/// Entry i of the writer test (`tools/reference/lmdb_fixtures.py::writer_entry`).
fn writer_entry(i: u64) -> (Vec<u8>, Vec<u8>) {
    let key = format!("key_{:06}", i * 7919 % 100_003).into_bytes();
    let sizes = [0usize, 1, 17, 100, 2020, 2021, 3000, 4080, 4081, 12000];
    let len = if i.is_multiple_of(3) {
        sizes[(i as usize) % sizes.len()]
    } else {
        ((i * 13) % 64) as usize
    };
    (key, value_bytes(i, len))
}

/// How many entries the writer test writes: enough for three levels.
const WRITER_COUNT: u64 = 8000;

#[test]
fn written_environments_read_back() {
    let entries: Vec<_> = (0..WRITER_COUNT).map(writer_entry).collect();
    let dir = TempDir::new("lmdb");
    let env_dir = dir.path().join("img_lmdb");
    let stat = write_lmdb(&env_dir, entries.clone()).unwrap();
    assert!(stat.depth >= 3, "{stat:?}");
    assert!(stat.overflow_pages > 0, "{stat:?}");
    let env = LmdbReader::open(&env_dir).unwrap();
    assert_eq!(env.stat(), stat);
    assert_content(&env, &entries, "written");
    // The file is exactly the pages in use; nothing else is left in the directory.
    let len = std::fs::metadata(env_dir.join("data.mdb")).unwrap().len();
    assert_eq!(len, (stat.last_page + 1) * 4096);
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names, [std::ffi::OsString::from("img_lmdb")]);

    // Rewriting replaces the environment.
    write_lmdb(&env_dir, vec![(b"only".to_vec(), b"one".to_vec())]).unwrap();
    let env = LmdbReader::open(&env_dir).unwrap();
    assert_eq!(env.keys().unwrap(), [b"only".to_vec()]);
    assert_eq!(env.stat().depth, 1);
    // An empty environment.
    write_lmdb(&env_dir, Vec::new()).unwrap();
    let env = LmdbReader::open(&env_dir).unwrap();
    assert!(env.is_empty() && env.keys().unwrap().is_empty() && env.get(b"x").unwrap().is_none());

    if let Ok(out) = std::env::var("GAGAVATAR_LMDB_OUT") {
        write_lmdb(Path::new(&out), entries).unwrap();
    }
}

#[test]
fn writer_edge_sizes() {
    // The largest key, values at the inline / overflow boundary for it, and single-page data.
    let big_key = vec![b'k'; 511];
    let mut entries = vec![];
    for (i, len) in [
        0usize,
        1,
        2038 - 8 - 511,
        2038 - 8 - 511 + 1,
        4096 - 16,
        4096 - 15,
        1 << 20,
    ]
    .into_iter()
    .enumerate()
    {
        let mut k = big_key.clone();
        k[510] = b'0' + i as u8;
        entries.push((k, value_bytes(i as u64, len)));
    }
    // Many maximal keys: branch pages hold only a few, so the tree grows deep.
    for i in 0..400u64 {
        let mut k = format!("{i:05}").into_bytes();
        k.resize(511, b'z');
        entries.push((k, value_bytes(i, 3)));
    }
    let dir = TempDir::new("lmdb-edge");
    let stat = write_lmdb(&dir.path().join("e"), entries.clone()).unwrap();
    assert!(stat.depth >= 3, "{stat:?}");
    let env = LmdbReader::open(&dir.path().join("e")).unwrap();
    assert_content(&env, &entries, "edge sizes");
}

#[test]
fn writer_refuses_bad_keys() {
    let dir = TempDir::new("lmdb-bad");
    let target = dir.path().join("env");
    type Entries = Vec<(Vec<u8>, Vec<u8>)>;
    let cases: Vec<(Entries, &str)> = vec![
        (
            vec![(b"a".to_vec(), vec![1]), (b"a".to_vec(), vec![2])],
            "given twice",
        ),
        (vec![(Vec::new(), vec![1])], "has 0 bytes"),
        (vec![(vec![b'x'; 512], vec![1])], "has 512 bytes"),
    ];
    for (entries, needle) in cases {
        let e = write_lmdb(&target, entries).unwrap_err();
        assert!(
            matches!(e, FormatError::Write { .. }) && e.to_string().contains(needle),
            "{e}"
        );
        assert!(!target.exists(), "nothing is left behind on failure");
    }
    let leftovers: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert!(leftovers.is_empty(), "temporary directories are removed");
}

/// Every read path of a reader; must never panic.
fn exercise(bytes: Vec<u8>, keys: &[Vec<u8>]) -> bool {
    let Ok(env) = LmdbReader::from_bytes(Path::new("mem"), bytes) else {
        return false;
    };
    let mut ok = env.keys().is_ok();
    for k in keys {
        ok &= env.get(k).is_ok();
        ok &= env.contains_key(k).is_ok();
    }
    ok
}

fn xorshift(state: &mut u64) -> u64 {
    *state ^= *state << 13;
    *state ^= *state >> 7;
    *state ^= *state << 17;
    *state
}

#[test]
fn truncated_and_corrupted_files_give_errors() {
    // Every prefix of a small environment written by Python's `lmdb` (3 pages: a copy of
    // `crates/data/tests/data/release_small/img_lmdb`).
    let small = std::fs::read(data("lmdb_small/data.mdb")).unwrap();
    let small_keys = LmdbReader::open(&data("lmdb_small"))
        .unwrap()
        .keys()
        .unwrap();
    for cut in 0..small.len() {
        assert!(
            !exercise(small[..cut].to_vec(), &small_keys),
            "a {cut}-byte prefix read cleanly"
        );
    }
    assert!(exercise(small.clone(), &small_keys));
    // Prefixes of the two-level one every 61 bytes, and every page boundary +-1.
    let mixed = std::fs::read(data("lmdb_mixed/data.mdb")).unwrap();
    let keys: Vec<Vec<u8>> = expected_entries("lmdb_mixed")
        .into_iter()
        .map(|(k, _)| k)
        .collect();
    let mut cuts: Vec<usize> = (0..mixed.len()).step_by(61).collect();
    for p in (0..=mixed.len()).step_by(4096) {
        cuts.extend([p.saturating_sub(1), p, p + 1]);
    }
    for cut in cuts.into_iter().filter(|&c| c < mixed.len()) {
        let _ = exercise(mixed[..cut].to_vec(), &keys);
        assert!(
            LmdbReader::from_bytes(Path::new("mem"), mixed[..cut].to_vec())
                .and_then(|e| e.keys().map(|_| ()))
                .is_err()
                || cut >= 8192,
            "a {cut}-byte prefix lost its meta pages yet opened"
        );
    }
    // Random byte corruptions in the tree pages and meta pages.
    let mut state = 0x9e37_79b9_7f4a_7c15_u64;
    let mut noticed = 0;
    for n in 0..4000 {
        let mut bad = mixed.clone();
        for _ in 0..(1 + n % 4) {
            let r = xorshift(&mut state);
            let pos = (r % bad.len() as u64) as usize;
            bad[pos] = (r >> 40) as u8;
        }
        noticed += usize::from(!exercise(bad, &keys));
    }
    assert!(
        noticed > 100,
        "only {noticed} of 4000 corruptions were noticed"
    );
    // A fully random page in place of the root.
    let env = LmdbReader::open(&data("lmdb_mixed")).unwrap();
    let root_at = 7 * 4096;
    let mut bad = mixed.clone();
    for (i, b) in bad[root_at..root_at + 4096].iter_mut().enumerate() {
        *b = (i * 131 % 251) as u8;
    }
    assert!(!exercise(bad, &keys));
    drop(env);
}

#[test]
fn unsupported_and_foreign_files_are_named() {
    let e = LmdbReader::open(&data("numpy_misc_p4.pkl"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("numpy_misc_p4.pkl") && e.contains("LMDB"), "{e}");
    let e = LmdbReader::open(&data("no_such_env"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("no_such_env"), "{e}");
    // dupsort main database (flag 0x04 in the main DB record of both meta pages).
    let mut bytes = std::fs::read(data("lmdb_deep/data.mdb")).unwrap();
    for page in [0usize, 4096] {
        bytes[page + 88 + 4] = 0x04;
    }
    let e = LmdbReader::from_bytes(Path::new("dup.mdb"), bytes)
        .unwrap_err()
        .to_string();
    assert!(e.contains("duplicate keys (dupsort)"), "{e}");
}

// ---- byte-level golden of the writer -----------------------------------------------------

/// The largest leaf node liblmdb keeps inline on a 4096-byte page (`src/lmdb.rs::node_max`).
const NODE_MAX: usize = 2038;
/// A leaf node's header ahead of its key.
const NODE_HEADER: usize = 8;
/// Small entries of the golden: enough to need two leaf pages (depth 2).
const GOLDEN_SMALL: u64 = 96;
/// The golden environment and its expected JSON (also read by
/// `tools/reference/writer_goldens_check.py`).
const LMDB_GOLDEN: &str = "tests/golden/written/lmdb/data.mdb";
const LMDB_GOLDEN_JSON: &str = "tests/golden/written/lmdb_expected.json";
const LMDB_BLESS: &str = "GAGAVATAR_BLESS=1 cargo test -p gagavatar-formats --test lmdb \
                          written_environment_matches_golden";

/// The golden's entries `(key, seed, length)`, value `value_bytes(seed, length)`, in the
/// (unsorted) order given to the writer: release-like frame keys with values of 0 to 96 bytes,
/// a value at the largest inline size for its key, one a byte over (one overflow page) and one
/// over two pages.
fn golden_lmdb_entries() -> Vec<(String, u64, usize)> {
    let mut entries: Vec<(String, u64, usize)> = (0..GOLDEN_SMALL)
        // 37 is coprime with 96: a permutation, so keys arrive out of order.
        .map(|j| (j * 37) % GOLDEN_SMALL)
        .map(|i| {
            (
                format!("spk_{}_{}", i % 3, i / 3),
                i,
                ((i * 29) % 97) as usize,
            )
        })
        .collect();
    for (key, seed, len) in [
        (
            "spk_x_inline",
            500,
            NODE_MAX - NODE_HEADER - "spk_x_inline".len(),
        ),
        (
            "spk_x_overflow",
            501,
            NODE_MAX - NODE_HEADER - "spk_x_overflow".len() + 1,
        ),
        ("spk_x_large", 502, 5000),
    ] {
        entries.insert(entries.len() / 2, (key.to_owned(), seed, len));
    }
    entries
}

#[test]
fn written_environment_matches_golden() {
    let spec = golden_lmdb_entries();
    let entries: Vec<(Vec<u8>, Vec<u8>)> = spec
        .iter()
        .map(|(k, seed, len)| (k.as_bytes().to_vec(), value_bytes(*seed, *len)))
        .collect();
    let dir = TempDir::new("lmdb-golden");
    let env_dir = dir.path().join("env");
    let stat = write_lmdb(&env_dir, entries.clone()).unwrap();
    // The input covers what it is meant to: two levels, inline and overflow values.
    assert_eq!(stat.depth, 2, "{stat:?}");
    assert_eq!(stat.overflow_pages, 3, "{stat:?}");
    assert_content(
        &LmdbReader::open(&env_dir).unwrap(),
        &entries,
        "golden input",
    );
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let written = std::fs::read(env_dir.join("data.mdb")).unwrap();
    golden::check_bytes(&root.join(LMDB_GOLDEN), &written, LMDB_BLESS);

    let mut sorted = spec.clone();
    sorted.sort();
    let expected = serde_json::json!({
        "about": "entries in key order as [key, seed, length]; value bytes: \
                  (seed * 31 + j * 7 + (j >> 8)) % 256 for j < length",
        "stat": {
            "psize": stat.page_size,
            "depth": stat.depth,
            "branch_pages": stat.branch_pages,
            "leaf_pages": stat.leaf_pages,
            "overflow_pages": stat.overflow_pages,
            "entries": stat.entries,
        },
        "last_pgno": stat.last_page,
        "last_txnid": stat.txnid,
        "entries": sorted
            .iter()
            .map(|(k, seed, len)| serde_json::json!([k, seed, len]))
            .collect::<Vec<_>>(),
    });
    golden::check_json(&root.join(LMDB_GOLDEN_JSON), &expected, LMDB_BLESS);
}
