#!/usr/bin/env python3
"""Loads a folder written by `gagavatar-track` the way the GAGAvatar release's inference code
loads a tracked driver or dataset folder, and checks what that code relies on.

Written from the project's specs (GAGAVATAR.md section 10, TRACKING.md section 6), not from the
release's code:

* records: `smoothed.pkl` if present, else `optim.pkl`, read with plain `pickle.load` (no
  custom classes): a dict frame name -> dict of numpy arrays; the six keys `bbox [4]`,
  `shapecode [300]`, `expcode [100]`, `posecode [6]`, `eyecode [6]`, `transform_matrix [3,4]`,
  all float32 and finite; the release converts each with `torch.tensor(...)`.
* frame order: names sorted by the integer after their last underscore (the driver loader);
  for training, the video id is the text before the first underscore (so names must not
  contain another underscore).
* images: `img_lmdb/` opened read-only without a lock file (`lmdb.open(path, readonly=True,
  lock=False, readahead=False, meminit=True)`), value of `name.encode()` decoded as an RGB image
  (torchvision's `decode_image` when installed, else Pillow), 512x512.
* camera: `transform_matrix` = [R | T] with R a rotation (rows orthonormal, det +1); the point
  plane of GAGAVATAR.md section 3 built from it is finite; global pose `posecode[0:3]` zero.
* `track.json`: frames and keys match the pickles; windows are integer boxes; 70 fitted
  landmarks per frame; its records equal the final pickle's.

Usage:
    python3 tools/reference/track_loader_check.py DIR [DIR ...]

Sample folders for it (synthetic heads, photo and video):
    GAGAVATAR_TRACK_SAMPLE_DIR=/tmp/track_samples cargo test -p gagavatar-track \
        --test output folder_reads_back
    python3 tools/reference/track_loader_check.py /tmp/track_samples/photo /tmp/track_samples/video

Needs numpy, lmdb and Pillow (tested with numpy 1.26.4, lmdb 1.5.1, Pillow 11.0.0); torch is
used when installed to mirror `torch.tensor(...)` conversions.
"""

import io
import json
import os
import pickle
import sys

import numpy as np

SHAPES = {
    "bbox": (4,),
    "shapecode": (300,),
    "expcode": (100,),
    "posecode": (6,),
    "eyecode": (6,),
    "transform_matrix": (3, 4),
}


class CheckError(Exception):
    pass


def need(cond, msg):
    if not cond:
        raise CheckError(msg)


def load_records(path):
    with open(path, "rb") as f:
        data = pickle.load(f)
    need(isinstance(data, dict), f"{path}: top level is {type(data).__name__}, not dict")
    for name, rec in data.items():
        need(isinstance(name, str), f"{path}: key {name!r} is not a str")
        need(isinstance(rec, dict), f"{path}: {name} is {type(rec).__name__}, not dict")
        for key, shape in SHAPES.items():
            need(key in rec, f"{path}: {name} lacks {key}")
            a = rec[key]
            need(isinstance(a, np.ndarray), f"{path}: {name}.{key} is {type(a).__name__}")
            need(a.dtype == np.float32, f"{path}: {name}.{key} dtype {a.dtype}")
            need(a.shape == shape, f"{path}: {name}.{key} shape {a.shape}, expected {shape}")
            need(np.isfinite(a).all(), f"{path}: {name}.{key} not finite")
    return data


def frame_order(names):
    # The driver loader: sorted(keys, key=lambda x: int(x.split('_')[-1])).
    return sorted(names, key=lambda x: int(x.split("_")[-1]))


def video_id(name):
    # The training loader's get_video_id (ignoring its 'img_' special case).
    return name.split("_")[0]


def point_plane(tm, size=296):
    """GAGAVATAR.md section 3: rays through a plane at the depth of the world origin."""
    r = tm[:, :3].astype(np.float64)
    t = tm[:, 3].astype(np.float64)
    lin = np.linspace(1.0, -1.0, size)
    x, y = np.meshgrid(lin, lin, indexing="xy")
    rays = np.stack([x / 12.0, y / 12.0, np.ones_like(x)], axis=-1).reshape(-1, 3)
    dirs = rays @ r.T
    cam_dir = r @ np.array([0.0, 0.0, 1.0])
    origin = -(r @ t)
    distance = abs(float(origin @ cam_dir))
    return origin + distance * dirs, cam_dir


def decode(payload):
    try:
        import torch
        import torchvision

        buf = torch.tensor(np.frombuffer(payload, dtype=np.uint8))
        img = torchvision.io.decode_image(buf, mode=torchvision.io.ImageReadMode.RGB)
        return img.permute(1, 2, 0).numpy()
    except ImportError:
        from PIL import Image

        return np.asarray(Image.open(io.BytesIO(payload)).convert("RGB"))


def check_dir(d):
    import lmdb

    smoothed = os.path.join(d, "smoothed.pkl")
    optim = os.path.join(d, "optim.pkl")
    need(os.path.isfile(optim), f"{d}: no optim.pkl")
    records_path = smoothed if os.path.exists(smoothed) else optim
    records = load_records(records_path)
    raw = load_records(optim)
    need(set(raw) == set(records), f"{d}: optim.pkl and smoothed.pkl hold different frames")
    names = frame_order(list(records))
    idx = [int(n.split("_")[-1]) for n in names]
    need(idx == list(range(len(idx))), f"{d}: frame numbers {idx[:5]}... are not 0..n-1")
    vids = {video_id(n) for n in names}
    need(len(vids) == 1, f"{d}: the training loader would see videos {sorted(vids)}")

    try:
        import torch

        for n in names:
            for key in SHAPES:
                torch.tensor(records[n][key]).float()
    except ImportError:
        pass

    for n in names:
        rec = records[n]
        tm = rec["transform_matrix"]
        r = tm[:, :3].astype(np.float64)
        need(np.abs(r @ r.T - np.eye(3)).max() < 1e-5, f"{d}: {n} R is not orthonormal")
        need(abs(np.linalg.det(r) - 1.0) < 1e-5, f"{d}: {n} det R = {np.linalg.det(r)}")
        need(np.all(rec["posecode"][:3] == 0), f"{d}: {n} global pose is not zero")
        need(0 <= rec["bbox"].min() and rec["bbox"].max() <= 1, f"{d}: {n} bbox outside [0, 1]")
        pts, cam_dir = point_plane(tm)
        need(np.isfinite(pts).all() and np.isfinite(cam_dir).all(), f"{d}: {n} point plane")
        # The head (world origin) is in front of the camera: depth = (0 R + T)_z = T_z > 0.
        need(tm[2, 3] > 0, f"{d}: {n} the head is behind the camera")

    env = lmdb.open(os.path.join(d, "img_lmdb"), readonly=True, lock=False, readahead=False, meminit=True)
    with env.begin(write=False) as txn:
        keys = [k.decode() for k in txn.cursor().iternext(values=False)]
        need(sorted(keys) == sorted(names), f"{d}: LMDB keys differ from the records' frames")
        for n in names:
            payload = txn.get(n.encode())
            need(payload is not None, f"{d}: LMDB lacks {n}")
            need(payload[:3] == b"\xff\xd8\xff", f"{d}: {n} is not a JPEG")
            img = decode(payload)
            need(img.shape == (512, 512, 3) and img.dtype == np.uint8, f"{d}: {n} image {img.shape}")
    env.close()

    with open(os.path.join(d, "track.json")) as f:
        tj = json.load(f)
    need(tj["format"] == "gagavatar-track" and tj["version"] == 1, f"{d}: track.json format")
    need([fr["key"] for fr in tj["frames"]] == names, f"{d}: track.json frames differ")
    for fr in tj["frames"]:
        w = fr["window"]
        need(len(w) == 4 and all(isinstance(v, int) for v in w) and w[2] > w[0] and w[3] > w[1],
             f"{d}: {fr['key']} window {w}")
        need(len(fr["landmarks_fitted"]) == 70, f"{d}: {fr['key']} fitted landmarks")
        det = fr["landmarks_detected"]
        need(det is None or len(det) == 70, f"{d}: {fr['key']} detected landmarks")
        need(det is not None or not fr["face_found"], f"{d}: {fr['key']} face without landmarks")
        for key in SHAPES:
            a = np.asarray(fr["record"][key], dtype=np.float32)
            need(np.array_equal(a, records[fr["key"]][key]), f"{d}: {fr['key']}.{key} differs from the pickle")
    found = sum(fr["face_found"] for fr in tj["frames"])
    print(f"{d}: OK: {len(names)} frames ({found} with a face) from {os.path.basename(records_path)}, "
          f"six float32 keys, 512x512 JPEGs, track.json consistent")


def main():
    if len(sys.argv) < 2:
        print(__doc__)
        return 2
    ok = True
    for d in sys.argv[1:]:
        try:
            check_dir(d)
        except CheckError as e:
            ok = False
            print(f"FAIL: {e}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
