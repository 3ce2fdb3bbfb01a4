#!/usr/bin/env python3
"""Independent NumPy reference for the FLAME forward pass (GAGAVATAR.md section 9) and the
landmark / projection conventions, used to write the golden files of crates/flame/tests/golden.

Written from the spec (standard FLAME linear blend skinning with 4x4 rigid transforms, in
float64), not from the Rust code. It writes:

* flame_synth_golden.safetensors: inputs and expected outputs for the synthetic asset that
  `gagavatar flame synth --seed 0` writes (the asset itself, 27 MB, is not committed; the test
  regenerates it in-process and checks a fingerprint first).
* tiny_flame.pt: a small random asset (40 vertices) saved with torch.save as nested dicts, the
  release's container format, using int64 / int32 / float64 / strided tensors to exercise the
  reader; tiny_golden.safetensors: its expected outputs.

Usage (from the repository root):
    cargo run --release -p gagavatar -- flame synth -o /tmp/flame_synth.safetensors --seed 0
    python3 tools/reference/flame_reference.py --asset /tmp/flame_synth.safetensors \
        --out-dir crates/flame/tests/golden
"""

import argparse
import os

import numpy as np
import torch
from safetensors.numpy import load_file, save_file

SCALE = 5.0
EPS = 1e-8


def rodrigues(r):
    """[N,3] axis-angle -> [N,3,3]; angle = |r + 1e-8| as in the standard FLAME code."""
    angle = np.linalg.norm(r + EPS, axis=1, keepdims=True)
    d = r / angle
    c = np.cos(angle)[:, :, None]
    s = np.sin(angle)[:, :, None]
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    zero = np.zeros_like(x)
    k = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=1).reshape(-1, 3, 3)
    eye = np.eye(3)[None]
    return eye + s * k + (1.0 - c) * (k @ k)


def as_f32_f64(a):
    """The Rust loader keeps floats as f32; compute on exactly those values, in f64."""
    return np.asarray(a, dtype=np.float32).astype(np.float64)


class Flame:
    def __init__(self, t, n_shape_file, n_shape, n_exp):
        self.v_template = as_f32_f64(t["flame_model.v_template"])
        self.faces = np.asarray(t["flame_model.f"]).astype(np.int64)
        sd = as_f32_f64(t["flame_model.shapedirs"])
        self.shapedirs = np.concatenate(
            [sd[:, :, :n_shape], sd[:, :, n_shape_file:n_shape_file + n_exp]], axis=2)
        pd = as_f32_f64(t["flame_model.posedirs"])
        self.posedirs = pd.reshape(-1, pd.shape[-1]).T  # [36, V*3]
        self.j_regressor = as_f32_f64(t["flame_model.J_regressor"])
        self.weights = as_f32_f64(t["flame_model.weights"])
        parents = np.asarray(t["flame_model.kintree_table"])[0].astype(np.int64).copy()
        parents[0] = -1
        self.parents = parents
        g = lambda k: np.asarray(t["lmk_embeddings." + k])
        self.static_faces = g("static_lmk_faces_idx").astype(np.int64).reshape(-1)
        self.static_bary = as_f32_f64(g("static_lmk_bary_coords")).reshape(-1, 3)
        self.dyn_faces = g("dynamic_lmk_faces_idx").astype(np.int64)
        self.dyn_bary = as_f32_f64(g("dynamic_lmk_bary_coords"))
        # The release's FLAME reads the 70-point `_with_eye` pair (TRACKING.md section 4); a
        # plain `full_lmk_*` pair, when present, is not used.
        self.full_faces = g("full_lmk_faces_idx_with_eye").astype(np.int64).reshape(-1)
        self.full_bary = as_f32_f64(g("full_lmk_bary_coords_with_eye")).reshape(-1, 3)

    def forward(self, shape, exp, pose, eye):
        b = shape.shape[0]
        nv = self.v_template.shape[0]
        betas = np.concatenate([shape, exp], axis=1)
        v_shaped = self.v_template[None] + np.einsum("bl,vkl->bvk", betas, self.shapedirs)
        joints = np.einsum("jv,bvk->bjk", self.j_regressor, v_shaped)
        full_pose = np.concatenate([pose[:, :3], np.zeros((b, 3)), pose[:, 3:6], eye], axis=1)
        rot = rodrigues(full_pose.reshape(-1, 3)).reshape(b, -1, 3, 3)
        nj = rot.shape[1]
        pose_feature = (rot[:, 1:] - np.eye(3)).reshape(b, -1)
        v_posed = v_shaped + (pose_feature @ self.posedirs).reshape(b, nv, 3)

        rel_joints = joints.copy()
        rel_joints[:, 1:] -= joints[:, self.parents[1:]]
        tmat = np.zeros((b, nj, 4, 4))
        tmat[:, :, :3, :3] = rot
        tmat[:, :, :3, 3] = rel_joints
        tmat[:, :, 3, 3] = 1.0
        chain = [tmat[:, 0]]
        for i in range(1, nj):
            chain.append(chain[self.parents[i]] @ tmat[:, i])
        transforms = np.stack(chain, axis=1)
        posed_joints = transforms[:, :, :3, 3].copy()
        rel = transforms.copy()
        rel[:, :, :3, 3] -= np.einsum("bjik,bjk->bji", transforms[:, :, :3, :3], joints)
        t = np.einsum("vj,bjmn->bvmn", self.weights, rel)
        homog = np.concatenate([v_posed, np.ones((b, nv, 1))], axis=2)
        verts = np.einsum("bvmn,bvn->bvm", t[:, :, :3, :], homog)
        return verts * SCALE, posed_joints * SCALE, full_pose

    def dynamic_rows(self, full_pose):
        """Yaw of R_global R_neck, whole degrees (clamp max 39, round half-to-even), row index."""
        b = full_pose.shape[0]
        rows = []
        for i in range(b):
            rg = rodrigues(full_pose[i:i + 1, 0:3])[0]
            rn = rodrigues(full_pose[i:i + 1, 3:6])[0]
            r = rg @ rn
            sy = np.sqrt(r[0, 0] ** 2 + r[1, 0] ** 2)
            yaw = np.arctan2(-r[2, 0], sy)
            deg = int(np.round(min(yaw * 180.0 / np.pi, 39.0)))
            if deg >= 0:
                rows.append(deg)
            elif deg < -39:
                rows.append(78)
            else:
                rows.append(39 - deg)
        return np.array(rows, dtype=np.int64)

    def embed(self, verts, faces, bary):
        tri = verts[:, self.faces[faces]]  # [B, L, 3, 3]
        return np.einsum("blkc,lk->blc", tri, bary)

    def landmarks(self, verts, full_pose):
        rows = self.dynamic_rows(full_pose)
        out = []
        for i, r in enumerate(rows):
            f = np.concatenate([self.dyn_faces[r], self.static_faces])
            w = np.concatenate([self.dyn_bary[r], self.static_bary])
            out.append(self.embed(verts[i:i + 1], f, w)[0])
        full = self.embed(verts, self.full_faces, self.full_bary)
        return np.stack(out), full, rows


def project(points, tm, w, h):
    """PyTorch3D row convention p R + T, x/y flipped to the splatting convention, focal 12 NDC."""
    r = tm[:, :, :3]
    t = tm[:, :, 3]
    cam = np.einsum("bni,bij->bnj", points, r) + t[:, None, :]
    ndc_x = 12.0 * -cam[..., 0] / cam[..., 2]
    ndc_y = 12.0 * -cam[..., 1] / cam[..., 2]
    return np.stack([((ndc_x + 1.0) * w - 1.0) / 2.0, ((ndc_y + 1.0) * h - 1.0) / 2.0], axis=-1)


def camera(yaw, pitch, dist):
    """A release-style camera looking at the origin from +z (PyTorch3D R = rot_y(pi) ...)."""
    base = np.diag([-1.0, 1.0, -1.0])
    rot = rodrigues(np.array([[pitch, yaw, 0.0]]))[0] @ base
    return np.concatenate([rot, np.array([[0.0], [0.0], [dist]])], axis=1)


def synth_golden(asset_path, out_dir):
    t = load_file(asset_path)
    rng = np.random.default_rng(1234)
    b = 4
    shape = np.zeros((b, 300))
    exp = np.zeros((b, 100))
    pose = np.zeros((b, 6))
    eye = np.zeros((b, 6))
    shape[1:] = rng.normal(size=(3, 300)) * 0.8
    exp[1:] = rng.normal(size=(3, 100)) * 0.8
    pose[1] = [0.0, 0.0, 0.0, 0.25, 0.01, -0.02]
    pose[2] = [0.05, 0.35, 0.02, 0.1, 0.0, 0.0]  # yaw ~ +20 deg
    pose[3] = [-0.1, -0.55, 0.1, 0.3, -0.05, 0.03]  # yaw ~ -31 deg
    eye[1] = [0.1, 0.2, 0.0, 0.1, 0.2, 0.0]
    eye[2] = [-0.15, -0.1, 0.02, -0.15, -0.1, 0.02]
    eye[3] = [0.05, 0.3, 0.0, 0.02, 0.28, 0.0]
    # The Rust side receives f32 inputs; use their exact values here.
    shape, exp, pose, eye = (as_f32_f64(a) for a in (shape, exp, pose, eye))

    flame = Flame(t, 300, 300, 100)
    verts, joints, full_pose = flame.forward(shape, exp, pose, eye)
    lmk68, full, rows = flame.landmarks(verts, full_pose)
    tm = as_f32_f64(np.stack([camera(0.0, 0.0, 9.0), camera(0.2, -0.1, 9.5),
                              camera(-0.3, 0.05, 8.5), camera(0.1, 0.2, 10.0)]))
    pixels = project(lmk68, tm, 512, 512)

    reduced = Flame(t, 300, 100, 50)
    rverts, rjoints, _ = reduced.forward(shape[:2, :100], exp[:2, :50], pose[:2], eye[:2])

    sd = as_f32_f64(t["flame_model.shapedirs"])
    out = {
        "shape": shape, "expression": exp, "pose": pose, "eye": eye,
        "vertices": verts, "joints": joints, "lmk68": lmk68, "full": full,
        "dynamic_rows": rows, "transform": tm, "pixels68": pixels,
        "reduced.vertices": rverts, "reduced.joints": rjoints,
        # Fingerprint of the asset the golden was made from.
        "asset.v_template_sum": np.array([as_f32_f64(t["flame_model.v_template"]).sum()]),
        "asset.shapedirs_abs_sum": np.array([np.abs(sd).sum()]),
        "asset.posedirs_abs_sum": np.array([np.abs(as_f32_f64(t["flame_model.posedirs"])).sum()]),
    }
    out = {k: np.ascontiguousarray(v) for k, v in out.items()}
    path = os.path.join(out_dir, "flame_synth_golden.safetensors")
    save_file(out, path)
    print(f"wrote {path} ({os.path.getsize(path)} bytes); dynamic rows {rows.tolist()}")


def tiny_asset(rng):
    nv, nf, ns, ne = 40, 60, 6, 4
    v = rng.normal(size=(nv, 3)) * 0.05
    f = rng.integers(0, nv, size=(nf, 3))
    shapedirs = rng.normal(size=(nv, 3, ns + ne)) * 0.01
    posedirs = rng.normal(size=(nv, 3, 36)) * 0.01
    jr = rng.random(size=(5, nv)) ** 4
    jr /= jr.sum(axis=1, keepdims=True)
    w = rng.random(size=(nv, 5)) ** 3
    w /= w.sum(axis=1, keepdims=True)
    kintree = np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], dtype=np.int64)

    def bary(*shape, gen=None):
        b = (gen or rng).random(size=shape + (3,)) + 0.05
        return b / b.sum(axis=-1, keepdims=True)

    # Its own stream, so the draws of the other tensors (and of the golden inputs) stay as they
    # were before the `_with_eye` pair was added.
    eye_rng = np.random.default_rng(7070)
    eye_bary = lambda *shape: bary(*shape, gen=eye_rng)

    f32 = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float32))
    # posedirs saved as a strided (transposed) view, J_regressor as float64, one index table as
    # int32: the reader must handle all of these, not just contiguous f32/i64.
    posedirs_t = torch.from_numpy(np.ascontiguousarray(posedirs.astype(np.float32).transpose(2, 0, 1)))
    obj = {
        "flame_model": {
            "v_template": f32(v),
            "f": torch.from_numpy(f.astype(np.int64)),
            "shapedirs": f32(shapedirs),
            "posedirs": posedirs_t.permute(1, 2, 0),
            "J_regressor": torch.from_numpy(jr.astype(np.float32).astype(np.float64)),
            "weights": f32(w),
            "kintree_table": torch.from_numpy(kintree),
        },
        "lmk_embeddings": {
            "static_lmk_faces_idx": torch.from_numpy(rng.integers(0, nf, size=5).astype(np.int64)),
            "static_lmk_bary_coords": f32(bary(5)),
            "dynamic_lmk_faces_idx": torch.from_numpy(rng.integers(0, nf, size=(79, 3)).astype(np.int64)),
            "dynamic_lmk_bary_coords": f32(bary(79, 3)),
            # A plain pair the reader must skip (different values from the `_with_eye` pair).
            "full_lmk_faces_idx": torch.from_numpy(rng.integers(0, nf, size=(1, 7)).astype(np.int32)),
            "full_lmk_bary_coords": f32(bary(1, 7)),
            "full_lmk_faces_idx_with_eye": torch.from_numpy(
                eye_rng.integers(0, nf, size=(1, 7)).astype(np.int32)),
            "full_lmk_bary_coords_with_eye": f32(eye_bary(1, 7)),
        },
        "note": "tiny random FLAME-format asset for loader tests",
    }
    flat = {}
    for group, d in obj.items():
        if isinstance(d, dict):
            for k, val in d.items():
                flat[f"{group}.{k}"] = val.numpy()
    return obj, flat, ns, ne


def tiny_golden(out_dir):
    rng = np.random.default_rng(99)
    obj, flat, ns, ne = tiny_asset(rng)
    pt_path = os.path.join(out_dir, "tiny_flame.pt")
    torch.save(obj, pt_path)
    b = 3
    shape = as_f32_f64(rng.normal(size=(b, ns)))
    exp = as_f32_f64(rng.normal(size=(b, ne)))
    pose = as_f32_f64(rng.normal(size=(b, 6)) * 0.3)
    eye = as_f32_f64(rng.normal(size=(b, 6)) * 0.2)
    flame = Flame(flat, ns, ns, ne)
    verts, joints, full_pose = flame.forward(shape, exp, pose, eye)
    lmk68, full, rows = flame.landmarks(verts, full_pose)
    out = {"shape": shape, "expression": exp, "pose": pose, "eye": eye, "vertices": verts,
           "joints": joints, "lmk68": lmk68, "full": full, "dynamic_rows": rows}
    path = os.path.join(out_dir, "tiny_golden.safetensors")
    save_file({k: np.ascontiguousarray(v) for k, v in out.items()}, path)
    print(f"wrote {pt_path} ({os.path.getsize(pt_path)} bytes), {path}; rows {rows.tolist()}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--asset", required=True, help="synthetic asset from `gagavatar flame synth --seed 0`")
    ap.add_argument("--out-dir", default="crates/flame/tests/golden")
    args = ap.parse_args()
    os.makedirs(args.out_dir, exist_ok=True)
    synth_golden(args.asset, args.out_dir)
    tiny_golden(args.out_dir)


if __name__ == "__main__":
    main()
