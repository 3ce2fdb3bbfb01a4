#!/usr/bin/env python3
"""Independent reference for `gagavatar_train::lpips` (LPIPS v0.1, AlexNet variant).

Written from the definition, without the `lpips` package: inputs in [0, 1] -> `2 x - 1` ->
`(x - shift) / scale` with shift (-.030, -.088, -.188), scale (.458, .448, .450); AlexNet
features after the five ReLUs (conv 11/4/2, pool, conv 5/1/2, pool, conv 3/1/1 x 3; max-pools
3x3 stride 2); each feature map divided by `sqrt(sum_c f^2) + 1e-10`; squared difference;
1x1 convolution with `lin_k` (no bias); spatial mean; sum over the five layers.

Writes to `crates/train/tests/data/`:

- `lpips_weights.safetensors`: seeded weights under the `lpips` package's state-dict names
  (`net.slice1.0.weight` ... `net.slice5.10.bias`, `lin0.model.1.weight` ... `lin4.model.1.weight`,
  plus the `scaling_layer.shift/scale` buffers, which the Rust loader ignores). The channel
  widths are narrowed (16, 32, 48, 32, 32 instead of 64, 192, 384, 256, 256) to keep the file
  small; the computation is the same.
- `lpips.safetensors`: three 64x64 image pairs (`in0`, `in1`, float32; the last pair is
  identical), the distance per pair (`distance`, float64) and per layer (`layers`, [5, 3]).

Run from the repository root: `python3 tools/reference/lpips_reference.py --out
crates/train/tests/data`. Deterministic; needs torch 2.5.1, numpy 2.1.3 and safetensors.
"""

import argparse
import os

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import save_file

torch.set_num_threads(1)
torch.use_deterministic_algorithms(True)

SHIFT = [-0.030, -0.088, -0.188]
SCALE = [0.458, 0.448, 0.450]
EPS = 1e-10
# (state-dict prefix, kernel, stride, padding, max-pool before)
CONVS = [
    ("net.slice1.0", 11, 4, 2, False),
    ("net.slice2.3", 5, 1, 2, True),
    ("net.slice3.6", 3, 1, 1, True),
    ("net.slice4.8", 3, 1, 1, False),
    ("net.slice5.10", 3, 1, 1, False),
]
WIDTHS = [16, 32, 48, 32, 32]
SEED = 11


def save(tensors, path):
    """Writes atomically (temp sibling, then rename)."""
    tensors = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    tmp = os.path.join(os.path.dirname(path) or ".", "." + os.path.basename(path) + ".tmp")
    save_file(tensors, tmp)
    os.replace(tmp, path)
    print(f"wrote {path} ({os.path.getsize(path) / 1024:.1f} KiB, {len(tensors)} tensors)")


def make_weights(rng):
    """He-uniform conv weights, biases in [-0.1, 0.1), non-negative linear heads (as the
    trained ones are) in [0, 0.5); float32."""
    w = {}
    cin = 3
    for (name, k, _, _, _), cout in zip(CONVS, WIDTHS):
        bound = np.sqrt(6.0 / (cin * k * k))
        w[f"{name}.weight"] = rng.uniform(-bound, bound, (cout, cin, k, k))
        w[f"{name}.bias"] = rng.uniform(-0.1, 0.1, (cout,))
        cin = cout
    for i, c in enumerate(WIDTHS):
        w[f"lin{i}.model.1.weight"] = rng.uniform(0.0, 0.5, (1, c, 1, 1))
    w = {k: torch.from_numpy(v).float() for k, v in w.items()}
    w["scaling_layer.shift"] = torch.tensor(SHIFT).float().reshape(1, 3, 1, 1)
    w["scaling_layer.scale"] = torch.tensor(SCALE).float().reshape(1, 3, 1, 1)
    return w


def features(w, x):
    shift = torch.tensor(SHIFT, dtype=torch.float64).reshape(1, 3, 1, 1)
    scale = torch.tensor(SCALE, dtype=torch.float64).reshape(1, 3, 1, 1)
    h = ((2.0 * x - 1.0) - shift) / scale
    out = []
    for name, _, stride, pad, pool in CONVS:
        if pool:
            h = F.max_pool2d(h, 3, 2)
        h = F.conv2d(h, w[f"{name}.weight"].double(), w[f"{name}.bias"].double(), stride, pad)
        h = F.relu(h)
        out.append(h)
    return out


def unit(f):
    return f / (torch.sqrt((f * f).sum(dim=1, keepdim=True)) + EPS)


def lpips(w, a, b):
    """Per-layer distances [5, B] in float64."""
    layers = []
    for i, (fa, fb) in enumerate(zip(features(w, a), features(w, b))):
        d = (unit(fa) - unit(fb)) ** 2
        d = F.conv2d(d, w[f"lin{i}.model.1.weight"].double())
        layers.append(d.mean(dim=(2, 3)).reshape(-1))
    return torch.stack(layers)


def smooth_image(rng, b, h, w):
    """Images with structure (blurred noise plus a gradient), in [0, 1]."""
    x = torch.from_numpy(rng.random((b, 3, h, w)))
    k = torch.ones(3, 1, 5, 5, dtype=torch.float64) / 25.0
    blurred = F.conv2d(F.pad(x, (2, 2, 2, 2), mode="reflect"), k, groups=3)
    yy = torch.linspace(0, 1, h, dtype=torch.float64)[:, None]
    xx = torch.linspace(0, 1, w, dtype=torch.float64)[None, :]
    return (0.6 * blurred + 0.3 * (0.5 * yy + 0.5 * xx) + 0.1 * x).clamp(0, 1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="crates/train/tests/data")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    rng = np.random.default_rng(SEED)
    w = make_weights(rng)
    a = smooth_image(rng, 3, 64, 64)
    b = smooth_image(rng, 3, 64, 64)
    # Pair 1: a small perturbation (a near-zero distance); pair 2: identical images (exactly 0).
    b[1] = (a[1] + 0.03 * (b[1] - 0.5)).clamp(0, 1)
    b[2] = a[2]
    # Both sides see the float32 values the Rust test reads.
    a, b = a.float().double(), b.float().double()
    layers = lpips(w, a, b)
    dist = layers.sum(dim=0)
    print("distances", dist.tolist())
    save(w, os.path.join(args.out, "lpips_weights.safetensors"))
    save(
        {"in0": a.float(), "in1": b.float(), "distance": dist, "layers": layers},
        os.path.join(args.out, "lpips.safetensors"),
    )


if __name__ == "__main__":
    main()
