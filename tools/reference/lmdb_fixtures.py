#!/usr/bin/env python3
"""LMDB fixtures of `crates/formats` (`src/lmdb.rs`), written by Python's `lmdb` binding (1.5.1,
which bundles liblmdb 0.9.31), and a checker for environments written by our Rust writer.

Fixtures (in `crates/formats/tests/data/`):

* `lmdb_mixed/data.mdb`: two write transactions, so the newest meta page is page 0
  (txnid 2; page 1 holds the older txnid 1). Transaction 1 puts 200 keys `frame_NNNN` in a
  shuffled order (values 0..40 bytes); transaction 2 puts 100 more, overwrites 10, deletes 5,
  and puts 4 values larger than a page (3000, 4100, 9000 and 2030 bytes: overflow pages; 2030 is
  the first size that overflows with a 10-byte key, since the node limit is 2038 bytes). Depth 2.
* `lmdb_deep/data.mdb`: 70 keys of 500 bytes (append mode, full pages): depth 3.
* `lmdb_expected.json`: per fixture the stat (`psize`, `depth`, `branch_pages`, `leaf_pages`,
  `overflow_pages`, `entries`); for `lmdb_mixed` every entry as `[key, seed, length]` (keys are
  ASCII), the value bytes being `value_bytes(seed, length)` (below; the Rust test has the same
  formula); for `lmdb_deep` the count, its entries being `deep_key(i)` -> `value_bytes(i, 4)`.

Regenerate (from the repository root):  python3 tools/reference/lmdb_fixtures.py

Check an environment written by our writer (the Rust test `written_environments_read_back` in `crates/formats/tests/lmdb.rs` writes one
to `$GAGAVATAR_LMDB_OUT` when that variable is set):

    python3 tools/reference/lmdb_fixtures.py --check DIR [--count N]

opens DIR read-only with `lock=False` and again with the default locking (which creates
`lock.mdb` beside `data.mdb`; so this runs on a copy), iterates every entry with a cursor,
checks each against `writer_entry(i)` for i < N (the formula the Rust test writes), checks
`stat()` against the entry count, then, on the copy, opens it read-write, puts and deletes
entries in one transaction, reopens and re-checks, to show liblmdb itself can continue writing
the environment.
"""

import argparse
import json
import os
import random
import shutil
import sys
import tempfile

import lmdb

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..")
OUT = os.path.join(ROOT, "crates", "formats", "tests", "data")


def value_bytes(seed, length):
    return bytes((seed * 31 + j * 7 + (j >> 8)) % 256 for j in range(length))


def writer_entry(i):
    """Entry i of the Rust writer test (`tests/lmdb.rs::writer_entry`)."""
    key = f"key_{i * 7919 % 100003:06d}".encode()
    sizes = [0, 1, 17, 100, 2020, 2021, 3000, 4080, 4081, 12000]
    length = sizes[i % len(sizes)] if i % 3 == 0 else (i * 13) % 64
    return key, value_bytes(i, length)


def stat_of(env):
    s = env.stat()
    return {k: s[k] for k in ("psize", "depth", "branch_pages", "leaf_pages", "overflow_pages",
                              "entries")}


def fresh(path):
    if os.path.exists(path):
        shutil.rmtree(path)
    os.makedirs(path)


def make_mixed(expected):
    path = os.path.join(OUT, "lmdb_mixed")
    fresh(path)
    rng = random.Random(5)
    content = {}
    env = lmdb.open(path, map_size=1 << 22)
    first = list(range(200))
    rng.shuffle(first)
    with env.begin(write=True) as txn:
        for i in first:
            key = f"frame_{i:04d}".encode()
            content[key] = (i, rng.randrange(0, 41))
            txn.put(key, value_bytes(*content[key]))
    with env.begin(write=True) as txn:
        for i in range(200, 300):
            key = f"frame_{i:04d}".encode()
            content[key] = (i, rng.randrange(0, 41))
            txn.put(key, value_bytes(*content[key]))
        for i in rng.sample(range(300), 10):
            key = f"frame_{i:04d}".encode()
            content[key] = (1000 + i, rng.randrange(0, 41))
            txn.put(key, value_bytes(*content[key]))
        for i in rng.sample(range(300), 5):
            key = f"frame_{i:04d}".encode()
            assert txn.delete(key)
            del content[key]
        for n, length in enumerate([3000, 4100, 9000, 2030]):
            key = f"big_{n}".encode()
            content[key] = (77 + n, length)
            txn.put(key, value_bytes(*content[key]))
    stat = stat_of(env)
    env.close()
    os.remove(os.path.join(path, "lock.mdb"))
    assert stat["depth"] >= 2 and stat["overflow_pages"] > 0, stat
    expected["lmdb_mixed"] = {
        "stat": stat,
        "entries": [[k.decode(), s, n] for k, (s, n) in sorted(content.items())],
    }


def deep_key(i):
    """Key i of `lmdb_deep` (its value is `value_bytes(i, 4)`)."""
    return (f"{i:05d}" + "k" * 495).encode()


def make_deep(expected):
    path = os.path.join(OUT, "lmdb_deep")
    fresh(path)
    env = lmdb.open(path, map_size=1 << 22)
    content = {}
    with env.begin(write=True) as txn:
        for i in range(70):
            key = deep_key(i)
            content[key] = (i, 4)
            assert txn.put(key, value_bytes(i, 4), append=True)
    stat = stat_of(env)
    env.close()
    os.remove(os.path.join(path, "lock.mdb"))
    assert stat["depth"] == 3, stat
    expected["lmdb_deep"] = {"stat": stat, "count": len(content)}


def check_entries(env, count):
    want = dict(writer_entry(i) for i in range(count))
    seen = 0
    prev = None
    with env.begin() as txn:
        for k, v in txn.cursor():
            assert prev is None or prev < k, f"keys out of order at {k!r}"
            prev = k
            assert k in want, f"unexpected key {k!r}"
            assert v == want[k], f"value of {k!r}: {len(v)} bytes, expected {len(want[k])}"
            seen += 1
        for k, v in want.items():
            got = txn.get(k)
            assert got == v, f"get({k!r})"
    assert seen == len(want), f"{seen} entries, expected {len(want)}"
    assert env.stat()["entries"] == len(want), env.stat()
    return env.stat()


def check(path, count):
    with tempfile.TemporaryDirectory() as tmp:
        copy = os.path.join(tmp, "env")
        shutil.copytree(path, copy)
        env = lmdb.open(copy, readonly=True, lock=False)
        stat = check_entries(env, count)
        env.close()
        print(f"read-only, lock=False: {count} entries OK, stat {dict(stat)}")
        env = lmdb.open(copy, readonly=True)
        check_entries(env, count)
        env.close()
        print("read-only with lock.mdb: OK")
        env = lmdb.open(copy, map_size=1 << 30)
        with env.begin(write=True) as txn:
            txn.put(b"aaa_added_by_python", b"x" * 5000)
            txn.put(b"key_zzzzzz", b"small")
            first = writer_entry(0)[0]
            assert txn.delete(first)
        env.close()
        env = lmdb.open(copy, readonly=True, lock=False)
        with env.begin() as txn:
            assert txn.get(b"aaa_added_by_python") == b"x" * 5000
            assert txn.get(b"key_zzzzzz") == b"small"
            assert txn.get(first) is None
            n = sum(1 for _ in txn.cursor())
        assert n == count + 1, n
        env.close()
        print("read-write continuation (put, overflow put, delete, reopen): OK")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", metavar="DIR")
    ap.add_argument("--count", type=int, default=8000)
    args = ap.parse_args()
    if args.check:
        check(args.check, args.count)
        return 0
    expected = {}
    make_mixed(expected)
    make_deep(expected)
    with open(os.path.join(OUT, "lmdb_expected.json"), "w") as f:
        json.dump(expected, f, indent=0)
        f.write("\n")
    for name, e in expected.items():
        size = os.path.getsize(os.path.join(OUT, name, "data.mdb"))
        print(f"{name}: {size} bytes, stat {e['stat']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
