"""PyTorch CPU reference timings for the shapes of benches/conv.rs (f32, NCHW, 2 threads).

Run: python3 crates/ops/benches/conv_torch.py   (prints ms per call: the fastest repeat and
the process CPU time per call, which is steadier on a shared machine; compare with
examples/conv_probe.rs, which prints the same two numbers)
"""
import resource
import time

import torch

torch.set_num_threads(2)
torch.manual_seed(0)

# (name, cin, cout, k, stride, padding, h, w) -- must match benches/conv.rs
SHAPES = [
    ("k3_64to32_512", 64, 32, 3, 1, 1, 512, 512),
    ("k3_16to16_512", 16, 16, 3, 1, 1, 512, 512),
    ("k3_32to32_512", 32, 32, 3, 1, 1, 512, 512),
    ("k3_128to128_296", 128, 128, 3, 1, 1, 296, 296),
    ("k3_283to128_296", 283, 128, 3, 1, 1, 296, 296),
    ("k3_256to256_148", 256, 256, 3, 1, 1, 148, 148),
    ("k3_1027to256_19", 1027, 256, 3, 1, 1, 19, 19),
    ("k1_128to41_296", 128, 41, 1, 1, 0, 296, 296),
    ("k3s2_256to256_37", 256, 256, 3, 2, 1, 37, 37),
]


def cpu_time():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def bench(f, min_time=1.0, min_iters=5):
    """(fastest wall ms, CPU ms per call)."""
    f()
    times = []
    start, c0 = time.perf_counter(), cpu_time()
    while len(times) < min_iters or time.perf_counter() - start < min_time:
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    cpu = (cpu_time() - c0) / len(times)
    return min(times) * 1e3, cpu * 1e3


def main():
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, "
          f"mkldnn {torch.backends.mkldnn.is_available()}")
    for name, cin, cout, k, s, p, h, w in SHAPES:
        x = torch.randn(1, cin, h, w)
        wt = torch.randn(cout, cin, k, k) * 0.05
        b = torch.randn(cout)
        with torch.no_grad():
            ms, cpu = bench(lambda: torch.nn.functional.conv2d(x, wt, b, stride=s, padding=p))
        print(f"{name:20s} forward  {ms:9.2f} ms  cpu {cpu:9.2f} ms")
    # Backward of the 296x296 128->128 case: grad wrt x, w and bias.
    x = torch.randn(1, 128, 296, 296, requires_grad=True)
    wt = (torch.randn(128, 128, 3, 3) * 0.05).requires_grad_()
    b = torch.randn(128, requires_grad=True)
    y = torch.nn.functional.conv2d(x, wt, b, padding=1)
    g = torch.randn_like(y)

    def back():
        torch.autograd.grad(y, (x, wt, b), g, retain_graph=True)

    ms, cpu = bench(back)
    print(f"{'k3_128to128_296':20s} backward {ms:9.2f} ms  cpu {cpu:9.2f} ms (grad x, w, bias)")


if __name__ == "__main__":
    main()
