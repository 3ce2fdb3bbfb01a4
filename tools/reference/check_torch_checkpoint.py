"""Checks that a torch checkpoint written by `gagavatar convert ... out.pt` loads in torch the way
the release code loads GAGAvatar.pt, and holds exactly the values of a safetensors file.

    python3 tools/reference/check_torch_checkpoint.py OUT.pt WEIGHTS.safetensors

Pinned: torch 2.5.1, numpy 2.1.3. Loads with weights_only=True (the restricted unpickler) and
weights_only=False (the release code's plain torch.load), and with mmap=True (needs the 64-byte
storage alignment). Exits non-zero on any difference.
"""

import json
import struct
import sys

import numpy as np
import torch


def read_safetensors(path):
    # Parsed by hand so the check does not depend on the safetensors package.
    with open(path, "rb") as f:
        n = struct.unpack("<Q", f.read(8))[0]
        header = json.loads(f.read(n))
        body = f.read()
    meta = header.pop("__metadata__", {}) or {}
    dtypes = {"F32": "<f4", "F64": "<f8", "F16": "<f2"}
    out = {}
    for k, v in header.items():
        a, b = v["data_offsets"]
        out[k] = np.frombuffer(body[a:b], dtype=dtypes[v["dtype"]]).reshape(v["shape"])
    return out, meta


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    pt, st = sys.argv[1], sys.argv[2]
    ref, meta = read_safetensors(st)
    failures = 0
    for label, kwargs in [
        ("weights_only=True", dict(weights_only=True)),
        ("weights_only=False", dict(weights_only=False)),
        ("weights_only=True, mmap=True", dict(weights_only=True, mmap=True)),
    ]:
        ckpt = torch.load(pt, map_location="cpu", **kwargs)
        model, cfg = ckpt["model"], ckpt["meta_cfg"]
        worst = 0.0
        bad = []
        missing = sorted(set(ref) - set(model))
        extra = sorted(set(model) - set(ref))
        for k, want in ref.items():
            if k not in model:
                continue
            got = model[k]
            if got.dtype != torch.float32 or tuple(got.shape) != want.shape:
                bad.append(f"{k}: {got.dtype} {tuple(got.shape)} vs {want.shape}")
                continue
            g = got.numpy()
            w = want.astype(np.float32)
            # Bit equality, so NaN and -0.0 count too.
            if not np.array_equal(g.view(np.uint32), w.view(np.uint32)):
                bad.append(k)
            with np.errstate(invalid="ignore"):
                d = np.abs(g.astype(np.float64) - w.astype(np.float64))
            d = d[np.isfinite(d)]
            if d.size:
                worst = max(worst, float(d.max()))
        print(
            f"{label}: {type(ckpt).__name__} keys {sorted(ckpt)}; model is {type(model).__name__} "
            f"of {len(model)} tensors; meta_cfg is {type(cfg).__name__}"
            + (f" (name={cfg.get('name')!r}, {len(cfg)} fields)" if isinstance(cfg, dict) else "")
            + f"; max abs diff {worst}; {len(bad)} differing, {len(missing)} missing, "
            f"{len(extra)} extra"
        )
        for line in (bad + [f"missing {k}" for k in missing] + [f"extra {k}" for k in extra])[:10]:
            print("   ", line)
        stored = meta.get("gagavatar.config")
        if stored is not None and cfg != json.loads(stored):
            print("    meta_cfg differs from the safetensors' gagavatar.config")
            failures += 1
        failures += len(bad) + len(missing) + len(extra)
    if failures:
        sys.exit(f"FAIL: {failures} problems")
    print("OK")


if __name__ == "__main__":
    main()
