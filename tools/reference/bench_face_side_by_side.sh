#!/usr/bin/env bash
# Times gagavatar's face perception and MediaPipe 0.10.21's Python solutions on the same frames,
# one right after the other, with the same number of cores, and prints the ratios.
#
#   tools/reference/bench_face_side_by_side.sh FRAMES [THREADS] [RUNS]
#
# FRAMES: a folder of frames (e.g. `ffmpeg -i clip.mp4 FRAMES/f%03d.png`). THREADS (default 2):
# gagavatar's --threads, and the cores MediaPipe is pinned to (its Python API has no thread
# setting). Needs a release build (`cargo build --release`) and mediapipe==0.10.21.
set -euo pipefail
frames=${1:?usage: bench_face_side_by_side.sh FRAMES [THREADS] [RUNS]}
threads=${2:-2}
runs=${3:-3}
here=$(cd "$(dirname "$0")" && pwd)
bin="$here/../../target/release/gagavatar"
cores=$(seq -s, 0 $((threads - 1)))
echo "load average: $(cut -d' ' -f1-3 /proc/loadavg), $(nproc) cores"
ours=$("$bin" bench face "$frames" --threads "$threads" --runs "$runs")
theirs=$(taskset -c "$cores" python3 "$here/bench_mediapipe_face.py" "$frames" --runs "$runs" 2>/dev/null)
echo "$ours"
echo "$theirs"
# The rows in the same order in both: tracking, short range, full range, photo, matte (ours at
# frame size, the comparable row).
python3 - "$ours" "$theirs" <<'PY'
import re, sys
med = lambda text: [float(x) for x in re.findall(r"median ([0-9.]+) ms", text)]
o, t = med(sys.argv[1]), med(sys.argv[2])
names = ["tracking frame", "detection, short range", "detection, full range", "photo (detect + 478)", "matte at frame size"]
ours = [o[0], o[1], o[2], o[3], o[5]]
print("MediaPipe time / gagavatar time (higher: gagavatar faster):")
for n, a, b in zip(names, ours, t):
    print(f"  {n}: {b:.2f} / {a:.2f} ms = {b / a:.2f}x")
PY
