#!/usr/bin/env python3
"""Writes the fixtures of `crates/data` (tracked-data pickles, images, a small release dataset)
into `crates/data/tests/data/` (the `numpy_*` pickles and the refused ones into
`crates/formats/tests/data/`, beside the pickle reader), and checks files written by our Rust
writers.

Fixtures:

* `records_p2.pkl`, `records_p4.pkl`: an `optim.pkl`-like dict of 3 frames (names with
  underscores, natural order != lexicographic order), each a dict of float32 numpy arrays
  `bbox [4]`, `shapecode [300]`, `expcode [100]`, `posecode [6]`, `eyecode [6]`,
  `transform_matrix [3,4]`, plus extra keys the reader must skip (`lmks [5,2]`, `frame_index`).
* `records_p2_numpy1.pkl`, `records_p4_numpy1.pkl`: the same bytes with numpy 1.x module names
  (`numpy.core.*` instead of numpy 2's `numpy._core.*`), the protocol 4 one re-emitted without
  frames (the edit changes string lengths). CPython + numpy must load them to the same dict.
* `records_shape_1x300.pkl`: the 3 frames with `shapecode [1,300]` and `transform_matrix
  [1,3,4]`.
* `records_expected.json`: frame -> field -> {"shape", "hex": little-endian float32 bytes}.
* `numpy_misc_p{2,4,5}.pkl` and `numpy_misc_p2_numpy1.pkl`: every numpy form the reader
  understands (dtypes f16/f32/f64/i8/i32/i64/u8/bool, big-endian arrays, Fortran order, 0-d and
  empty arrays, an object array of numbers, numpy scalars, a shared array) and plain Python data
  (lists, tuples, nested dicts, int keys, None, bool, bytes, OrderedDict). Protocol 5 pickles
  contiguous arrays through `numpy._core.numeric._frombuffer`.
  `numpy_misc_expected.json`: the canonical form (see `canon`) of each.
* Refused pickles (never loaded here; dumping does not execute anything):
  `evil_os_system.pkl` (an object whose `__reduce__` is `os.system`), `torch_tensor.pkl`
  (`pickle.dumps(torch.zeros(3))`), `custom_class.pkl` (an instance of a class of this script),
  `numpy_complex.pkl` (a complex array), `numpy_structured.pkl` (a structured dtype).
* Images: `img_rgb.png` (7x5 RGB), `img_gray.png` (7x5 grayscale), `img_rgb.jpg` (16x8, quality
  95, no chroma subsampling), `img_u8_chw.pt` (`torch.save` of a uint8 [3,5,7] tensor),
  `img_f32_hwc.pt` (float32 [5,7,3] in [0,1], values k/255), `img_f64_chw.pt` (float64
  [1,3,5,7]); `images_expected.json`: the RGB bytes of each (the JPEG's as PIL decodes it).
* `release_small/`: a release dataset folder: `optim.pkl` (6 frames of 2 videos),
  `img_lmdb/data.mdb` (written by Python's `lmdb`; PNG values, one JPEG, one torch tensor) and
  `dataset.json`. Pixel values follow `release_pixel` below.

Check mode (for files written by our Rust writers):

    python3 tools/reference/tracked_data_fixtures.py --check-records FILE.pkl EXPECTED.json

loads FILE.pkl with pickle + numpy (no torch) and compares every frame and field with
EXPECTED.json (`{"order": [frame names in file order], "frames": {frame: {field: nested list
of numbers}}}`), requiring float32 numpy arrays with those shapes and bit-identical values.

Regenerate (from the repository root):  python3 tools/reference/tracked_data_fixtures.py
Pinned versions: numpy 2.1.3, torch 2.5.1, Pillow (any; PNG is lossless, the JPEG's decoded
bytes are stored), lmdb 1.5.1.
"""

import argparse
import collections
import io
import json
import os
import pickle
import pickletools
import sys

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..")
OUT = os.path.join(ROOT, "crates", "data", "tests", "data")
# The format-level pickles (numpy forms, refused content) belong to the pickle reader's crate.
OUT_FORMATS = os.path.join(ROOT, "crates", "formats", "tests", "data")

FIELDS = {
    "bbox": (4,),
    "shapecode": (300,),
    "expcode": (100,),
    "posecode": (6,),
    "eyecode": (6,),
    "transform_matrix": (3, 4),
}


def write(name, data, out=OUT):
    path = os.path.join(out, name)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        f.write(data)


def write_json(name, obj, out=OUT):
    write(name, (json.dumps(obj, indent=1, sort_keys=False) + "\n").encode(), out)


# ------------------------------------------------------------------------------------------
# Tracked-frame records


def make_frame(rng, extra=True):
    f = {
        "bbox": np.concatenate([rng.uniform(0.1, 0.4, 2), rng.uniform(0.6, 0.9, 2)]).astype(
            np.float32
        ),
        "shapecode": rng.normal(0, 1, 300).astype(np.float32),
        "expcode": rng.normal(0, 0.5, 100).astype(np.float32),
        "posecode": np.concatenate([np.zeros(3), rng.normal(0, 0.1, 3)]).astype(np.float32),
        "eyecode": rng.normal(0, 0.05, 6).astype(np.float32),
        "transform_matrix": np.concatenate(
            [np.eye(3) + rng.normal(0, 0.01, (3, 3)), [[0.01], [-0.02], [9.5]]], axis=1
        ).astype(np.float32),
    }
    if extra:
        f["lmks"] = rng.uniform(0, 1, (5, 2)).astype(np.float32)
        f["frame_index"] = int(rng.integers(0, 100))
    return f


def records_fixture():
    rng = np.random.default_rng(20240601)
    names = ["id_01_clip_10", "id_01_clip_2", "id_01_clip_0"]
    return {n: make_frame(rng) for n in names}


def le_hex(a, dtype):
    return np.ascontiguousarray(a, dtype=np.dtype(dtype).newbyteorder("<")).tobytes().hex()


def numpy1_names(data):
    """The same pickle with numpy 1.x module names: each opcode re-emitted, frames dropped
    (the edit changes string lengths, and frames are optional for the unpickler)."""
    proto = data[1] if data[:1] == b"\x80" else 0
    ops = list(pickletools.genops(data))
    out = bytearray()
    for i, (op, arg, pos) in enumerate(ops):
        end = ops[i + 1][2] if i + 1 < len(ops) else len(data)
        raw = data[pos:end]
        if op.name == "FRAME":
            continue
        if isinstance(arg, str) and arg.startswith("numpy._core"):
            new = arg.replace("numpy._core", "numpy.core", 1)
            if op.name == "SHORT_BINUNICODE":
                b = new.encode()
                raw = b"\x8c" + bytes([len(b)]) + b
            elif op.name == "BINUNICODE":
                b = new.encode()
                raw = b"X" + len(b).to_bytes(4, "little") + b
            elif op.name == "GLOBAL":
                raw = b"c" + new.replace(" ", "\n").encode() + b"\n"
            else:
                raise ValueError(op.name)
        out += raw
    assert proto in (2, 4, 5)
    return bytes(out)


def check_same(a, b, where="root"):
    """Deep equality of two loaded pickles (arrays: dtype, shape and bytes)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        assert isinstance(a, np.ndarray) and isinstance(b, np.ndarray), where
        assert a.dtype == b.dtype and a.shape == b.shape, where
        if a.dtype == object:
            assert a.tolist() == b.tolist(), where
        else:
            assert a.tobytes() == b.tobytes(), where
        return
    assert type(a) is type(b), (where, type(a), type(b))
    if isinstance(a, dict):
        assert list(a.keys()) == list(b.keys()), where
        for k in a:
            check_same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            check_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, where


def write_records():
    recs = records_fixture()
    p2 = pickle.dumps(recs, protocol=2)
    p4 = pickle.dumps(recs, protocol=4)
    write("records_p2.pkl", p2)
    write("records_p4.pkl", p4)
    for name, data in [("records_p2_numpy1.pkl", numpy1_names(p2)),
                       ("records_p4_numpy1.pkl", numpy1_names(p4))]:
        assert b"numpy._core" not in data and b"numpy.core" in data
        check_same(pickle.loads(data), recs)
        write(name, data)
    batched = {}
    for n, f in recs.items():
        g = dict(f)
        g["shapecode"] = f["shapecode"].reshape(1, 300)
        g["transform_matrix"] = f["transform_matrix"].reshape(1, 3, 4)
        batched[n] = g
    write("records_shape_1x300.pkl", pickle.dumps(batched, protocol=4))
    expected = {
        n: {k: {"shape": list(FIELDS[k]), "hex": le_hex(f[k].reshape(FIELDS[k]), "f4")}
            for k in FIELDS}
        for n, f in recs.items()
    }
    write_json("records_expected.json", expected)


# ------------------------------------------------------------------------------------------
# Miscellaneous numpy / Python data and its canonical form
#
# canon: None -> null; bool -> true/false; int -> {"int": "decimal"}; float -> {"float": hex of
# the float64 bits}; str -> "text"; bytes -> {"bytes": hex}; list/tuple -> {"list": [...]};
# dict / OrderedDict -> {"dict": [[key, value], ...]} in insertion order, key str or {"int"};
# numpy array -> {"array": dtype, "shape": [...], "hex": C-order little-endian bytes} with dtype
# one of bool u8 i8 u16 i16 u32 i32 u64 i64 f16 f32 f64 (an object array of numbers reads as f64,
# or i64 when all are ints); numpy scalars read as the plain Python value.

DTYPE_NAMES = {
    np.dtype(np.bool_): "bool", np.dtype(np.uint8): "u8", np.dtype(np.int8): "i8",
    np.dtype(np.uint16): "u16", np.dtype(np.int16): "i16", np.dtype(np.uint32): "u32",
    np.dtype(np.int32): "i32", np.dtype(np.uint64): "u64", np.dtype(np.int64): "i64",
    np.dtype(np.float16): "f16", np.dtype(np.float32): "f32", np.dtype(np.float64): "f64",
}


def canon(v):
    if v is None:
        return None
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return {"int": str(int(v))}
    if isinstance(v, (float, np.floating)):
        return {"float": np.float64(v).view(np.uint64).item().to_bytes(8, "big").hex()}
    if isinstance(v, str):
        return v
    if isinstance(v, (bytes, bytearray)):
        return {"bytes": bytes(v).hex()}
    if isinstance(v, (list, tuple)):
        return {"list": [canon(x) for x in v]}
    if isinstance(v, dict):
        return {"dict": [[k if isinstance(k, str) else {"int": str(k)}, canon(x)]
                         for k, x in v.items()]}
    if isinstance(v, np.ndarray):
        a = v
        if a.dtype == object:
            vals = a.ravel().tolist()
            dt = "i64" if all(isinstance(x, int) and not isinstance(x, bool) for x in vals) else "f64"
            a = np.array(vals, dtype="<i8" if dt == "i64" else "<f8").reshape(v.shape)
            return {"array": dt, "shape": list(v.shape), "hex": a.tobytes().hex()}
        dt = DTYPE_NAMES[a.dtype.newbyteorder("=")]
        le = np.ascontiguousarray(a).astype(a.dtype.newbyteorder("<"))
        return {"array": dt, "shape": list(a.shape), "hex": le.tobytes(order="C").hex()}
    raise TypeError(type(v))


def misc_fixture():
    shared = np.array([7.0, 8.0], np.float32)
    od = collections.OrderedDict()
    od["z"] = 1
    od["a"] = np.array([1, 2], np.int32)
    return {
        "f32": (np.arange(6, dtype=np.float32).reshape(2, 3) * 0.5 - 1),
        "f64_be": np.array([1.5, -2.25, 1e300, np.pi], dtype=">f8"),
        "i64": np.array([[-5, 2**40], [7, -(2**62)]], dtype=np.int64),
        "i32_be": np.array([1, -2, 3], dtype=">i4"),
        "i8": np.array([-128, 0, 127], dtype=np.int8),
        "u16_be": np.array([1, 65535], dtype=">u2"),
        "u8": np.arange(10, dtype=np.uint8),
        "bool": np.array([True, False, True]),
        "f16": np.array([0.5, -1.0, 65504.0, 1e-7], dtype=np.float16),
        "fortran": np.asfortranarray(np.arange(12, dtype=np.float32).reshape(3, 4)),
        "fortran_be": np.asfortranarray(np.arange(6, dtype=">f8").reshape(2, 3)),
        "zero_d": np.array(3.5, dtype=np.float32),
        "empty": np.zeros((0, 3), dtype=np.float32),
        "object_numbers": np.array([1.5, 2, -3], dtype=object),
        "object_ints": np.array([[1, 2], [3, -4]], dtype=object),
        # Object arrays pickle a C-order list even when the array is Fortran-ordered.
        "object_fortran": np.asfortranarray(np.array([[1, 2, 3], [4, 5, 6]], dtype=object)),
        "sliced": np.arange(20, dtype=np.float64).reshape(4, 5)[::2, 1::2],
        "np_f32": np.float32(0.1),
        "np_f64": np.float64(2.5),
        "np_i64": np.int64(-7),
        "np_u8": np.uint8(200),
        "np_bool": np.bool_(True),
        "py": [1, -(2**40), 2.5, "text é", None, True, False, b"\x00\xff", bytearray(b"ab"),
               (3, 4), {"nested": [1]}, {5: "int key"}],
        "ordered": od,
        "shared": [shared, shared],
    }


def write_misc():
    obj = misc_fixture()
    files = {}
    for proto in (2, 4, 5):
        data = pickle.dumps(obj, protocol=proto)
        files[f"numpy_misc_p{proto}.pkl"] = data
    files["numpy_misc_p2_numpy1.pkl"] = numpy1_names(files["numpy_misc_p2.pkl"])
    assert b"_frombuffer" in files["numpy_misc_p5.pkl"]
    want = canon(obj)
    for name, data in files.items():
        back = pickle.loads(data)
        assert canon(back) == want, name
        write(name, data, OUT_FORMATS)
    write_json("numpy_misc_expected.json", want, OUT_FORMATS)


# ------------------------------------------------------------------------------------------
# Pickles the reader must refuse


class Evil:
    def __reduce__(self):
        return (os.system, ("echo this must never run",))


class Custom:
    def __init__(self):
        self.x = 1


def write_refused():
    import torch

    write("evil_os_system.pkl", pickle.dumps({"frame_0": Evil()}, protocol=4), OUT_FORMATS)
    write("torch_tensor.pkl", pickle.dumps({"frame_0": {"shapecode": torch.zeros(3)}}, protocol=2), OUT_FORMATS)
    write("custom_class.pkl", pickle.dumps({"a": [Custom()]}, protocol=4), OUT_FORMATS)
    write("numpy_complex.pkl", pickle.dumps({"c": np.array([1 + 2j], np.complex64)}, protocol=4), OUT_FORMATS)
    st = np.zeros(2, dtype=[("a", "<f4"), ("b", "<i4")])
    write("numpy_structured.pkl", pickle.dumps({"s": st}, protocol=4), OUT_FORMATS)


# ------------------------------------------------------------------------------------------
# Images


def test_pattern(h, w):
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([(x * 37 + y * 11) % 256, (x * 5 + y * 53 + 90) % 256,
                     (x * y * 13 + 7) % 256], axis=-1).astype(np.uint8)


def smooth_pattern(h, w, offset=0):
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([x * 12 + y * 8 + 20 + offset, x * 6 + y * 14 + 40 + offset,
                     200 - x * 5 - y * 9 + offset], axis=-1).clip(0, 255).astype(np.uint8)


def encode(img, fmt, **kw):
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format=fmt, **kw)
    return buf.getvalue()


def decode(data):
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def torch_bytes(t):
    import torch

    buf = io.BytesIO()
    torch.save(t, buf)
    return buf.getvalue()


def write_images():
    import torch

    rgb = test_pattern(5, 7)
    gray = rgb[..., 1]
    smooth = smooth_pattern(8, 16)
    expected = {}
    write("img_rgb.png", encode(rgb, "PNG"))
    expected["img_rgb.png"] = rgb
    write("img_gray.png", encode(gray, "PNG"))
    expected["img_gray.png"] = np.repeat(gray[..., None], 3, axis=-1)
    jpg = encode(smooth, "JPEG", quality=95, subsampling=0)
    write("img_rgb.jpg", jpg)
    expected["img_rgb.jpg"] = decode(jpg)
    write("img_u8_chw.pt", torch_bytes(torch.from_numpy(rgb).permute(2, 0, 1).contiguous()))
    expected["img_u8_chw.pt"] = rgb
    write("img_f32_hwc.pt", torch_bytes(torch.from_numpy(rgb.astype(np.float32) / 255.0)))
    expected["img_f32_hwc.pt"] = rgb
    t64 = torch.from_numpy(rgb.astype(np.float64) / 255.0).permute(2, 0, 1)[None].contiguous()
    write("img_f64_chw.pt", torch_bytes(t64))
    expected["img_f64_chw.pt"] = rgb
    write_json("images_expected.json", {
        k: {"width": int(v.shape[1]), "height": int(v.shape[0]), "rgb_hex": v.tobytes().hex()}
        for k, v in expected.items()
    })


# ------------------------------------------------------------------------------------------
# A small release dataset folder


def release_pixel(frame_index):
    """8x8 RGB of frame `frame_index` (smooth, so the JPEG frame stays close)."""
    return smooth_pattern(8, 8, offset=2 * frame_index)


RELEASE_NAMES = ["spk_a_0", "spk_a_1", "spk_a_10", "spk_a_2", "spk_b_x_0", "spk_b_x_3"]


def write_release_small():
    import lmdb
    import torch

    base = os.path.join(OUT, "release_small")
    rng = np.random.default_rng(7)
    recs = {n: make_frame(rng, extra=False) for n in RELEASE_NAMES}
    write("release_small/optim.pkl", pickle.dumps(recs, protocol=4))
    write_json("release_small/dataset.json",
               {"train": ["spk_a_0", "spk_a_1", "spk_a_10", "spk_a_2"],
                "val": ["spk_b_x_0", "spk_b_x_3"], "test": []})
    lmdb_dir = os.path.join(base, "img_lmdb")
    for f in ("data.mdb", "lock.mdb"):
        if os.path.exists(os.path.join(lmdb_dir, f)):
            os.remove(os.path.join(lmdb_dir, f))
    env = lmdb.open(lmdb_dir, map_size=1 << 22)
    with env.begin(write=True) as txn:
        for i, n in enumerate(RELEASE_NAMES):
            img = release_pixel(i)
            if n == "spk_a_10":
                value = encode(img, "JPEG", quality=95, subsampling=0)
            elif n == "spk_b_x_3":
                value = torch_bytes(torch.from_numpy(img).permute(2, 0, 1).contiguous())
            else:
                value = encode(img, "PNG")
            txn.put(n.encode(), value)
    env.close()
    os.remove(os.path.join(lmdb_dir, "lock.mdb"))
    write_json("release_small/expected.json", {
        "records": {n: {k: {"shape": list(FIELDS[k]), "hex": le_hex(f[k], "f4")} for k in FIELDS}
                    for n, f in recs.items()},
        "jpeg_frame": "spk_a_10",
        "pixels": {n: release_pixel(i).tobytes().hex() for i, n in enumerate(RELEASE_NAMES)},
    })


# ------------------------------------------------------------------------------------------


def check_records(path, expected_path):
    """Loads a pickle written by our Rust writer and compares it with the expected numbers."""
    with open(path, "rb") as f:
        data = pickle.load(f)
    with open(path, "rb") as f:
        head = f.read(2)
    with open(expected_path) as f:
        doc = json.load(f)
    expected = doc["frames"]
    assert isinstance(data, dict), type(data)
    assert list(data.keys()) == doc["order"], (list(data)[:5], doc["order"][:5])
    assert sorted(data.keys()) == sorted(expected.keys())
    n_values = 0
    for name, fields in expected.items():
        frame = data[name]
        assert isinstance(frame, dict), (name, type(frame))
        assert list(frame.keys()) == list(FIELDS), (name, list(frame))
        for k in FIELDS:
            want = fields[k]
            a = frame[k]
            assert isinstance(a, np.ndarray), (name, k, type(a))
            assert a.dtype == np.float32, (name, k, a.dtype)
            w = np.array(want, dtype=np.float32)
            assert a.shape == w.shape, (name, k, a.shape, w.shape)
            assert a.flags.c_contiguous
            bad = np.flatnonzero(a.ravel().view(np.uint32) != w.ravel().view(np.uint32))
            assert bad.size == 0, (name, k, int(bad[0]), float(w.ravel()[bad[0]]),
                                   float(a.ravel()[bad[0]]))
            n_values += a.size
    proto = head[1] if head[:1] == b"\x80" else 0
    print(f"OK: {path}: {len(expected)} frames, {n_values} float32 values equal "
          f"(pickle protocol {proto}, numpy {np.__version__})")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check-records", nargs=2, metavar=("PKL", "EXPECTED_JSON"))
    args = ap.parse_args()
    if args.check_records:
        check_records(*args.check_records)
        return
    os.makedirs(OUT, exist_ok=True)
    write_records()
    write_misc()
    write_refused()
    write_images()
    write_release_small()
    print(f"wrote fixtures to {os.path.normpath(OUT)}")


if __name__ == "__main__":
    sys.exit(main())
