"""What the Python layer adds per frame over the Rust library: renders `N` frames, `--batch` per
call, and compares the wall time with the time spent inside the library's `render_batch`
(codes in, RGB frames out), measured inside the same calls.

    python python/bench/overhead.py [N] [--batch B] [--ckpt W --flame F]
"""

import argparse
import statistics
import time

import gagavatar as ga

p = argparse.ArgumentParser()
p.add_argument("n", type=int, nargs="?", default=100)
p.add_argument("--batch", type=int, default=1)
p.add_argument("--ckpt")
p.add_argument("--flame")
p.add_argument("--runs", type=int, default=5)
a = p.parse_args()

eng = ga.Engine(a.ckpt, flame=a.flame) if a.ckpt else ga.Engine.demo()
src = ga.read_record(ga.demo_file("source.json"))
av = eng.avatar(ga.demo_file("source.png"), src)
records = (ga.read_driver(ga.demo_file("driver.json")).records * (a.n // 100 + 1))[: a.n]
av.render(records[:2], watermark=False)  # warm-up
overheads, per_frame = [], []
for _ in range(a.runs):
    d0, t0 = av.library_seconds, time.perf_counter()
    for i in range(0, len(records), a.batch):
        av.render(records[i : i + a.batch], batch=a.batch, watermark=False)
    wall, drive = time.perf_counter() - t0, av.library_seconds - d0
    overheads.append(100.0 * (wall - drive) / drive)
    per_frame.append(1e3 * wall / len(records))
print(
    f"{eng.image_size}x{eng.image_size}, {len(records)} frames, batch {a.batch}: "
    f"{statistics.median(per_frame):.2f} ms a frame from Python; the layer adds "
    f"{statistics.median(overheads):.2f}% over the Rust library (median of {a.runs} runs)"
)
