#!/usr/bin/env python3
"""Scores the tracker's reprojected landmarks against an independent detector: dlib's 68-point
shape predictor (iBUG 300-W, `shape_predictor_68_face_landmarks.dat` from the PyPI package
`face_recognition_models`, CC0) on dlib's HOG face box.

Input: the JSON written by the Rust example `landmark_error` (every frame's image path and the
fitted FLAME's 70 landmarks reprojected into frame pixels; the first 68 are iBUG's order). Per
frame with a dlib face it prints the mean distance between our 68 reprojected points and
dlib's, over dlib's outer-eye-corner distance (points 36 and 45), and the same for the
MediaPipe points the fit was given (how far the two detectors' conventions differ), then the
medians.

Regenerate:
    pip install dlib-bin==20.0.1.post1 face_recognition_models==0.3.0 numpy pillow
    cargo run -p gagavatar-track --example landmark_error -- /tmp/photos.json PHOTO...
    python3 tools/reference/dlib_landmark_check.py /tmp/photos.json
    # a video's frames (see the example's header):
    python3 tools/reference/dlib_landmark_check.py /tmp/obama.json --quiet --upsample 0
    # or write the dlib points for inspection:
    python3 tools/reference/dlib_landmark_check.py /tmp/photos.json --dump /tmp/dlib.json

The package is located without importing it (its __init__ needs setuptools' pkg_resources).
"""

import argparse
import importlib.util
import json
import os
import sys

import dlib
import numpy as np
from PIL import Image


def predictor_path():
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or not spec.submodule_search_locations:
        sys.exit("face_recognition_models is not installed (pip install face_recognition_models)")
    root = list(spec.submodule_search_locations)[0]
    return os.path.join(root, "models", "shape_predictor_68_face_landmarks.dat")


def pts_or_none(v):
    if v is None or any(p is None for p in v[:68]):
        return None
    return np.array(v[:68], dtype=np.float64)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("track_json")
    ap.add_argument("--dump", help="write dlib's points per frame to this JSON")
    ap.add_argument("--quiet", action="store_true", help="medians only")
    ap.add_argument("--upsample", type=int, default=1, help="dlib detector upsampling (0 for large faces: faster)")
    a = ap.parse_args()
    doc = json.load(open(a.track_json))
    det = dlib.get_frontal_face_detector()
    pred = dlib.shape_predictor(predictor_path())
    ours, mp, dumped = [], [], []
    for f in doc["frames"]:
        rep = pts_or_none(f.get("reprojected"))
        mpp = pts_or_none(f.get("detected"))
        img = np.asarray(Image.open(f["path"]).convert("RGB"))
        boxes = det(img, a.upsample)
        if len(boxes) == 0:
            if not a.quiet:
                print(f"{f['path']}: dlib finds no face (ours: {'face' if f.get('face_found') else 'no face'})")
            dumped.append(None)
            continue
        # The dlib face that overlaps our points (the largest if we have none).
        if rep is not None:
            c = rep.mean(axis=0)
            box = min(boxes, key=lambda b: (b.center().x - c[0]) ** 2 + (b.center().y - c[1]) ** 2)
        else:
            box = max(boxes, key=lambda b: b.area())
        s = pred(img, box)
        # dlib's part coordinates are pixel indices; +0.5 puts them in the continuous convention
        # (pixel centres at +0.5) that our points use.
        d = np.array([[s.part(i).x + 0.5, s.part(i).y + 0.5] for i in range(68)])
        dumped.append(d.tolist())
        iod = np.linalg.norm(d[36] - d[45])
        line = f"{f['path']}:"
        if rep is not None:
            e = np.linalg.norm(rep - d, axis=1).mean() / iod
            ours.append(e)
            line += f" reprojected vs dlib {e:.4f}"
        if mpp is not None:
            e = np.linalg.norm(mpp - d, axis=1).mean() / iod
            mp.append(e)
            line += f"; MediaPipe (mapped) vs dlib {e:.4f}"
        if not a.quiet:
            print(line)
    n = len(doc["frames"])
    if ours:
        print(f"reprojected vs dlib: {len(ours)} of {n} frames, median {np.median(ours):.4f}, max {np.max(ours):.4f}")
    if mp:
        print(f"MediaPipe (mapped) vs dlib: {len(mp)} of {n} frames, median {np.median(mp):.4f}, max {np.max(mp):.4f}")
    if a.dump:
        json.dump({"dlib": dumped}, open(a.dump, "w"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
