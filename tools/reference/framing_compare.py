#!/usr/bin/env python3
"""Compares where our tracker's 512 crop puts the face with where the release's crops do.

Both sides are measured the same way: MediaPipe Face Mesh 0.10.21 (refine_landmarks, 478
points) gives, in 512-crop pixels, the iris midpoint (x, y), the inter-iris distance and the
mouth centre (mean of the lip corners 61 and 291).

* Ours: the `landmark_error` example's JSON (per frame the image path and our crop window);
  MediaPipe runs on the original image and the points are mapped through the window (the crop is
  a pure scale and shift of the frame).
* Theirs, per photo: the release's tracking visualisation `track_<name>.jpg` (a torchvision grid
  with padding 2; its first panel is the release's 512 crop), paired by file name
  (`--release monroe.jpg=/work/demos/track_monroe.jpg`).
* Theirs, in general: the 40 training crops of the release's VFHQ demo LMDB
  (`--lmdb /work/demos/vfhq_demo`), medians.

Regenerate (monroe and obama frames of the release's demo files):
    cargo run -p gagavatar-track --example landmark_error -- /tmp/photos.json /work/demos/monroe.jpg
    python3 tools/reference/framing_compare.py /tmp/photos.json \
        --release monroe.jpg=/work/demos/track_monroe.jpg --lmdb /work/demos/vfhq_demo
"""

import argparse
import io
import json
import os
import sys

import mediapipe as mp
import numpy as np
from PIL import Image

CROP = 512.0


def stats(p):
    """p: 478 x 2 points in 512-crop pixels."""
    eye = (p[468] + p[473]) / 2
    return {
        "eye_x": eye[0],
        "eye_y": eye[1],
        "iris_dist": np.linalg.norm(p[473] - p[468]),
        "mouth_x": (p[61][0] + p[291][0]) / 2,
        "mouth_y": (p[61][1] + p[291][1]) / 2,
    }


def detect(fm, img):
    h, w = img.shape[:2]
    r = fm.process(img)
    if not r.multi_face_landmarks:
        return None
    return np.array([[lm.x * w, lm.y * h] for lm in r.multi_face_landmarks[0].landmark])


def fmt(s):
    return ", ".join(f"{k} {v:7.2f}" for k, v in s.items())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("track_json", help="the landmark_error example's output")
    ap.add_argument("--release", action="append", default=[], help="NAME=track_NAME.jpg")
    ap.add_argument("--lmdb", help="folder of the release's LMDB of 512 crops")
    a = ap.parse_args()
    doc = json.load(open(a.track_json))
    release = dict(r.split("=", 1) for r in a.release)
    fm = mp.solutions.face_mesh.FaceMesh(static_image_mode=True, refine_landmarks=True, max_num_faces=1)
    ours_all = []
    with fm:
        for f in doc["frames"]:
            if "window" not in f:
                continue
            img = np.asarray(Image.open(f["path"]).convert("RGB"))
            p = detect(fm, img)
            if p is None:
                continue
            x0, y0, x1, y1 = f["window"]
            q = (p - [x0, y0]) * [CROP / (x1 - x0), CROP / (y1 - y0)]
            s = stats(q)
            ours_all.append(s)
            name = os.path.basename(f["path"])
            print(f"ours    {name}: {fmt(s)}")
            if name in release:
                grid = np.asarray(Image.open(release[name]).convert("RGB"))
                panel = np.ascontiguousarray(grid[2:514, 2:514])
                r = detect(fm, panel)
                if r is None:
                    print(f"release {name}: no face in the first panel")
                    continue
                t = stats(r)
                print(f"release {name}: {fmt(t)}")
                d = {k: s[k] - t[k] for k in s}
                print(f"ours - release, % of the crop: " + ", ".join(f"{k} {100 * v / CROP:+.2f}" for k, v in d.items()))
        if ours_all:
            med = {k: float(np.median([s[k] for s in ours_all])) for k in ours_all[0]}
            print(f"ours, median of {len(ours_all)}: {fmt(med)}")
        if a.lmdb:
            import lmdb

            env = lmdb.open(a.lmdb, readonly=True, lock=False)
            rows = []
            with env.begin() as txn:
                for _, v in txn.cursor():
                    img = np.asarray(Image.open(io.BytesIO(v)).convert("RGB"))
                    p = detect(fm, img)
                    if p is not None:
                        rows.append(stats(p * CROP / img.shape[0]))
            med_r = {k: float(np.median([s[k] for s in rows])) for k in rows[0]}
            print(f"release LMDB crops, median of {len(rows)}: {fmt(med_r)}")
            if ours_all:
                print("ours (median) - release LMDB (median), % of the crop: "
                      + ", ".join(f"{k} {100 * (med[k] - med_r[k]) / CROP:+.2f}" for k in med))
    return 0


if __name__ == "__main__":
    sys.exit(main())
