#!/usr/bin/env python3
"""Times MediaPipe 0.10.21's Python face solutions on a folder of frames, as
`gagavatar bench face FRAMES` times the Rust crate, for a side-by-side comparison.

    taskset -c 0,1 python3 tools/reference/bench_mediapipe_face.py FRAMES --runs 3

Measured per frame (each frame read beforehand; the first pass is a warm-up; medians over the
other passes), matching the rows of `gagavatar bench face`:
  tracking frame  FaceMesh(static_image_mode=False, max_num_faces=1, refine_landmarks=True)
  short range     FaceDetection(model_selection=0)
  full range      FaceDetection(model_selection=1)
  photo           FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=True)
  matte           SelfieSegmentation(model_selection=0): sampling, network and the mask resized
                  back to the frame size (the Rust row "matte at frame size")

Threads: MediaPipe's Python API has no thread setting; its TFLite/XNNPACK inference picks the
thread count from the CPUs it may use, so run it pinned to the same number of cores as
`gagavatar bench face --threads N` (`taskset -c 0,1` for 2).

Pinned: mediapipe==0.10.21, numpy==1.26.4, opencv-contrib-python==4.11.0.86.
"""

from __future__ import annotations

import argparse
import glob
import os
import time

import cv2
import numpy as np

import mediapipe as mp


def frames_from(paths, limit):
    files = []
    for p in paths:
        if os.path.isdir(p):
            files += sorted(f for f in glob.glob(os.path.join(p, "*")) if os.path.isfile(f))
        else:
            files.append(p)
    files = files[:limit]
    return [cv2.cvtColor(cv2.imread(f, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB) for f in files]


def measure(frames, runs, fn):
    times = []
    for run in range(runs):
        for f in frames:
            f = f.copy()
            t = time.perf_counter()
            fn(f)
            dt = (time.perf_counter() - t) * 1e3
            if run > 0:
                times.append(dt)
    return float(np.median(times)), float(np.min(times))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("frames", nargs="+")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--max-frames", type=int, default=120)
    args = ap.parse_args()
    frames = frames_from(args.frames, args.max_frames)
    runs = max(args.runs, 2)
    h, w = frames[0].shape[:2]
    cores = len(os.sched_getaffinity(0))
    sol = mp.solutions
    video = sol.face_mesh.FaceMesh(static_image_mode=False, max_num_faces=1, refine_landmarks=True)
    fd0 = sol.face_detection.FaceDetection(model_selection=0)
    fd1 = sol.face_detection.FaceDetection(model_selection=1)
    photo = sol.face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=True)
    seg = sol.selfie_segmentation.SelfieSegmentation(model_selection=0)
    rows = [
        ("tracking frame (FaceMesh video mode, refine_landmarks)", video.process),
        ("detection, short range (FaceDetection 0)", fd0.process),
        ("detection, full range (FaceDetection 1)", fd1.process),
        ("photo: FaceMesh static mode, refine_landmarks", photo.process),
        ("matte (SelfieSegmentation 0, mask resized to the frame)", seg.process),
    ]
    print(f"mediapipe {mp.__version__}, {len(frames)} frames of {w}x{h}, {cores} cores allowed, {runs - 1} timed passes:")
    for name, fn in rows:
        m, lo = measure(frames, runs, fn)
        print(f"  {name}: median {m:.2f} ms (min {lo:.2f})")


if __name__ == "__main__":
    main()
