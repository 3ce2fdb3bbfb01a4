#!/bin/bash
# Builds what tools/device/gpu_check.sh runs on the GPU machine: the release CLI and the
# crates/gpu test binary, stripped and gzipped into .dev/ (ignored by git; the working tree that
# travels is limited to 64 MiB), and the Vulkan loader debs into .gl/.
set -eu
cd "$(git rev-parse --show-toplevel)"
mkdir -p .dev .gl
cargo build --release -p gagavatar --locked
bin=$(cargo test -p gagavatar-gpu --locked --no-run --message-format=json 2>/dev/null \
    | grep -o '"executable":"[^"]*gagavatar_gpu-[^"]*"' | head -1 | cut -d'"' -f4)
strip -o .dev/gagavatar target/release/gagavatar
strip -o .dev/gpu_tests "$bin"
gzip -f .dev/gagavatar .dev/gpu_tests
pwd > .dev/built_at
# A 354-frame driver (the demo's 100 records, looped): `reenact` end to end at bench speed.
python3 - <<'PY'
import json
d = json.load(open("assets/demo/driver.json"))
frames = [d["frames"][i % len(d["frames"])] for i in range(354)]
json.dump({"fps": d["fps"], "frames": frames}, open(".dev/driver354.json", "w"))
PY
if [ -z "$(ls .gl/*.deb 2>/dev/null)" ]; then
    o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
    mkdir -p /tmp/amd64/partial
    apt-get $o update
    (cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
fi
du -sh .dev .gl
