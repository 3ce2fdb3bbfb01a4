#!/bin/bash
# The GPU check of issues 30/31, in one device call (see tools/device/README.md):
# adapter facts, the GPU parity tests on a real driver (release size included) and
# `bench drive` at release size, everything written to $OUT.
#
# Prepared here by tools/device/prepare.sh (stripped, gzipped binaries in .dev/, Vulkan loader
# debs in .gl/); run there with carry [".gl", ".dev"]:
#   bash tools/device/gpu_check.sh
set -u
# FRAMES, PRESET and TESTS (a test-name filter) shrink the run for a dry run on lavapipe.
FRAMES=${FRAMES:-300}
PRESET=${PRESET:-release}
TESTS=${TESTS:-}
OUT=${OUT:-/tmp/gpu_check_out}
mkdir -p "$OUT"
log() { echo "== $*" | tee -a "$OUT/summary.txt"; }

# The Vulkan loader (the machine has the NVIDIA driver but may lack the loader).
if ! ldconfig -p | grep -q libvulkan.so.1; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
fi
if [ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ] && [ -z "${VK_DRIVER_FILES:-}" ]; then
    export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
fi
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-$(mktemp -d)}

# Test binaries carry this checkout's absolute path (CARGO_MANIFEST_DIR) for their fixtures.
BUILT_AT=$(cat .dev/built_at)
if [ "$PWD" != "$BUILT_AT" ] && [ ! -e "$BUILT_AT" ]; then
    mkdir -p "$(dirname "$BUILT_AT")" && ln -s "$PWD" "$BUILT_AT"
fi

for f in .dev/*.gz; do gunzip -kf "$f"; done
chmod +x .dev/gagavatar .dev/gpu_tests

log "adapter"
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv > "$OUT/nvidia_smi.csv" 2>&1
cat "$OUT/nvidia_smi.csv" >> "$OUT/summary.txt"

log "bench drive, release, 300 frames, small and large Gaussians"
for regime in small large; do
    timeout 150 .dev/gagavatar bench drive --device gpu --preset "$PRESET" --frames "$FRAMES" \
        --regime "$regime" > "$OUT/bench_drive_$regime.txt" 2>&1
    echo "exit $? ($regime)" >> "$OUT/summary.txt"
    tail -25 "$OUT/bench_drive_$regime.txt" >> "$OUT/summary.txt"
done

log "GPU parity tests (every one, release size included)"
GAGAVATAR_REQUIRE_GPU_TESTS=1 timeout 240 .dev/gpu_tests $TESTS --include-ignored --test-threads 1 \
    > "$OUT/gpu_tests.txt" 2>&1
echo "exit $?" >> "$OUT/summary.txt"
grep -E "^test |test result" "$OUT/gpu_tests.txt" >> "$OUT/summary.txt"
log "done"
