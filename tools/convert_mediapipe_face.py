#!/usr/bin/env python3
"""Convert MediaPipe's Apache-2.0 face models (TFLite) into the small safetensors files that
`crates/face` ships (run once; the outputs are committed).

Source: the PyPI wheel mediapipe==0.10.21 (cp311, manylinux_2_28_x86_64), the newest wheel that
still ships the legacy face models. Every model file's sha256 is checked against the table below
(spec TRACKING.md section 8) and, when the wheel itself is given, the wheel's sha256 too.

    pip download mediapipe==0.10.21 --no-deps --python-version 3.11 \
        --platform manylinux_2_28_x86_64 --only-binary=:all: -d /tmp/mp
    python3 tools/convert_mediapipe_face.py \
        --wheel /tmp/mp/mediapipe-0.10.21-cp311-cp311-manylinux_2_28_x86_64.whl \
        --out crates/face/weights

Pinned tools: tflite==2.18.0 (flatbuffer parser), numpy==1.26.4, flatbuffers (its flexbuffers
module reads the custom ops' options). Nothing is executed from the models; the script reads the
flatbuffers as data.

What is written per model (`<name>.safetensors`):
  * the parameters of every CONV_2D, DEPTHWISE_CONV_2D, PRELU and custom transposed convolution,
    named `<layer>.kernel`, `<layer>.bias`, `<layer>.alpha`, where `<layer>` is the Keras layer
    name TFLite kept (the op's output tensor, or for the sparse full-range model the layer named
    in the kernel tensor). Layouts are TFLite's own: CONV_2D kernels [O, kh, kw, I], depthwise
    [1, kh, kw, C], PReLU alpha [1, 1, C], transposed convolution [O, kh, kw, I]. FLOAT16
    weights (behind DEQUANTIZE ops) stay F16, so the values are bit-identical to the model's;
    FLOAT32 ones stay F32.
  * the full-range detector is stored sparse in the wheel (46 CSR-compressed 1x1 kernels behind
    DENSIFY ops); they are expanded here to dense arrays (the same numbers, zeros filled in).
  * metadata: source file and version, both sha256s, licence, the map from each key to the TFLite
    tensor it came from, and the custom ops' options and the graph constants the Rust code
    hard-codes (a Rust test compares them).
Also written: LICENSE (the wheel's Apache-2.0 text, verbatim), NOTICE and README.md (provenance).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import re
import struct
import sys
import zipfile

import numpy as np
import tflite
from flatbuffers import flexbuffers
from tflite.BuiltinOperator import BuiltinOperator

MEDIAPIPE_VERSION = "0.10.21"
WHEEL_NAME = "mediapipe-0.10.21-cp311-cp311-manylinux_2_28_x86_64.whl"
WHEEL_SHA256 = "05dc4a9e593655a79558d05d6227d31018c2537a4bd3362b51e230cf22aecfe3"

# (output name, path inside the wheel, sha256 from spec TRACKING.md section 8)
MODELS = [
    (
        "face_detection_short_range",
        "mediapipe/modules/face_detection/face_detection_short_range.tflite",
        "bbff11cebd1eb27a1e004cae0b0e63ec8c551cbf34a4451148b4908b8db3eca8",
    ),
    (
        "face_detection_full_range",
        "mediapipe/modules/face_detection/face_detection_full_range_sparse.tflite",
        "2c3728e6da56f21e21a320433396fb06d40d9088f2247c05e5635a688d45dfe1",
    ),
    (
        "face_landmark_with_attention",
        "mediapipe/modules/face_landmark/face_landmark_with_attention.tflite",
        "e06a804e0144f9929eda782122916b35d60c697c3c9344013ca2bbe76a6ce2b4",
    ),
    (
        "selfie_segmentation",
        "mediapipe/modules/selfie_segmentation/selfie_segmentation.tflite",
        "9ee168ec7c8f2a16c56fe8e1cfbc514974cbbb7e434051b455635f1bd1462f5c",
    ),
]

OPNAMES = {v: k for k, v in BuiltinOperator.__dict__.items() if not k.startswith("_")}
TFLITE_DTYPES = {0: np.float32, 1: np.float16, 2: np.int32, 3: np.uint8, 9: np.int8}
SAFETENSORS_DTYPES = {np.dtype(np.float32): "F32", np.dtype(np.float16): "F16"}
CLEAN_NAME = re.compile(r"^[A-Za-z0-9_]+$")
SPARSE_LAYER = re.compile(r"model_1/model/([A-Za-z0-9_]+)/(?:Conv2D|depthwise)")


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


class Graph:
    """Subgraph 0 of a TFLite model, read as data."""

    def __init__(self, data: bytes):
        self.model = tflite.Model.GetRootAsModel(data, 0)
        self.g = self.model.Subgraphs(0)
        self.producer = {}
        self.ops = []
        for k in range(self.g.OperatorsLength()):
            op = self.g.Operators(k)
            oc = self.model.OperatorCodes(op.OpcodeIndex())
            code = max(oc.BuiltinCode(), oc.DeprecatedBuiltinCode())
            name = OPNAMES[code]
            if name == "CUSTOM":
                name = "CUSTOM:" + oc.CustomCode().decode()
            ins = [int(i) for i in op.InputsAsNumpy()]
            outs = [int(i) for i in op.OutputsAsNumpy()]
            self.ops.append((k, name, ins, outs, op, oc))
            for o in outs:
                self.producer[o] = (name, ins)

    def name(self, i: int) -> str:
        return self.g.Tensors(i).Name().decode()

    def shape(self, i: int) -> list[int]:
        t = self.g.Tensors(i)
        return [int(d) for d in t.ShapeAsNumpy()] if t.ShapeLength() else []

    def buffer(self, i: int) -> np.ndarray | None:
        t = self.g.Tensors(i)
        b = self.model.Buffers(t.Buffer())
        if b is None or b.DataLength() == 0:
            return None
        return np.frombuffer(b.DataAsNumpy().tobytes(), dtype=TFLITE_DTYPES[t.Type()])

    def constant(self, i: int) -> tuple[np.ndarray, str]:
        """The constant behind tensor i, through DEQUANTIZE and DENSIFY, in its stored dtype."""
        name, ins = self.producer.get(i, (None, None))
        if name == "DEQUANTIZE":
            return self.constant(ins[0])
        if name == "DENSIFY":
            return self.densify(ins[0]), self.name(ins[0])
        if name is not None:
            raise ValueError(f"tensor {self.name(i)} is computed by {name}, not a constant")
        data = self.buffer(i)
        if data is None:
            raise ValueError(f"tensor {self.name(i)} has no data")
        if self.g.Tensors(i).Sparsity() is not None:
            raise ValueError(f"sparse tensor {self.name(i)} not behind a DENSIFY op")
        return data.reshape(self.shape(i)), self.name(i)

    def densify(self, i: int) -> np.ndarray:
        """TFLite sparse format with dense outer dimensions and one CSR (SPARSE_CSR) innermost
        dimension, traversal order identity, no block map: the only layout the wheel uses."""
        t = self.g.Tensors(i)
        sp = t.Sparsity()
        shape = self.shape(i)
        order = [int(v) for v in sp.TraversalOrderAsNumpy()]
        if order != list(range(len(shape))):
            raise ValueError(f"{self.name(i)}: traversal order {order} not supported")
        if sp.BlockMapLength() != 0:
            raise ValueError(f"{self.name(i)}: block maps not supported")
        ndim = sp.DimMetadataLength()
        for d in range(ndim - 1):
            dm = sp.DimMetadata(d)
            if dm.Format() != 0 or dm.DenseSize() != shape[d]:
                raise ValueError(f"{self.name(i)}: dimension {d} is not dense")
        last = sp.DimMetadata(ndim - 1)
        if last.Format() != 1:
            raise ValueError(f"{self.name(i)}: innermost dimension is not CSR")
        segments = sparse_vector(last.ArraySegments(), last.ArraySegmentsType())
        indices = sparse_vector(last.ArrayIndices(), last.ArrayIndicesType())
        values = self.buffer(i)
        rows = int(np.prod(shape[:-1]))
        if len(segments) != rows + 1 or segments[-1] != len(values) or len(indices) != len(values):
            raise ValueError(f"{self.name(i)}: inconsistent CSR arrays")
        dense = np.zeros((rows, shape[-1]), dtype=values.dtype)
        for r in range(rows):
            lo, hi = int(segments[r]), int(segments[r + 1])
            cols = indices[lo:hi].astype(np.int64)
            if np.any(cols >= shape[-1]) or np.any(np.diff(cols) <= 0):
                raise ValueError(f"{self.name(i)}: bad column indices in row {r}")
            dense[r, cols] = values[lo:hi]
        return dense.reshape(shape)


def sparse_vector(table, kind: int) -> np.ndarray:
    from tflite.Int32Vector import Int32Vector
    from tflite.Uint16Vector import Uint16Vector
    from tflite.Uint8Vector import Uint8Vector

    cls = {1: Int32Vector, 2: Uint16Vector, 3: Uint8Vector}[kind]
    v = cls()
    v.Init(table.Bytes, table.Pos)
    return v.ValuesAsNumpy().astype(np.int64)


def layer_name(graph: Graph, op_out: int, kernel: int) -> str:
    out = graph.name(op_out)
    if CLEAN_NAME.match(out):
        return out
    m = SPARSE_LAYER.search(graph.name(kernel))
    if not m:
        raise ValueError(f"cannot name the layer of {out!r}")
    return m.group(1)


def extract(graph: Graph):
    """Parameters by key, the key -> TFLite tensor map, custom op options and graph constants."""
    params: dict[str, np.ndarray] = {}
    sources: dict[str, str] = {}
    custom = []
    constants = {}

    def put(key, idx):
        arr, src = graph.constant(idx)
        if key in params:
            raise ValueError(f"duplicate key {key}")
        params[key] = np.ascontiguousarray(arr)
        sources[key] = src

    for k, name, ins, outs, op, oc in graph.ops:
        if name in ("CONV_2D", "DEPTHWISE_CONV_2D", "CUSTOM:Convolution2DTransposeBias"):
            layer = layer_name(graph, outs[0], ins[1])
            put(f"{layer}.kernel", ins[1])
            put(f"{layer}.bias", ins[2])
        elif name == "PRELU":
            put(f"{graph.name(outs[0])}.alpha", ins[1])
        if name.startswith("CUSTOM:"):
            raw = op.CustomOptionsAsNumpy()
            opts = flexbuffers.Loads(raw.tobytes()) if not isinstance(raw, int) else None
            if name == "CUSTOM:Convolution2DTransposeBias":
                opts = [int(v) for v in np.asarray(raw).view(np.int32)]
            custom.append(
                {"op": name[7:], "version": oc.Version(), "output": graph.name(outs[0]), "options": opts}
            )
        if name == "MUL":
            for i in ins:
                producer = graph.producer.get(i, (None,))[0]
                if producer == "DEQUANTIZE" or (producer is None and graph.buffer(i) is not None):
                    arr, src = graph.constant(i)
                    constants[src] = arr.astype(np.float32).reshape(-1).tolist()
    return params, sources, custom, constants


def write_safetensors(path: str, tensors: dict[str, np.ndarray], metadata: dict[str, str]):
    header = {"__metadata__": metadata}
    offset = 0
    blobs = []
    for key in sorted(tensors):
        arr = tensors[key]
        dtype = SAFETENSORS_DTYPES[arr.dtype]
        raw = arr.astype(arr.dtype.newbyteorder("<")).tobytes()
        header[key] = {"dtype": dtype, "shape": list(arr.shape), "data_offsets": [offset, offset + len(raw)]}
        offset += len(raw)
        blobs.append(raw)
    h = json.dumps(header, separators=(",", ":"), sort_keys=True).encode()
    h += b" " * ((8 - len(h) % 8) % 8)
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(struct.pack("<Q", len(h)))
        f.write(h)
        for b in blobs:
            f.write(b)
    os.replace(tmp, path)


NOTICE = """gagavatar face models
=====================

The files *.safetensors in this folder are Google MediaPipe face models (face detection
short range and full range, the face landmark model with attention, selfie segmentation),
Copyright The MediaPipe Authors, licensed under the Apache License, Version 2.0
(see LICENSE in this folder, copied verbatim from the mediapipe {version} wheel).

Source: PyPI package mediapipe=={version}, file {wheel}
(sha256 {wheel_sha}), the .tflite files listed in README.md.

Modifications: the weights were read out of the TFLite flatbuffers and stored in the
safetensors format by tools/convert_mediapipe_face.py. Values are unchanged (float16 kept as
float16); the full-range detector's sparse (CSR) 1x1 kernels were expanded to dense arrays.
No other change.
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--wheel", help=f"path to {WHEEL_NAME}")
    src.add_argument("--site-packages", help="folder holding an installed mediapipe=={MEDIAPIPE_VERSION}")
    ap.add_argument("--out", required=True, help="output folder (crates/face/weights)")
    args = ap.parse_args()

    if args.wheel:
        wheel_bytes = open(args.wheel, "rb").read()
        wheel_sha = sha256(wheel_bytes)
        if wheel_sha != WHEEL_SHA256:
            sys.exit(f"wheel sha256 {wheel_sha} != expected {WHEEL_SHA256}")
        zf = zipfile.ZipFile(io.BytesIO(wheel_bytes))
        read = zf.read
        licence = zf.read(f"mediapipe-{MEDIAPIPE_VERSION}.dist-info/LICENSE")
    else:
        wheel_sha = WHEEL_SHA256 + " (not re-checked: read from an installed package)"
        root = args.site_packages

        def read(p):
            return open(os.path.join(root, p), "rb").read()

        licence = read(f"mediapipe-{MEDIAPIPE_VERSION}.dist-info/LICENSE")

    os.makedirs(args.out, exist_ok=True)
    rows = []
    for name, path, expect in MODELS:
        data = read(path)
        digest = sha256(data)
        if digest != expect:
            sys.exit(f"{path}: sha256 {digest} != expected {expect}")
        graph = Graph(data)
        params, sources, custom, constants = extract(graph)
        metadata = {
            "format": "gagavatar-face-weights-1",
            "model": name,
            "source": f"mediapipe=={MEDIAPIPE_VERSION} ({WHEEL_NAME}): {path}",
            "source_sha256": digest,
            "wheel_sha256": wheel_sha,
            "license": "Apache-2.0",
            "converter": "tools/convert_mediapipe_face.py",
            "tflite_tensors": json.dumps(sources, sort_keys=True),
            "custom_ops": json.dumps(custom),
            "constants": json.dumps(constants, sort_keys=True),
        }
        out = os.path.join(args.out, f"{name}.safetensors")
        write_safetensors(out, params, metadata)
        n = sum(int(np.prod(a.shape)) for a in params.values())
        size = os.path.getsize(out)
        rows.append((name, path, len(data), digest, len(params), n, size))
        print(f"{out}: {len(params)} tensors, {n} parameters, {size} bytes")

    with open(os.path.join(args.out, "LICENSE"), "wb") as f:
        f.write(licence)
    with open(os.path.join(args.out, "NOTICE"), "w") as f:
        f.write(NOTICE.format(version=MEDIAPIPE_VERSION, wheel=WHEEL_NAME, wheel_sha=WHEEL_SHA256))
    with open(os.path.join(args.out, "README.md"), "w") as f:
        f.write("# MediaPipe face models (Apache-2.0)\n\n")
        f.write(
            f"Converted by `tools/convert_mediapipe_face.py` from the PyPI wheel `{WHEEL_NAME}` "
            f"(mediapipe=={MEDIAPIPE_VERSION}, sha256 `{WHEEL_SHA256}`). Licence: Apache-2.0 "
            "(`LICENSE`, `NOTICE`). Each file's metadata repeats its source, hashes and licence and "
            "maps every key to the TFLite tensor it came from.\n\n"
        )
        f.write("| file | source in the wheel | source bytes | source sha256 | tensors | parameters | file bytes |\n")
        f.write("|---|---|---|---|---|---|---|\n")
        for name, path, nbytes, digest, nt, n, size in rows:
            f.write(f"| `{name}.safetensors` | `{path}` | {nbytes:,} | `{digest}` | {nt} | {n:,} | {size:,} |\n")
        f.write(
            "\nThe full-range detector is the wheel's sparse model (the one MediaPipe's Python "
            "`FaceDetection(model_selection=1)` runs), with its CSR-compressed kernels expanded "
            "to dense arrays.\n"
        )


if __name__ == "__main__":
    main()
