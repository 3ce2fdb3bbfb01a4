#!/usr/bin/env python3
"""Reads the byte-level goldens of our Rust writers with the real Python libraries and compares
them with the values the Rust tests wrote.

CI (no Python) compares each writer's output byte for byte with a committed golden; this script
is what shows those bytes are right. Goldens and the expected JSON beside each (both written by
the Rust test with GAGAVATAR_BLESS=1):

* `crates/formats/tests/golden/written/lmdb/data.mdb` + `lmdb_expected.json`
  (`gagavatar_formats::lmdb::write_lmdb`; test `--test lmdb written_environment_matches_golden`):
  opened with `lmdb` read-only without and with a lock file, every entry compared in cursor
  order, `stat()` and `info()` compared with what our writer reported, then liblmdb writes to it
  (small put, overflow put, delete) and it is reopened and re-checked.
* `crates/data/tests/data/written/optim.pkl` + `optim_expected.json`
  (`gagavatar_data::records::write_records`; `--test records written_records_match_golden`):
  `pickle.load` + numpy with warnings as errors, through
  `tracked_data_fixtures.check_records` (float32 arrays of the release's shapes, bit-identical
  values, frames in natural order).
* `crates/formats/tests/golden/written/checkpoint.pt` + `checkpoint_expected.json`
  (`gagavatar_formats::torch_zip::write_torch_zip`; `--test torch_zip
  written_checkpoint_matches_golden`): `torch.load` with `weights_only=True`, plain
  (`weights_only=False`, as the release code loads) and `weights_only=True, mmap=True`; the
  dict and state-dict types and key orders, every tensor's dtype, shape, layout and bytes, and
  `meta_cfg` (types, values and dict key order).

Run from anywhere (the goldens are never modified: liblmdb and torch work on copies):

    python3 tools/reference/writer_goldens_check.py

Pinned (`requirements.txt`): Python 3.11, numpy 2.1.3, lmdb 1.5.1 (bundles liblmdb 0.9.31),
torch 2.5.1. Prints one line per check and `OK`; exits non-zero on any difference.
"""

import collections
import json
import os
import shutil
import struct
import sys
import tempfile
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, "..", ".."))
FORMATS_GOLDEN = os.path.join(ROOT, "crates", "formats", "tests", "golden", "written")
DATA_GOLDEN = os.path.join(ROOT, "crates", "data", "tests", "data", "written")

sys.path.insert(0, HERE)
# The fixture scripts' own definitions: the value formula both sides use, liblmdb's stat
# fields, and the records check of `--check-records`.
from lmdb_fixtures import stat_of, value_bytes  # noqa: E402
from tracked_data_fixtures import check_records  # noqa: E402

# Values at least this long are counted as large (liblmdb's node limit is 2038 bytes).
LARGE_VALUE = 2000
# A value larger than a page, so liblmdb's continuation allocates overflow pages too.
CONTINUATION_BIG = 5000
# Storages are aligned so `torch.load(mmap=True)` can map them in place.
TORCH_ALIGN = 64


def load_json(path):
    with open(path, encoding="utf-8") as f:
        return json.load(f)


# ---- LMDB --------------------------------------------------------------------------------


def lmdb_check_entries(env, want):
    """Every entry in cursor order equals `want` (a list of (key, value) in key order)."""
    with env.begin() as txn:
        got = [(bytes(k), bytes(v)) for k, v in txn.cursor()]
        for k, v in want:
            assert txn.get(k) == v, f"get({k!r})"
    assert len(got) == len(want), f"{len(got)} entries, expected {len(want)}"
    for i, ((gk, gv), (wk, wv)) in enumerate(zip(got, want)):
        assert gk == wk, f"entry {i}: key {gk!r}, expected {wk!r}"
        assert gv == wv, f"{wk!r}: value of {len(gv)} bytes differs from the expected {len(wv)}"


def check_lmdb():
    import lmdb

    exp = load_json(os.path.join(FORMATS_GOLDEN, "lmdb_expected.json"))
    want = [(k.encode(), value_bytes(seed, n)) for k, seed, n in exp["entries"]]
    assert [k for k, _ in want] == sorted(k for k, _ in want), "expected entries not in key order"
    with tempfile.TemporaryDirectory() as tmp:
        copy = os.path.join(tmp, "env")
        shutil.copytree(os.path.join(FORMATS_GOLDEN, "lmdb"), copy)
        assert os.listdir(copy) == ["data.mdb"], os.listdir(copy)

        env = lmdb.open(copy, readonly=True, lock=False)
        lmdb_check_entries(env, want)
        stat, info = stat_of(env), env.info()
        env.close()
        assert stat == exp["stat"], (stat, exp["stat"])
        assert info["last_pgno"] == exp["last_pgno"], info
        assert info["last_txnid"] == exp["last_txnid"], info
        big = sum(1 for _, v in want if len(v) >= LARGE_VALUE)
        print(f"lmdb: read-only, lock=False: {len(want)} entries equal ({big} large), "
              f"stat {stat}, last_pgno {info['last_pgno']}, txnid {info['last_txnid']}: OK")

        env = lmdb.open(copy, readonly=True)
        lmdb_check_entries(env, want)
        env.close()
        print("lmdb: read-only with lock.mdb: OK")

        env = lmdb.open(copy, map_size=1 << 24)
        added = [(b"aaa_added_by_python", b"x" * CONTINUATION_BIG), (b"zzz_small", b"small")]
        removed = want[len(want) // 2][0]
        with env.begin(write=True) as txn:
            for k, v in added:
                assert txn.put(k, v)
            assert txn.delete(removed)
        env.close()
        after = sorted([kv for kv in want if kv[0] != removed] + added)
        env = lmdb.open(copy, readonly=True, lock=False)
        lmdb_check_entries(env, after)
        env.close()
        print(f"lmdb: liblmdb continues writing it (overflow put, small put, delete "
              f"{removed.decode()}, reopen): {len(after)} entries equal: OK")


# ---- records pickle ----------------------------------------------------------------------


def check_records_golden():
    with warnings.catch_warnings():
        # numpy 2 must resolve the numpy 1.x module names the writer uses without a warning.
        warnings.simplefilter("error")
        check_records(os.path.join(DATA_GOLDEN, "optim.pkl"),
                      os.path.join(DATA_GOLDEN, "optim_expected.json"))


# ---- torch zip ---------------------------------------------------------------------------


def strict_difference(got, want, where):
    """The first difference between loaded Python data and its JSON form, types included (so
    True != 1 and 1 != 1.0), dict key order aside; None when equal."""
    if type(got) is not type(want):
        return f"{where}: {type(got).__name__} {got!r}, expected {type(want).__name__} {want!r}"
    if isinstance(got, dict):
        if sorted(got) != sorted(want):
            return f"{where}: keys {sorted(got)}, expected {sorted(want)}"
        for k in want:
            d = strict_difference(got[k], want[k], f"{where}/{k}")
            if d:
                return d
        return None
    if isinstance(got, list):
        if len(got) != len(want):
            return f"{where}: {len(got)} items, expected {len(want)}"
        for i, (g, w) in enumerate(zip(got, want)):
            d = strict_difference(g, w, f"{where}/{i}")
            if d:
                return d
        return None
    if isinstance(got, float):
        same = struct.pack("<d", got) == struct.pack("<d", want)
        return None if same else f"{where}: {got!r}, expected {want!r}"
    return None if got == want else f"{where}: {got!r}, expected {want!r}"


def key_orders(value, path=""):
    """`[[path, [keys]], ...]` of every dict, depth first (the Rust test's `key_orders`)."""
    out = []
    if isinstance(value, dict):
        out.append([path, list(value)])
        for k, v in value.items():
            out.extend(key_orders(v, f"{path}/{k}"))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            out.extend(key_orders(v, f"{path}/{i}"))
    return out


def check_torch_layout(path, exp):
    """The archive as torch's reader needs it, read with zipfile alone."""
    import zipfile

    with open(path, "rb") as f:
        raw = f.read()
    with zipfile.ZipFile(path) as z:
        names = z.namelist()
        n = len(exp["model_order"])
        want = (["archive/data.pkl", "archive/byteorder"]
                + [f"archive/data/{i}" for i in range(n)] + ["archive/version"])
        assert names == want, names
        assert z.read("archive/byteorder") == b"little"
        assert z.read("archive/version") == b"3\n"
        for info in z.infolist():
            assert info.compress_type == zipfile.ZIP_STORED, info
            # The local header (30 bytes, name and extra lengths at 26 and 28), its name and
            # its extra field (which holds the alignment padding) precede the data.
            at = info.header_offset
            assert raw[at:at + 4] == b"PK\x03\x04", info.filename
            name_len, extra_len = struct.unpack_from("<HH", raw, at + 26)
            start = at + 30 + name_len + extra_len
            assert start % TORCH_ALIGN == 0, (info.filename, start)
    print(f"torch zip: {len(names)} stored entries under archive/, data {TORCH_ALIGN}-byte "
          f"aligned: OK")


def check_torch():
    import torch

    exp = load_json(os.path.join(FORMATS_GOLDEN, "checkpoint_expected.json"))
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "checkpoint.pt")
        shutil.copyfile(os.path.join(FORMATS_GOLDEN, "checkpoint.pt"), path)
        check_torch_layout(path, exp)
        for label, kwargs in [
            ("weights_only=True", dict(weights_only=True)),
            ("weights_only=False", dict(weights_only=False)),
            ("weights_only=True, mmap=True", dict(weights_only=True, mmap=True)),
        ]:
            ckpt = torch.load(path, map_location="cpu", **kwargs)
            assert type(ckpt) is dict, type(ckpt)
            assert list(ckpt) == ["model", "meta_cfg"], list(ckpt)
            model, cfg = ckpt["model"], ckpt["meta_cfg"]
            assert type(model) is collections.OrderedDict, type(model)
            assert list(model) == exp["model_order"], list(model)
            for key in exp["model_order"]:
                t, want = model[key], exp["model"][key]
                assert t.dtype == torch.float32, (key, t.dtype)
                assert list(t.shape) == want["shape"], (key, list(t.shape))
                assert t.is_contiguous() and t.storage_offset() == 0, key
                got = t.numpy().tobytes().hex()
                assert got == want["hex"], (key, got, want["hex"])
            d = strict_difference(cfg, exp["meta_cfg"], "meta_cfg")
            assert d is None, d
            assert key_orders(cfg) == exp["meta_cfg_key_order"], key_orders(cfg)
            print(f"torch.load({label}): dict {list(ckpt)}, model an OrderedDict of "
                  f"{len(model)} float32 tensors with the expected shapes and bytes, meta_cfg "
                  f"equal with its key order: OK")


def main():
    import lmdb
    import torch

    print(f"Python {sys.version.split()[0]}, numpy {np.__version__}, lmdb {lmdb.__version__} "
          f"(liblmdb {'.'.join(map(str, lmdb.version()))}), torch {torch.__version__}")
    check_lmdb()
    check_records_golden()
    check_torch()
    print("OK")


if __name__ == "__main__":
    main()
