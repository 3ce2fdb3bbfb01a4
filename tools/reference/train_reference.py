#!/usr/bin/env python3
"""Independent reference for the training building blocks of `crates/train` (spec section 11).

Writes small golden files to `crates/train/tests/data/`:

- `metrics.safetensors`: PSNR and SSIM (11x11 Gaussian, sigma 1.5, valid windows) per image,
  per channel and on luma.
- `head_box.safetensors`: integer head boxes of many bboxes (float32 arithmetic in PyTorch's
  order) and antialiased crop-resizes.
- `perceptual.safetensors`: the AlexNet + VGG-Face perceptual distance with seeded weights
  (SplitMix64 stream shared with `gagavatar_train::perceptual::seeded_weights`), features, the
  ten layer terms and the input gradient, in float64.
- `adam.safetensors`: parameters after each step of `torch.optim.Adam` (betas (0, 0.99)) with
  the release's groups and `LinearLR` decay, float32.
- `losses.safetensors`: every loss term and the gradients of the total, float64.

Run from the repository root: `python3 tools/reference/train_reference.py --out
crates/train/tests/data`. Deterministic; needs only torch, numpy and safetensors (pinned in
requirements.txt). With torchmetrics installed it also cross-checks PSNR/SSIM against it.
"""

import argparse
import math
import os

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import save_file

torch.set_num_threads(1)
torch.use_deterministic_algorithms(True)

# ----------------------------------------------------------------------------------------------
# I/O


def save(tensors, path):
    """Writes atomically (temp sibling, then rename)."""
    tensors = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    tmp = os.path.join(os.path.dirname(path) or ".", "." + os.path.basename(path) + ".tmp")
    save_file(tensors, tmp)
    os.replace(tmp, path)
    size = os.path.getsize(path)
    print(f"wrote {path} ({size / 1024:.1f} KiB, {len(tensors)} tensors)")


def smooth_image(rng, b, c, h, w):
    """Random images with structure (sum of blurred noise and gradients), in [0, 1]."""
    x = torch.from_numpy(rng.random((b, c, h, w))).double()
    k = torch.ones(c, 1, 5, 5, dtype=torch.float64) / 25.0
    blurred = F.conv2d(F.pad(x, (2, 2, 2, 2), mode="reflect"), k, groups=c)
    yy = torch.linspace(0, 1, h, dtype=torch.float64)[:, None]
    xx = torch.linspace(0, 1, w, dtype=torch.float64)[None, :]
    grad = (0.5 * yy + 0.5 * xx)[None, None]
    out = 0.6 * blurred + 0.3 * grad + 0.1 * x
    return out.clamp(0, 1)


# ----------------------------------------------------------------------------------------------
# Metrics


def gaussian_1d(size=11, sigma=1.5):
    d = torch.arange(size, dtype=torch.float64) - (size // 2)
    g = torch.exp(-0.5 * (d / sigma) ** 2)
    return g / g.sum()


def ssim_map_mean(x, y, windows="reflect"):
    """x, y: [N, 1, H, W] float64 in [0, 1] -> per-item mean SSIM. `reflect`: mirror-pad by 5
    (one window per pixel, as torchmetrics 1.4.2 which the release used); `valid`: windows
    inside the image only."""
    g = gaussian_1d()
    win = (g[:, None] * g[None, :])[None, None]
    c1, c2 = 0.01**2, 0.03**2
    if windows == "reflect":
        x = F.pad(x, (5, 5, 5, 5), mode="reflect")
        y = F.pad(y, (5, 5, 5, 5), mode="reflect")
    mu_x = F.conv2d(x, win)
    mu_y = F.conv2d(y, win)
    sxx = (F.conv2d(x * x, win) - mu_x**2).clamp_min(0)
    syy = (F.conv2d(y * y, win) - mu_y**2).clamp_min(0)
    sxy = F.conv2d(x * y, win) - mu_x * mu_y
    m = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return m.flatten(1).mean(1)


def ssim_per_channel(a, b, windows="reflect"):
    bs, c, h, w = a.shape
    v = ssim_map_mean(a.reshape(bs * c, 1, h, w), b.reshape(bs * c, 1, h, w), windows)
    return v.reshape(bs, c).mean(1)


def luma(x):
    return 0.2989 * x[:, 0:1] + 0.587 * x[:, 1:2] + 0.114 * x[:, 2:3]


def psnr_per_image(a, b):
    mse = ((a - b) ** 2).flatten(1).mean(1)
    return -10.0 * torch.log10(mse)


def make_metrics(rng):
    a = smooth_image(rng, 2, 3, 40, 48)
    noise = torch.from_numpy(rng.normal(0, 0.05, a.shape))
    b = (a * 0.9 + 0.05 + noise).clamp(0, 1)
    b[1] = (a[1].flip(-1) * 0.5 + b[1] * 0.5).clamp(0, 1)  # a structurally different pair
    # Values outside [0, 1] are clamped by the metrics (the release clamps before measuring).
    a_in = a.clone()
    a_in[0, 0, 0, 0] = 1.5
    a_in[0, 1, 3, 4] = -0.25
    a32, b32 = a_in.float(), b.float()
    ac, bc = a32.double().clamp(0, 1), b32.double().clamp(0, 1)
    out = {
        "a": a32,
        "b": b32,
        "psnr": psnr_per_image(ac, bc),
        "ssim_reflect": ssim_per_channel(ac, bc, "reflect"),
        "ssim_valid": ssim_per_channel(ac, bc, "valid"),
        "ssim_gray_reflect": ssim_map_mean(luma(ac), luma(bc), "reflect"),
        "ssim_gray_valid": ssim_map_mean(luma(ac), luma(bc), "valid"),
    }
    try:
        import torchmetrics
        import torchmetrics.functional.image as tmi

        for i in range(2):
            p = tmi.peak_signal_noise_ratio(ac[i : i + 1], bc[i : i + 1], data_range=(0.0, 1.0))
            s = tmi.structural_similarity_index_measure(ac[i : i + 1], bc[i : i + 1], data_range=1.0)
            sg = tmi.structural_similarity_index_measure(luma(ac[i : i + 1]), luma(bc[i : i + 1]), data_range=1.0)
            print(
                f"torchmetrics {torchmetrics.__version__} cross-check image {i}: "
                f"psnr {float(p) - float(out['psnr'][i]):+.2e}, "
                f"ssim {float(s) - float(out['ssim_reflect'][i]):+.2e}, "
                f"luma ssim {float(sg) - float(out['ssim_gray_reflect'][i]):+.2e}"
            )
    except ImportError:
        print("torchmetrics not installed: no cross-check")
    return out


# ----------------------------------------------------------------------------------------------
# Head box


def head_box_ref(bbox, h, w):
    """bbox: [K, 4] float32 tensor -> [K, 4] int64 (x0, y0, x1, y1), all float32 arithmetic."""
    x0, y0, x1, y1 = bbox.unbind(-1)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    side = torch.sqrt((y1 - y0) * (x1 - x0)) * 1.1
    for lim in (cx * 2, cy * 2, (1 - cx) * 2, (1 - cy) * 2):
        side = torch.min(side, lim)
    corners = torch.stack([cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2], -1)
    corners = corners.clamp(0, 1)
    scale = torch.tensor([w, h, w, h], dtype=torch.float32)
    return (corners * scale).long()


def make_head_box(rng):
    k = 400
    c = rng.uniform(-0.05, 1.05, (k, 2))
    size = np.exp(rng.uniform(np.log(1e-3), np.log(1.2), (k, 2)))
    bb = np.concatenate([c - size / 2, c + size / 2], 1)
    special = np.array(
        [
            [0.0, 0.0, 1.0, 1.0],
            [0.0, 0.2, 0.3, 0.6],
            [0.7, 0.7, 1.0, 1.0],
            [0.25, 0.25, 0.75, 0.75],
            [0.5, 0.5, 0.5005, 0.5005],
            [0.1, 0.45, 0.9, 0.55],
            [0.999, 0.4, 1.0, 0.6],
            [0.3, 0.3, 0.31, 0.9],
        ]
    )
    bb = np.concatenate([special, bb], 0)
    # Many values on a fine grid too: exact binary fractions make truncation ties likely.
    grid = np.round(rng.uniform(0, 1, (64, 4)) * 64) / 64
    grid = np.concatenate([np.minimum(grid[:, :2], grid[:, 2:]), np.maximum(grid[:, :2], grid[:, 2:])], 1)
    bb = torch.from_numpy(np.concatenate([bb, grid], 0)).float()
    area_ok = (bb[:, 2] > bb[:, 0]) & (bb[:, 3] > bb[:, 1])
    out = {"bbox": bb}
    for n in (512, 64):
        boxes = head_box_ref(bb, n, n)
        valid = area_ok & (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
        out[f"boxes_{n}"] = boxes
        out[f"valid_{n}"] = valid.to(torch.int64)
        print(f"head boxes at {n}: {int(valid.sum())} of {len(bb)} valid")
    # Crop-resize golden.
    img = smooth_image(rng, 2, 3, 64, 64).float()
    cb = torch.tensor([[0.2, 0.25, 0.7, 0.8], [0.05, 0.1, 0.45, 0.35]], dtype=torch.float32)
    boxes = head_box_ref(cb, 64, 64)
    out["crop_image"] = img
    out["crop_bbox"] = cb
    for size in (24, 48):
        crops = []
        for i, bx in enumerate(boxes.tolist()):
            crop = img.double()[i : i + 1, :, bx[1] : bx[3], bx[0] : bx[2]]
            crops.append(F.interpolate(crop, size=(size, size), mode="bilinear", align_corners=False, antialias=True))
        out[f"crop_{size}"] = torch.cat(crops).float()
    return out


# ----------------------------------------------------------------------------------------------
# Perceptual networks

MASK64 = (1 << 64) - 1
GOLDEN = 0x9E3779B97F4A7C15


def splitmix64(x):
    """Vectorised over a uint64 array (wrapping arithmetic)."""
    with np.errstate(over="ignore"):
        z = x + np.uint64(GOLDEN)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


ALEX = [  # key, cin, cout, k, stride, pad, pool before
    ("net.slice1.0", 3, 64, 11, 4, 2, False),
    ("net.slice2.3", 64, 192, 5, 1, 2, True),
    ("net.slice3.6", 192, 384, 3, 1, 1, True),
    ("net.slice4.8", 384, 256, 3, 1, 1, False),
    ("net.slice5.10", 256, 256, 3, 1, 1, False),
]
VGG = [(0, 3, 64), (2, 64, 64), (5, 64, 128), (7, 128, 128), (10, 128, 256), (12, 256, 256), (14, 256, 256),
       (17, 256, 512), (19, 512, 512), (21, 512, 512), (24, 512, 512), (26, 512, 512), (28, 512, 512)]
VGG_BLOCKS = [[0], [2, 5], [7, 10], [12, 14, 17], [19, 21, 24]]


def key_list():
    keys = []
    for name, cin, cout, k, *_ in ALEX:
        keys += [(f"{name}.weight", (cout, cin, k, k)), (f"{name}.bias", (cout,))]
    for idx, cin, cout in VGG:
        keys += [(f"vggface.network.{idx}.weight", (cout, cin, 3, 3)), (f"vggface.network.{idx}.bias", (cout,))]
    return keys


def seeded_weights(seed, only=None):
    """The same values as the Rust `seeded_weights(seed)`, as float32 tensors."""
    out = {}
    for ki, (key, shape) in enumerate(key_list()):
        if only is not None and not any(key.startswith(o) for o in only):
            continue
        n = int(np.prod(shape))
        bound = math.sqrt(6.0 / int(np.prod(shape[1:]))) if key.endswith(".weight") else 0.1
        base = splitmix64(np.array([(seed ^ (ki << 32)) & MASK64], dtype=np.uint64))[0]
        with np.errstate(over="ignore"):
            states = base + np.arange(n, dtype=np.uint64) * np.uint64(GOLDEN)
        z = splitmix64(states)
        u = (z >> np.uint64(11)).astype(np.float64) * (1.0 / float(1 << 53))
        vals = ((2.0 * u - 1.0) * bound).astype(np.float32)
        out[key] = torch.from_numpy(vals.reshape(shape))
    return out


class Perceptual:
    """The release's perceptual distance, written from the crate's documented definition."""

    def __init__(self, weights, dtype=torch.float64):
        self.w = {k: v.to(dtype) for k, v in weights.items()}

    def conv(self, x, key, stride=1, pad=1):
        return F.conv2d(x, self.w[key + ".weight"], self.w[key + ".bias"], stride=stride, padding=pad)

    def alex(self, x):
        mean = torch.tensor([0.485, 0.456, 0.406], dtype=x.dtype).view(1, 3, 1, 1)
        std = torch.tensor([0.229, 0.224, 0.225], dtype=x.dtype).view(1, 3, 1, 1)
        h = (x - mean) / std
        feats = []
        for name, _, _, _, s, p, pool in ALEX:
            if pool:
                h = F.max_pool2d(h, 3, 2)
            h = F.relu(self.conv(h, name, s, p))
            feats.append(h)
        return feats

    def vgg(self, x):
        mean = torch.tensor([129.186279296875, 104.76238250732422, 93.59396362304688], dtype=x.dtype).view(1, 3, 1, 1)
        h = x * 255 - mean
        feats = []
        for bi, block in enumerate(VGG_BLOCKS):
            if bi > 0:
                h = F.max_pool2d(h, 2, 2)
            for idx in block:
                h = F.relu(self.conv(h, f"vggface.network.{idx}"))
            feats.append(h)
        return feats

    @staticmethod
    def norm(f, eps=1e-10):
        return f / (torch.sqrt(torch.sum(f**2, dim=1, keepdim=True)) + eps)

    def terms(self, pred, target):
        weights = [0.1, 0.1, 1.0, 1.0, 1.0]
        fa, ta = self.alex(pred), self.alex(target)
        fv, tv = self.vgg(pred), self.vgg(target)
        out = []
        for l in range(5):
            d = F.l1_loss(self.norm(fa[l]), self.norm(ta[l]), reduction="none").sum(1, keepdim=True).mean()
            out.append(d * weights[l])
        for l in range(5):
            d = F.l1_loss(self.norm(fv[l]), self.norm(tv[l]), reduction="none").sum(1, keepdim=True).mean()
            out.append(d * weights[l] * 0.5)
        return out

    def loss(self, pred, target):
        return sum(self.terms(pred, target))


PERCEP_SEED = 7


def used_keys():
    return [a[0] for a in ALEX] + [f"vggface.network.{i}." for b in VGG_BLOCKS for i in b]


def make_perceptual(rng, net):
    x = smooth_image(rng, 2, 3, 48, 48).float()
    y = (x.double() * 0.8 + 0.1 + torch.from_numpy(rng.normal(0, 0.05, x.shape))).clamp(0, 1).float()
    xd = x.double().requires_grad_(True)
    terms = net.terms(xd, y.double())
    loss = sum(terms)
    (gx,) = torch.autograd.grad(loss, xd)
    with torch.no_grad():
        fa = net.alex(x.double())
        fv = net.vgg(x.double())
    out = {"x": x, "y": y, "terms": torch.stack(terms).detach(), "loss": loss.detach(), "grad_x": gx.float()}
    for l in range(5):
        out[f"alex_{l}"] = fa[l][0].float()
    for l in (3, 4):
        out[f"vgg_{l}"] = fv[l][0].float()
    print(f"perceptual: loss {float(loss):.6f}, terms {[round(float(t), 5) for t in terms]}")
    return out


# ----------------------------------------------------------------------------------------------
# Adam


ADAM_PARAMS = [
    ("enc.w", (4, 5)),
    ("upsampler.style_mlp.0.weight", (3, 3)),
    ("upsampler.final_linear.bias", (6,)),
    ("gs_generator_g.color_layers.0.bias", (7,)),
]
ADAM_STEPS = 6
ADAM_SKIP = {(2, "gs_generator_g.color_layers.0.bias"), (3, "enc.w")}


def run_adam(rng, lr, total, prefix, out):
    params = {}
    for name, shape in ADAM_PARAMS:
        p = torch.from_numpy(rng.normal(0, 1, shape)).float()
        out[f"{prefix}init.{name}"] = p.clone()
        params[name] = torch.nn.Parameter(p)
    low = [params[n] for n, _ in ADAM_PARAMS if "style_mlp" in n or "final_linear" in n]
    normal = [params[n] for n, _ in ADAM_PARAMS if not ("style_mlp" in n or "final_linear" in n)]
    opt = torch.optim.Adam(
        [{"params": normal, "lr": lr}, {"params": low, "lr": lr * 0.1}], lr=lr, betas=(0.0, 0.99)
    )
    sched = torch.optim.lr_scheduler.LinearLR(opt, start_factor=1.0, end_factor=0.1, total_iters=total)
    lrs = []
    for step in range(ADAM_STEPS):
        lrs.append(opt.param_groups[0]["lr"])
        # The closed form the crate uses.
        closed = lr * (1 - 0.9 * min(step, total) / total)
        assert abs(lrs[-1] - closed) <= 1e-15 * lr, (lrs[-1], closed)
        for name, shape in ADAM_PARAMS:
            if (step, name) in ADAM_SKIP:
                params[name].grad = None
                continue
            # Mixed magnitudes, including a tiny and a large gradient.
            g = rng.normal(0, 1, shape) * (10.0 ** rng.integers(-3, 2))
            g = torch.from_numpy(g).float()
            out[f"{prefix}grad{step}.{name}"] = g
            params[name].grad = g.clone()
        opt.step()
        sched.step()
        for name, _ in ADAM_PARAMS:
            out[f"{prefix}param{step}.{name}"] = params[name].detach().clone()
    out[f"{prefix}lrs"] = torch.tensor(lrs, dtype=torch.float64)


def make_adam(rng):
    out = {}
    run_adam(rng, 1e-4, 3, "release.", out)
    run_adam(rng, 1e-2, 4, "large.", out)
    return out


# ----------------------------------------------------------------------------------------------
# Losses


def lifting_ref(lifted, targets):
    d = ((targets[:, :, None, :] - lifted[:, None, :, :]) ** 2).sum(-1)  # [B, M, N]
    srt = torch.sort(d.detach(), dim=-1).values
    gap = (srt[..., 1] - srt[..., 0]) / srt[..., 1].clamp_min(1e-12)
    assert float(gap.min()) > 1e-4, "near tie in the nearest neighbour: float32 search may differ"
    idx = d.detach().argmin(-1)
    chosen = torch.gather(lifted, 1, idx[..., None].expand(-1, -1, 3))
    return ((targets - chosen) ** 2).sum(-1).mean() * 10


def blocks_sign(rng, shape, block=8):
    b, c, h, w = shape
    s = np.sign(rng.normal(size=(b, c, (h + block - 1) // block, (w + block - 1) // block)))
    s = np.repeat(np.repeat(s, block, 2), block, 3)[:, :, :h, :w]
    return torch.from_numpy(s)


def make_losses(rng, net):
    b, h, w, box = 2, 40, 40, 36
    bbox = torch.tensor([[0.3, 0.2, 0.75, 0.8], [0.05, 0.1, 0.5, 0.45]], dtype=torch.float32)
    boxes = head_box_ref(bbox, h, w).tolist()

    def crops(x):
        return torch.cat([
            F.interpolate(x[i : i + 1, :, bx[1] : bx[3], bx[0] : bx[2]], size=(box, box), mode="bilinear",
                          align_corners=False, antialias=True)
            for i, bx in enumerate(boxes)
        ])

    # Predictions differ from the target by at least MARGIN in every pixel and every crop sample
    # used by an L1 term (except one exactly matching patch), so float32 rounding cannot flip the
    # sign of a difference (the L1 gradient) between our run and this float64 one.
    margin = 1e-4
    for attempt in range(100):
        gt = smooth_image(rng, b, 3, h, w).float().double()
        fine = (gt + blocks_sign(rng, gt.shape) * (0.03 + 0.05 * torch.from_numpy(rng.random(gt.shape))))
        fine = fine.clamp(0.001, 0.999).float().double()
        crgb = (gt + blocks_sign(rng, gt.shape) * (0.03 + 0.1 * torch.from_numpy(rng.random(gt.shape))))
        crgb = crgb.clamp(-0.2, 1.2).float().double()
        # An exactly matching patch outside the head box: its L1 subgradient must be 0, not +-1.
        crgb[0, :, :4, :4] = gt[0, :, :4, :4]
        pix = (crgb - gt).abs()
        pix[0, :, :4, :4] = 1.0
        worst = min(float((fine - gt).abs().min()), float(pix.min()),
                    float((crops(fine) - crops(gt)).abs().min()), float((crops(crgb) - crops(gt)).abs().min()))
        if worst > margin:
            break
    else:
        raise SystemExit("no loss fixture with a sign margin found")
    print(f"losses: attempt {attempt}, smallest |difference| in an L1 term {worst:.2e}")
    coarse = torch.cat([crgb, torch.from_numpy(rng.normal(0, 1, (b, 1, h, w)))], 1)
    lifted = torch.from_numpy(rng.normal(0, 1, (b, 300, 3)))
    targets = torch.from_numpy(rng.normal(0, 0.8, (b, 50, 3)))
    gt, fine, coarse = gt.float(), fine.float(), coarse.float()
    lifted, targets = lifted.float(), targets.float()

    cd = coarse.double().requires_grad_(True)
    fd = fine.double().requires_grad_(True)
    ld = lifted.double().requires_grad_(True)
    g = gt.double()
    crgb = cd[:, :3]
    img = 0.5 * (F.l1_loss(crgb, g) + F.l1_loss(fd, g))

    gc, cc, fc = crops(g), crops(crgb), crops(fd)
    box_l1 = 0.5 * (F.l1_loss(cc, gc) + F.l1_loss(fc, gc))
    percep = 0.01 * (net.loss(cc, gc) + net.loss(fc, gc))
    point = lifting_ref(ld, targets.double())
    total = img + box_l1 + percep + point
    gcoarse, gfine, glifted = torch.autograd.grad(total, (cd, fd, ld))
    print(f"losses: img {float(img):.6f} box {float(box_l1):.6f} percep {float(percep):.6f} "
          f"point {float(point):.6f} total {float(total):.6f}; boxes {boxes}")
    return {
        "coarse": coarse, "fine": fine, "gt": gt, "bbox": bbox, "lifted": lifted, "targets": targets,
        "box_size": torch.tensor([box], dtype=torch.int64),
        "img": img.detach(), "box": box_l1.detach(), "percep": percep.detach(), "point": point.detach(),
        "total": total.detach(), "grad_coarse": gcoarse.float(), "grad_fine": gfine.float(),
        "grad_lifted": glifted.float(),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="crates/train/tests/data")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    net = Perceptual(seeded_weights(PERCEP_SEED, only=used_keys()))
    save(make_metrics(np.random.default_rng(1)), os.path.join(args.out, "metrics.safetensors"))
    save(make_head_box(np.random.default_rng(2)), os.path.join(args.out, "head_box.safetensors"))
    save(make_perceptual(np.random.default_rng(3), net), os.path.join(args.out, "perceptual.safetensors"))
    save(make_adam(np.random.default_rng(4)), os.path.join(args.out, "adam.safetensors"))
    save(make_losses(np.random.default_rng(5), net), os.path.join(args.out, "losses.safetensors"))
    # A few seeded weight values, so the Rust test proves the shared stream independently.
    w = seeded_weights(PERCEP_SEED, only=["net.slice1.0.", "vggface.network.28.bias"])
    probe = {k: v.flatten()[:16].clone() for k, v in w.items()}
    save(probe, os.path.join(args.out, "seeded_weights_probe.safetensors"))


if __name__ == "__main__":
    main()
