#!/usr/bin/env python3
"""MediaPipe reference for `crates/face`: writes the small golden files its tests compare to.

Pinned: mediapipe==0.10.21 (cp311 wheel, the last with the legacy face models and API),
numpy==1.26.4, opencv-contrib-python==4.11.0.86 (pulled by mediapipe), scikit-image==0.26.0
(test pictures). Run from the repository root:

    python3 tools/reference/face_reference.py goldens --out crates/face/tests/golden

What is written (everything from MediaPipe itself, nothing from this project's code):

  images/*.png      the test pictures: scikit-image's public-domain / CC0 photos and
                    deterministic transforms of them (scaled into larger canvases, rotated,
                    flipped, cropped, shrunk to small faces); their licences in images/README.md.
  crops/*.png       what MediaPipe's ImageToTensorCalculator feeds a model for a given image and
                    rotated rectangle (8-bit, before the value-range map), several rectangles
                    and both border modes.
  models.json       raw model outputs, computed by MediaPipe's InferenceCalculator (TFLite with
                    XNNPACK, as the solutions run them) on those crops: detector logits and the
                    regressors of the best anchors, the 478-point model's outputs, a 64x64
                    subsample of the selfie mask.
  pipeline.json     per test picture: FaceDetection (both models) detections, FaceMesh
                    (static_image_mode, refine_landmarks: 478 points) landmarks; the selfie masks
                    as masks/*.png (8-bit).
  video.json        FaceMesh in video (tracking) mode over a synthetic sequence (frames made from
                    the test pictures, written to video/*.png): landmarks per frame, and a frame
                    with no face that makes it re-detect.

Model inputs are the exact tensors MediaPipe builds: the reference builds small MediaPipe
graphs (ImageToTensorCalculator -> InferenceCalculator -> TensorsToFloatsCalculator) through the
mediapipe Python binding, so crops and raw outputs are MediaPipe's own.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import cv2
import numpy as np

import mediapipe as mp
from google.protobuf import text_format
from mediapipe.framework import calculator_pb2
from mediapipe.framework.formats import rect_pb2
from mediapipe.python import packet_creator, packet_getter
from mediapipe.python._framework_bindings import resource_util

MP_DIR = os.path.dirname(mp.__file__)
resource_util.set_resource_dir(os.path.dirname(MP_DIR))

# ----------------------------------------------------------------------------------------------
# MediaPipe graphs run from Python.


def run_graph(cfg_text: str, inputs: dict, outputs: list[str], side=None):
    """Runs a one-shot graph; `inputs` maps stream names to packets; returns the first packet
    value of each output stream (as float lists)."""
    cfg = text_format.Parse(cfg_text, calculator_pb2.CalculatorGraphConfig())
    g = mp.CalculatorGraph(graph_config=cfg)
    got = {name: [] for name in outputs}
    for name in outputs:
        g.observe_output_stream(name, lambda s, p, n=name: got[n].append(np.array(packet_getter.get_float_list(p), np.float32)))
    g.start_run(side or {})
    for name, packet in inputs.items():
        g.add_packet_to_input_stream(name, packet.at(0))
    g.close()
    return {k: (v[0] if v else None) for k, v in got.items()}


def image_packet(img: np.ndarray):
    return packet_creator.create_image_frame(image_format=mp.ImageFormat.SRGB, data=np.ascontiguousarray(img))


def rect_packet(r: dict):
    return packet_creator.create_proto(
        rect_pb2.NormalizedRect(
            x_center=r["cx"], y_center=r["cy"], width=r["w"], height=r["h"], rotation=r["rotation"]
        )
    )


def image_to_tensor_node(size, lo, hi, border, keep_aspect, out="tensors"):
    b = {"zero": "BORDER_ZERO", "replicate": "BORDER_REPLICATE"}[border]
    return f"""
node {{
  calculator: "ImageToTensorCalculator"
  input_stream: "IMAGE:image"
  input_stream: "NORM_RECT:roi"
  output_stream: "TENSORS:{out}"
  options: {{ [mediapipe.ImageToTensorCalculatorOptions.ext] {{
      output_tensor_width: {size[0]} output_tensor_height: {size[1]}
      keep_aspect_ratio: {str(keep_aspect).lower()}
      output_tensor_float_range {{ min: {lo} max: {hi} }}
      border_mode: {b} }} }}
}}"""


def mp_crop(img, roi, size, border):
    """MediaPipe's 8-bit crop of `roi` (normalised rect) of `img`."""
    cfg = (
        'input_stream: "image" input_stream: "roi" output_stream: "floats"'
        + image_to_tensor_node(size, 0.0, 1.0, border, False)
        + """
node { calculator: "TensorsToFloatsCalculator" input_stream: "TENSORS:tensors" output_stream: "FLOATS:floats" }"""
    )
    out = run_graph(cfg, {"image": image_packet(img), "roi": rect_packet(roi)}, ["floats"])["floats"]
    v = np.round(out * 255.0)
    assert np.abs(out * 255.0 - v).max() < 1e-3, "crop is not 8-bit"
    return v.astype(np.uint8).reshape(size[1], size[0], 3)


def mp_model(img, roi, size, lo, hi, border, keep_aspect, model_path, n_outputs):
    """Raw outputs of a model on MediaPipe's own input tensor (the custom-op resolver loaded
    as FaceMesh and SelfieSegmentation load it)."""
    splits = "".join(f" ranges: {{ begin: {i} end: {i + 1} }}" for i in range(n_outputs))
    outs = "".join(f' output_stream: "t{i}"' for i in range(n_outputs))
    floats = "".join(
        f'node {{ calculator: "TensorsToFloatsCalculator" input_stream: "TENSORS:t{i}" output_stream: "FLOATS:f{i}" }}\n'
        for i in range(n_outputs)
    )
    cfg = (
        'input_stream: "image" input_stream: "roi"'
        + "".join(f' output_stream: "f{i}"' for i in range(n_outputs))
        + image_to_tensor_node(size, lo, hi, border, keep_aspect, out="input_tensors")
        + f"""
node {{ calculator: "TfLiteCustomOpResolverCalculator" output_side_packet: "OP_RESOLVER:op_resolver" }}
node {{
  calculator: "InferenceCalculator"
  input_stream: "TENSORS:input_tensors"
  output_stream: "TENSORS:output_tensors"
  input_side_packet: "OP_RESOLVER:op_resolver"
  options: {{ [mediapipe.InferenceCalculatorOptions.ext] {{ model_path: "{model_path}" delegate {{ xnnpack {{}} }} }} }}
}}
node {{
  calculator: "SplitTensorVectorCalculator"
  input_stream: "output_tensors"{outs}
  options: {{ [mediapipe.SplitVectorCalculatorOptions.ext] {{{splits} }} }}
}}
{floats}"""
    )
    got = run_graph(cfg, {"image": image_packet(img), "roi": rect_packet(roi)}, [f"f{i}" for i in range(n_outputs)])
    return [got[f"f{i}"] for i in range(n_outputs)]


# ----------------------------------------------------------------------------------------------
# Test pictures.


def skimage_pictures():
    import skimage.data as d

    return {
        "astronaut": d.astronaut(),
        "camera": cv2.cvtColor(d.camera(), cv2.COLOR_GRAY2RGB),
        "chelsea": d.chelsea(),
        "coffee": d.coffee(),
        "rocket": d.rocket(),
    }


def canvas(img, cw, ch, x, y, scale, fill=(40, 60, 80)):
    """`img` scaled by `scale` (area) and pasted with its top-left at (x, y) on a plain canvas."""
    h, w = img.shape[:2]
    small = cv2.resize(img, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    out = np.empty((ch, cw, 3), np.uint8)
    out[:] = fill
    sh, sw = small.shape[:2]
    x0, y0 = max(x, 0), max(y, 0)
    x1, y1 = min(x + sw, cw), min(y + sh, ch)
    out[y0:y1, x0:x1] = small[y0 - y : y1 - y, x0 - x : x1 - x]
    return out


def rotate(img, degrees, scale=1.0):
    h, w = img.shape[:2]
    m = cv2.getRotationMatrix2D((w / 2, h / 2), degrees, scale)
    return cv2.warpAffine(img, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def test_pictures():
    """(name, picture, licence note) of every test picture, deterministic."""
    s = skimage_pictures()
    a = s["astronaut"]
    nasa = "NASA (Eileen Collins), public domain (scikit-image `astronaut`); transformed by the script"
    out = [
        ("astronaut_384", cv2.resize(a, (384, 384), interpolation=cv2.INTER_AREA), nasa),
        ("astronaut_tilt20", rotate(cv2.resize(a, (320, 320), interpolation=cv2.INTER_AREA), 20), nasa),
        ("astronaut_tilt_minus35", rotate(cv2.resize(a, (320, 320), interpolation=cv2.INTER_AREA), -35), nasa),
        ("astronaut_flip", cv2.flip(cv2.resize(a, (300, 300), interpolation=cv2.INTER_AREA), 1), nasa),
        ("astronaut_face_crop", cv2.resize(a[40:300, 120:330], (210, 260), interpolation=cv2.INTER_AREA), nasa),
        ("astronaut_small_in_wide", canvas(a, 480, 270, 300, 60, 0.3), nasa),
        ("astronaut_tiny_in_tall", canvas(a, 240, 400, 20, 200, 0.22), nasa),
        ("astronaut_landscape_offcentre", canvas(a, 448, 256, -40, -30, 0.62), nasa),
        ("camera", cv2.resize(s["camera"], (256, 256), interpolation=cv2.INTER_AREA), "Lav Varshney, CC0 (scikit-image `camera`)"),
        ("chelsea_cat", cv2.resize(s["chelsea"], (300, 225), interpolation=cv2.INTER_AREA), "Stefan van der Walt, CC0 (scikit-image `chelsea`)"),
        ("coffee", cv2.resize(s["coffee"], (300, 200), interpolation=cv2.INTER_AREA), "Rachel Michetti, CC0 (scikit-image `coffee`)"),
        ("rocket", cv2.resize(s["rocket"], (214, 142), interpolation=cv2.INTER_AREA), "SpaceX, released into the public domain (scikit-image `rocket`)"),
        ("flat_grey", np.full((64, 96, 3), 128, np.uint8), "generated by the script (no content)"),
    ]
    return out


# ----------------------------------------------------------------------------------------------
# Goldens.


def write_png(path, rgb):
    ok = cv2.imwrite(path, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert ok, path


def read_png(path):
    return cv2.cvtColor(cv2.imread(path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def r6(v):
    return [float(f"{x:.7g}") for x in np.asarray(v, np.float64).reshape(-1)]


WHOLE = {"cx": 0.5, "cy": 0.5, "w": 1.0, "h": 1.0, "rotation": 0.0}
ASTRO_FACE = {"cx": 0.43, "cy": 0.26, "w": 0.3, "h": 0.3, "rotation": 0.12}


def crops_goldens(out, pics):
    """MediaPipe crops: name -> (picture, rect, size, border)."""
    os.makedirs(os.path.join(out, "crops"), exist_ok=True)
    cases = [
        ("letterbox_wide_128", "astronaut_small_in_wide", WHOLE, (128, 128), "zero", True),
        ("letterbox_tall_192", "astronaut_tiny_in_tall", WHOLE, (192, 192), "zero", True),
        ("face_rotated_192", "astronaut_384", ASTRO_FACE, (192, 192), "replicate", False),
        ("face_outside_192", "astronaut_face_crop", {"cx": 0.1, "cy": 0.9, "w": 0.9, "h": 0.7, "rotation": -0.6}, (192, 192), "replicate", False),
        ("selfie_256", "astronaut_landscape_offcentre", WHOLE, (256, 256), "zero", False),
        ("zero_rotated_64", "camera", {"cx": 0.6, "cy": 0.4, "w": 1.3, "h": 0.9, "rotation": 2.5}, (64, 48), "zero", False),
    ]
    meta = []
    for name, pic, roi, size, border, keep in cases:
        img = pics[pic]
        roi = dict(roi)
        if keep:
            # What PadRoi does for the letterbox: the rect widened to the tensor's aspect.
            h, w = img.shape[:2]
            side = max(w, h)
            roi["w"], roi["h"] = side / w, side / h
        crop = mp_crop(img, roi, size, border)
        write_png(os.path.join(out, "crops", f"{name}.png"), crop)
        meta.append({"name": name, "image": pic, "roi": roi, "width": size[0], "height": size[1], "border": border})
    return meta


def model_goldens(pics):
    a = pics["astronaut_384"]
    res = {}
    # Short range on the letterboxed picture.
    logits_reg = mp_model(
        a, WHOLE, (128, 128), -1.0, 1.0, "zero", True, "mediapipe/modules/face_detection/face_detection_short_range.tflite", 2
    )
    res["short_range"] = detector_golden(pics["astronaut_384"], "astronaut_384", logits_reg, 896)
    logits_reg = mp_model(
        a, WHOLE, (192, 192), -1.0, 1.0, "zero", True, "mediapipe/modules/face_detection/face_detection_full_range_sparse.tflite", 2
    )
    res["full_range"] = detector_golden(pics["astronaut_384"], "astronaut_384", logits_reg, 2304)
    outs = mp_model(
        a, ASTRO_FACE, (192, 192), 0.0, 1.0, "replicate", False, "mediapipe/modules/face_landmark/face_landmark_with_attention.tflite", 7
    )
    names = ["mesh", "lips", "left_eye", "right_eye", "left_iris", "right_iris", "face_flag"]
    res["landmarks"] = {
        "image": "astronaut_384",
        "roi": ASTRO_FACE,
        "outputs": {n: r6(o) for n, o in zip(names, outs)},
    }
    pic = "astronaut_landscape_offcentre"
    (mask,) = mp_model(
        pics[pic], WHOLE, (256, 256), 0.0, 1.0, "zero", False, "mediapipe/modules/selfie_segmentation/selfie_segmentation.tflite", 1
    )
    mask = mask.reshape(256, 256)
    res["selfie"] = {"image": pic, "stride": 4, "mask": r6(mask[::4, ::4])}
    return res


def detector_golden(img, name, outs, n):
    # Output order: regressors (16 per anchor) then classificators.
    reg, cls = (outs[0], outs[1]) if outs[0].size == n * 16 else (outs[1], outs[0])
    reg = reg.reshape(n, 16)
    best = [int(i) for i in np.argsort(-cls)[:24]]
    return {
        "image": name,
        "logits": r6(cls),
        "best_anchors": best,
        "best_regressors": [r6(reg[i]) for i in best],
    }


def detections_json(res):
    out = []
    for d in res.detections or []:
        b = d.location_data.relative_bounding_box
        out.append(
            {
                "score": float(d.score[0]),
                "box": [b.xmin, b.ymin, b.width, b.height],
                "keypoints": [[k.x, k.y] for k in d.location_data.relative_keypoints],
            }
        )
    return out


def landmarks_json(res):
    return [[[p.x, p.y, p.z] for p in f.landmark] for f in (res.multi_face_landmarks or [])]


MAX_FACES = 4


def pipeline_goldens(out, pics):
    os.makedirs(os.path.join(out, "masks"), exist_ok=True)
    fd0 = mp.solutions.face_detection.FaceDetection(model_selection=0, min_detection_confidence=0.5)
    fd1 = mp.solutions.face_detection.FaceDetection(model_selection=1, min_detection_confidence=0.5)
    fm = mp.solutions.face_mesh.FaceMesh(
        static_image_mode=True, max_num_faces=MAX_FACES, refine_landmarks=True, min_detection_confidence=0.5
    )
    seg = mp.solutions.selfie_segmentation.SelfieSegmentation(model_selection=0)
    res = {"max_faces": MAX_FACES, "pictures": {}}
    for name, img in pics.items():
        entry = {
            "width": img.shape[1],
            "height": img.shape[0],
            "short_range": detections_json(fd0.process(img)),
            "full_range": detections_json(fd1.process(img)),
            "mesh": landmarks_json(fm.process(img)),
        }
        mask = seg.process(img).segmentation_mask
        m8 = np.clip(np.round(mask * 255.0), 0, 255).astype(np.uint8)
        cv2.imwrite(os.path.join(out, "masks", f"{name}.png"), m8, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        entry["mask_mean"] = float(mask.mean())
        res["pictures"][name] = entry
        print(name, len(entry["short_range"]), len(entry["full_range"]), len(entry["mesh"]))
    return res


def video_goldens(out, pics):
    """A synthetic clip: crops of a test picture along a smooth path (MediaPipe's own crops,
    which the Rust side reproduces bit for bit), with two black frames that make the tracker
    lose the face and detect again."""
    base = "astronaut_384"
    img = pics[base]
    size = (224, 224)
    rects = []
    for t in range(14):
        if t in (8, 9):
            rects.append({"cx": 3.0, "cy": 3.0, "w": 0.5, "h": 0.5, "rotation": 0.0})
            continue
        a = t / 13.0
        rects.append(
            {
                "cx": 0.45 + 0.03 * np.sin(2.1 * a * np.pi),
                "cy": 0.33 + 0.02 * np.cos(1.7 * a * np.pi),
                "w": 0.62 - 0.08 * a,
                "h": 0.62 - 0.08 * a,
                "rotation": 0.25 * np.sin(1.3 * a * np.pi),
            }
        )
    rects = [{k: float(np.float32(v)) for k, v in r.items()} for r in rects]
    frames = [mp_crop(img, r, size, "zero") for r in rects]
    fm = mp.solutions.face_mesh.FaceMesh(static_image_mode=False, max_num_faces=1, refine_landmarks=True)
    lms = []
    for f in frames:
        got = landmarks_json(fm.process(f))
        lms.append(got[0] if got else None)
    print("video: faces in", sum(x is not None for x in lms), "of", len(lms), "frames")
    return {"image": base, "width": size[0], "height": size[1], "rects": rects, "landmarks": lms}


def parity(frames_dir, rust_dir):
    """Runs MediaPipe over the frames the Rust example `parity_frames` processed and prints how
    far apart the two are (the issue's parity measures)."""
    rust = json.load(open(os.path.join(rust_dir, "rust.json")))["frames"]
    fd0 = mp.solutions.face_detection.FaceDetection(model_selection=0)
    fd1 = mp.solutions.face_detection.FaceDetection(model_selection=1)
    photo = mp.solutions.face_mesh.FaceMesh(static_image_mode=True, max_num_faces=MAX_FACES, refine_landmarks=True)
    video = mp.solutions.face_mesh.FaceMesh(static_image_mode=False, max_num_faces=1, refine_landmarks=True)
    seg = mp.solutions.selfie_segmentation.SelfieSegmentation(model_selection=0)
    stats = {k: [] for k in ("box", "kp", "score", "lm_static", "lm_video", "iou", "mad")}
    found = {"detect": [0, 0], "mesh": [0, 0], "video": [0, 0]}
    for fr in rust:
        matches = [f for f in sorted(os.listdir(frames_dir)) if os.path.splitext(f)[0] == fr["name"]]
        img = read_png(os.path.join(frames_dir, matches[0]))
        h, w = img.shape[:2]
        for key, fd in (("short_range", fd0), ("full_range", fd1)):
            want = detections_json(fd.process(img))
            got = fr[key]
            found["detect"][0] += len(want) == len(got)
            found["detect"][1] += 1
            for a, b in zip(got, want):
                stats["score"].append(abs(a["score"] - b["score"]))
                stats["box"].append(np.abs(np.array(a["box"]) - np.array(b["box"])).max())
                stats["kp"].append(np.abs(np.array(a["keypoints"]) - np.array(b["keypoints"])).max())
        for key, sol, name in (("mesh", photo, "lm_static"), ("tracked", video, "lm_video")):
            want = landmarks_json(sol.process(img))
            got = fr[key]
            if key == "tracked":
                got = [] if got is None else [got]
                want = want[:1]
            fk = "mesh" if key == "mesh" else "video"
            found[fk][0] += len(want) == len(got)
            found[fk][1] += 1
            for a, b in zip(got, want):
                a, b = np.array(a)[:, :2] * [w, h], np.array(b)[:, :2] * [w, h]
                side = (b.max(0) - b.min(0)).max()
                stats[name].append(np.linalg.norm(a - b, axis=1).mean() / side)
        mask = seg.process(img).segmentation_mask
        mine = cv2.imread(os.path.join(rust_dir, "mattes", fr["name"] + ".png"), cv2.IMREAD_UNCHANGED) / 65535.0
        inter = np.logical_and(mask >= 0.5, mine >= 0.5).sum()
        union = np.logical_or(mask >= 0.5, mine >= 0.5).sum()
        stats["iou"].append(1.0 if union == 0 else inter / union)
        stats["mad"].append(np.abs(mask - mine).mean())
    n = len(rust)
    print(f"{n} frames")
    for k, (same, total) in found.items():
        print(f"  {k}: same face count in {same} of {total} comparisons")
    for k, v in stats.items():
        if v:
            v = np.array(v)
            print(f"  {k}: mean {v.mean():.3g}, worst {v.max() if k not in ('iou',) else v.min():.3g} ({len(v)} values)")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("goldens")
    g.add_argument("--out", required=True)
    pa = sub.add_parser("parity", help="compare with the output of the Rust example parity_frames")
    pa.add_argument("--frames", required=True)
    pa.add_argument("--rust", required=True, help="OUT_DIR of parity_frames")
    args = ap.parse_args()
    assert mp.__version__ == "0.10.21", mp.__version__
    assert np.__version__ == "1.26.4", np.__version__
    if args.cmd == "parity":
        parity(args.frames, args.rust)
        return
    out = args.out
    os.makedirs(os.path.join(out, "images"), exist_ok=True)
    pics = {}
    rows = []
    for name, img, note in test_pictures():
        path = os.path.join(out, "images", f"{name}.png")
        write_png(path, img)
        pics[name] = read_png(path)
        assert np.array_equal(pics[name], img)
        rows.append((name, img.shape[1], img.shape[0], note))
    with open(os.path.join(out, "images", "README.md"), "w") as f:
        f.write(
            "# Test pictures\n\nWritten by `tools/reference/face_reference.py` from the photos shipped with "
            "scikit-image 0.26.0 (`skimage.data`; their docstrings state the licences below), resized or "
            "transformed by the script.\n\n| file | size | source and licence |\n|---|---|---|\n"
        )
        for name, w, h, note in rows:
            f.write(f"| `{name}.png` | {w}x{h} | {note} |\n")
    crops = crops_goldens(out, pics)
    models = model_goldens(pics)
    with open(os.path.join(out, "models.json"), "w") as f:
        json.dump({"crops": crops, "models": models}, f)
    with open(os.path.join(out, "pipeline.json"), "w") as f:
        json.dump(pipeline_goldens(out, pics), f)
    with open(os.path.join(out, "video.json"), "w") as f:
        json.dump(video_goldens(out, pics), f)
    print("wrote", out)


if __name__ == "__main__":
    main()
