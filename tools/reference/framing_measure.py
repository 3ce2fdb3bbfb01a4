#!/usr/bin/env python3
"""Measures how faces are framed in the release's 512 training crops, for the head-box
calibration of `crates/track/src/crop.rs` (`FramingCalibration`).

Runs MediaPipe Face Mesh (refine_landmarks=True: 478 points with irises) on every image of an
LMDB of release crops and prints medians of:
* the iris midpoint (points 468, 473), in crop pixels (the spec's table, TRACKING.md section 2);
* the 468-point mesh's axis-aligned height (the spec's table) and its extent along the face's
  up axis (perpendicular to the iris line; what the tracker measures, so tilted heads are
  framed like upright ones);
* the inter-iris distance;
* the iris midpoint in the face's frame: its offset from the crop centre turned by minus the
  iris line's angle, plus the centre (what the tracker places).

Usage (the release tracker's demo LMDB of 40 VFHQ crops):
    python3 tools/reference/framing_measure.py /work/demos/vfhq_demo

Measured with mediapipe 0.10.21, lmdb 1.5.1, numpy 1.26.4, Pillow 11.0.0 (40 of 40 crops):
    iris midpoint median (255.56, 199.03); axis-aligned mesh height 277.22; along the up axis
    273.64; inter-iris 92.65; iris midpoint in the face frame (259.94, 200.04).
The first three reproduce the spec's table.
"""

import io
import sys

import lmdb
import mediapipe as mp
import numpy as np
from PIL import Image


def main():
    if len(sys.argv) != 2:
        print(__doc__)
        return 2
    env = lmdb.open(sys.argv[1], readonly=True, lock=False)
    rows = []
    mesh = mp.solutions.face_mesh.FaceMesh(static_image_mode=True, refine_landmarks=True, max_num_faces=1)
    with env.begin() as txn, mesh as fm:
        total = 0
        for _, v in txn.cursor():
            total += 1
            img = np.asarray(Image.open(io.BytesIO(v)).convert("RGB"))
            h, w = img.shape[:2]
            r = fm.process(img)
            if not r.multi_face_landmarks:
                continue
            p = np.array([[lm.x * w, lm.y * h] for lm in r.multi_face_landmarks[0].landmark])
            e0, e1 = p[468], p[473]
            d = (e1 - e0) / np.linalg.norm(e1 - e0)
            down = np.array([-d[1], d[0]])
            t = p[:468] @ down
            centre = np.array([w / 2, h / 2])
            c = (e0 + e1) / 2 - centre
            rows.append({
                "eye": (e0 + e1) / 2,
                "height": p[:468, 1].max() - p[:468, 1].min(),
                "height_up": t.max() - t.min(),
                "iris": np.linalg.norm(e1 - e0),
                "eye_face": np.array([c @ d, c @ down]) + centre,
            })
    med = lambda k: np.median(np.array([r[k] for r in rows]), axis=0)
    print(f"{len(rows)} of {total} crops with a face")
    print("iris midpoint median", med("eye"))
    print("mesh height: axis-aligned", med("height"), "along the up axis", med("height_up"))
    print("inter-iris", med("iris"))
    print("iris midpoint in the face frame", med("eye_face"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
