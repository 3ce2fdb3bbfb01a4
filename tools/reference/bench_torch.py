"""PyTorch timing of the reference network (net_reference.py) at a preset's size, stage by stage,
so `gagavatar bench model` can be compared with PyTorch on the same CPU at the same moment
(machine load and clock vary; only numbers taken side by side compare).

    python3 tools/reference/bench_torch.py --preset release --threads 2 --runs 5
    python3 tools/reference/bench_torch.py --preset release --threads 2 --precision bf16

`--precision bf16` runs every stage under `torch.autocast('cpu', dtype=torch.bfloat16)`,
PyTorch's own mixed precision (bf16 matmuls and convolutions, f32 elsewhere), to compare with
`gagavatar bench model --precision bf16`. With `--weights W.safetensors` (e.g. from `gagavatar
init-weights --preset release --seed 1`) it also prints the quality cost the Rust bench prints:
the renderer alone on a fixed pattern, bf16 against f32 (max abs, PSNR).

Stages match `gagavatar bench model`: preprocess, dino, dpt head, gs_generator_g, l0, l1,
reconstruct (their sum, as one pass), renderer (StyleUNet on a random coarse image). Weights are
PyTorch's default initialisation in float32 (timing does not depend on their values).
"""

import argparse
import os
import resource
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import net_reference as nr  # noqa: E402

import torch  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="release", choices=sorted(nr.PRESETS))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--precision", default="f32", choices=["f32", "bf16"])
    ap.add_argument("--weights", help="safetensors weights to load instead of PyTorch's default init")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    # net_reference defaults to float64 for the goldens; inference runs in float32.
    torch.set_default_dtype(torch.float32)
    c = nr.PRESETS[args.preset]
    model = nr.GAGAvatarRef(c).eval()
    if args.weights:
        from safetensors.torch import load_file
        nr.DT = torch.float32
        nr.load_weights(model, load_file(args.weights))
    gen = torch.Generator().manual_seed(0)
    img = torch.rand(1, 3, c.image_size, c.image_size, generator=gen)
    tm = torch.tensor([[[-1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 9.0]]])
    coarse = torch.rand(1, c.color_dim, c.image_size, c.image_size, generator=gen)
    stages = ["preprocess", "dino", "dpt head", "gs_generator_g", "gs_generator_l0", "gs_generator_l1",
              "reconstruct (total)", "renderer"]
    times = {s: [] for s in stages}
    autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=args.precision == "bf16")
    with torch.inference_mode(), autocast:
        for run in range(args.runs + 1):
            dbg = {}
            lap = {}
            t0 = time.perf_counter()
            x = nr.preprocess(img, c)
            t1 = time.perf_counter()
            toks = model.base_model.dino_model(x)
            t2 = time.perf_counter()
            f_local = model.base_model.dpt(toks, x, dbg)
            t3 = time.perf_counter()
            f_id = toks[3][:, 0]
            pp, pd = nr.plane_from_transform(tm, c.plane_size())
            e = nr.harmonic(pd)
            t4 = time.perf_counter()
            model.gs_generator_g(model.head_base, f_id, e, dbg)
            t5 = time.perf_counter()
            model.gs_generator_l0(f_local, e, pp, pd, 1.0, dbg, "l0")
            t6 = time.perf_counter()
            model.gs_generator_l1(f_local, e, pp, pd, -1.0, dbg, "l1")
            t7 = time.perf_counter()
            model.upsampler(coarse, dbg)
            t8 = time.perf_counter()
            lap = {"preprocess": t1 - t0, "dino": t2 - t1, "dpt head": t3 - t2, "gs_generator_g": t5 - t4,
                   "gs_generator_l0": t6 - t5, "gs_generator_l1": t7 - t6, "reconstruct (total)": t7 - t0,
                   "renderer": t8 - t7}
            if run > 0:
                for k, v in lap.items():
                    times[k].append(v * 1e3)
    print(f"PyTorch {torch.__version__} reference, {args.preset} {args.precision} ({args.threads} threads, "
          f"median of {args.runs} runs after a warm-up)")
    for s in stages:
        print(f"  {s:<22}{statistics.median(times[s]):10.1f} ms")
    print(f"  {'peak RSS':<22}{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:10.0f} MiB")
    if args.weights and args.precision == "bf16":
        pattern = render_pattern(c.color_dim, c.image_size)
        with torch.inference_mode():
            full = model.upsampler(pattern, {}).double()
            with torch.autocast("cpu", dtype=torch.bfloat16):
                low = model.upsampler(pattern, {}).double()
        d = (low - full).abs()
        psnr = 10 * torch.log10(1.0 / (d * d).mean()).item()
        print(f"  renderer alone (pattern), bf16 against f32: max abs {d.max().item():.2e}, "
              f"PSNR {psnr:.1f} dB")


def render_pattern(channels, size):
    """`0.5 + 0.5 sin(0.05 (c + 1) x + 0.07 y + 0.3 c)`, as `gagavatar bench model` builds it."""
    ch = torch.arange(channels, dtype=torch.float64).view(-1, 1, 1)
    y = torch.arange(size, dtype=torch.float64).view(1, -1, 1)
    x = torch.arange(size, dtype=torch.float64).view(1, 1, -1)
    a = 0.05 * (ch + 1) * x + 0.07 * y + 0.3 * ch
    return (0.5 + 0.5 * torch.sin(a)).to(torch.float32).unsqueeze(0)


if __name__ == "__main__":
    main()
