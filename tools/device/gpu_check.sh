#!/bin/bash
# The GPU check of issues 30/31, in one device call (see tools/device/README.md):
# adapter facts, the GPU parity tests on a real driver (release size included, their measured
# maxima printed), `bench drive` at release size for both Gaussian regimes, `bench
# reconstruct` (f16 and f32), `bench renderer-grad` and `bench dpt-grad` (issue 31: the
# renderer's and the DPT head's training forward and backward), `bench splat --device gpu`, `train-bench` on the GPU and the CPU (issue 31:
# `train --device gpu`'s split step), `reenact` end to end (reconstruct on the GPU too), and a sweep of
# convolution tilings (GAGAVATAR_GPU_TUNE, no rebuild), everything written to $OUT: a
# summary.txt to read, one JSON per bench run (bench_*.json) and check.json gathering them.
#
# Prepared here by tools/device/prepare.sh (stripped, gzipped binaries in .dev/, Vulkan loader
# debs in .gl/); run there with carry [".gl", ".dev"]:
#   bash tools/device/gpu_check.sh
set -u
# FRAMES, SWEEP_FRAMES, REENACT_FRAMES, RECONSTRUCT_RUNS, GRAD_RUNS, PRESET and TESTS (a
# test-name filter) shrink the run for a dry run on lavapipe; SKIP_TESTS=1 leaves the parity
# tests out. STEPS (drive reconstruct grad splat train reenact tests sweep; SPLAT_PLANE shrinks
# the splat scene; TRAIN_BATCH, TRAIN_RUNS size train-bench; TRAIN_FREEZE=1 freezes a small
# preset's backbone, so that a dry run takes the release's path: backbone and DPT head on the
# GPU), DRIVE_RUNS (small large f16),
# RECONSTRUCT_PRECISIONS and REENACT_PRECISIONS (f16 f32) pick what a later call redoes.
FRAMES=${FRAMES:-300}
SWEEP_FRAMES=${SWEEP_FRAMES:-40}
PRESET=${PRESET:-release}
TESTS=${TESTS:-}
OUT=${OUT:-/tmp/gpu_check_out}
mkdir -p "$OUT"
log() { echo "== $*" | tee -a "$OUT/summary.txt"; }

# Convolution precisions and tilings to time, as "precision|tuning" (precision: f32 or f16,
# the tensor cores; tuning keys of crates/gpu/src/tuning.rs, nothing = the defaults).
TUNES=(
    "f32|"
    "f16|"
    "f16|mma_fit=0,mma_prefetch=0,mma_small_prefetch=0"
    "f16|mma_prefetch=0,mma_small_prefetch=0"
    "f16|mma_fit=0"
    "f16|mma_bk=16"
    "f16|mma_small_prefetch=0"
)

# Tunings of `bench reconstruct` on the tensor cores, beside its defaults.
RECONSTRUCT_TUNES=(
    "mma_fit=0,mma_prefetch=0,mma_small_prefetch=0"
    "mma_prefetch=0,mma_small_prefetch=0"
    "ln_slices=64"
)

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

# Unpacked outside the checkout (a dry run must leave no 150 MiB of binaries in .dev/, which
# would push the next device call's working tree over its limit).
BIN=$(mktemp -d)
for f in .dev/*.gz; do gunzip -c "$f" > "$BIN/$(basename "$f" .gz)"; done
chmod +x "$BIN/gagavatar" "$BIN/gpu_tests"

log "adapter"
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv > "$OUT/nvidia_smi.csv" 2>&1
cat "$OUT/nvidia_smi.csv" >> "$OUT/summary.txt"

# STEPS picks sections (a second call after a fix need not redo the rest).
STEPS=${STEPS:-drive reconstruct grad splat train reenact tests sweep}
want() { case " $STEPS " in *" $1 "*) return 0 ;; *) return 1 ;; esac; }

want drive && {
log "bench drive, $PRESET, $FRAMES frames: f32 (small and large Gaussians), f16 tensor cores (small)"
for run in ${DRIVE_RUNS:-small large f16}; do
    regime=$run precision=f32
    [ "$run" = f16 ] && regime=small precision=f16
    timeout 150 "$BIN/gagavatar" bench drive --device gpu --gpu-precision "$precision" \
        --preset "$PRESET" --frames "$FRAMES" --regime "$regime" --json "$OUT/bench_$run.json" \
        --dispatches > "$OUT/bench_drive_$run.txt" 2>&1
    echo "exit $? ($run)" >> "$OUT/summary.txt"
    tail -33 "$OUT/bench_drive_$run.txt" >> "$OUT/summary.txt"
done
}

want reconstruct && {
log "bench reconstruct, $PRESET seeded weights, ${RECONSTRUCT_RUNS:-20} runs: f16 tensor cores, then f32"
for precision in ${RECONSTRUCT_PRECISIONS:-f16 f32}; do
    timeout 120 "$BIN/gagavatar" bench reconstruct --device gpu --gpu-precision "$precision" \
        --preset "$PRESET" --runs "${RECONSTRUCT_RUNS:-20}" --dispatches \
        --json "$OUT/bench_reconstruct_$precision.json" > "$OUT/bench_reconstruct_$precision.txt" 2>&1
    echo "exit $? (reconstruct, $precision)" >> "$OUT/summary.txt"
    tail -32 "$OUT/bench_reconstruct_$precision.txt" >> "$OUT/summary.txt"
done
# The kernels' knobs against each other on the tensor cores (the defaults ran above).
i=0
for tune in "${RECONSTRUCT_TUNES[@]}"; do
    GAGAVATAR_GPU_TUNE="$tune" timeout 90 "$BIN/gagavatar" bench reconstruct --device gpu \
        --gpu-precision f16 --preset "$PRESET" --runs "${RECONSTRUCT_RUNS:-20}" \
        > "$OUT/reconstruct_tune_$i.txt" 2>&1
    rc=$?
    med=$(grep -o 'median [0-9.]* ms' "$OUT/reconstruct_tune_$i.txt")
    dino=$(grep -o 'dino *[0-9.]* ms' "$OUT/reconstruct_tune_$i.txt")
    echo "reconstruct tune $i [f16 $tune] exit $rc $med; $dino" >> "$OUT/summary.txt"
    [ $rc = 0 ] || tail -3 "$OUT/reconstruct_tune_$i.txt" >> "$OUT/summary.txt"
    i=$((i + 1))
done
}

want grad && {
log "bench renderer-grad (training forward + backward, f32), $PRESET seeded weights, ${GRAD_RUNS:-10} steps"
timeout 90 "$BIN/gagavatar" bench renderer-grad --device gpu --preset "$PRESET" \
    --runs "${GRAD_RUNS:-10}" --json "$OUT/bench_renderer_grad.json" \
    > "$OUT/bench_renderer_grad.txt" 2>&1
echo "exit $? (renderer-grad)" >> "$OUT/summary.txt"
tail -5 "$OUT/bench_renderer_grad.txt" >> "$OUT/summary.txt"
log "bench dpt-grad (the DPT head's training forward + backward per sample, f32), $PRESET seeded weights, ${GRAD_RUNS:-10} samples"
timeout 90 "$BIN/gagavatar" bench dpt-grad --device gpu --preset "$PRESET" \
    --runs "${GRAD_RUNS:-10}" > "$BIN/bench_dpt_grad.txt" 2>&1
echo "exit $? (dpt-grad)" >> "$OUT/summary.txt"
tail -4 "$BIN/bench_dpt_grad.txt" >> "$OUT/summary.txt"
}

want splat && {
log "bench splat (training forward + backward of the splatting, issue 31), ${SPLAT_PLANE:-296}-point planes, ${GRAD_RUNS:-10} runs"
timeout 120 "$BIN/gagavatar" bench splat --device gpu --regime both --plane "${SPLAT_PLANE:-296}" \
    --runs "${GRAD_RUNS:-10}" > "$OUT/bench_splat.txt" 2>&1
echo "exit $? (splat)" >> "$OUT/summary.txt"
grep -E "^splat|^error" "$OUT/bench_splat.txt" >> "$OUT/summary.txt"
}

want train && {
log "train-bench (issue 31: train --device gpu's split step against the CPU step), $PRESET seeded weights and perceptual networks, batch ${TRAIN_BATCH:-1}, ${TRAIN_RUNS:-2} steps"
TRAIN_CFG=(--preset "$PRESET")
if [ "${TRAIN_FREEZE:-0}" = 1 ]; then
    sed 's/^\[model\]$/[model]\nfreeze_backbone = true/' "crates/train/configs/$PRESET.toml" \
        > "$BIN/train_frozen.toml"
    TRAIN_CFG=(--config "$BIN/train_frozen.toml")
fi
for device in gpu cpu; do
    timeout 200 "$BIN/gagavatar" train-bench "${TRAIN_CFG[@]}" --batch "${TRAIN_BATCH:-1}" \
        --runs "${TRAIN_RUNS:-2}" --seeded-percep --device "$device" \
        > "$OUT/train_bench_$device.txt" 2>&1
    echo "exit $? (train-bench --device $device)" >> "$OUT/summary.txt"
    grep -E "^train step|^split step|^error" "$OUT/train_bench_$device.txt" >> "$OUT/summary.txt"
done
}

want reenact && {
log "reenact end to end, $PRESET seeded weights, ${REENACT_FRAMES:-354} frames (records cached: no tracking), f16 then f32"
"$BIN/gagavatar" init-weights --preset "$PRESET" --seed 1 -o "$BIN/weights.safetensors" > /dev/null 2>&1
for precision in ${REENACT_PRECISIONS:-f16 f32}; do
    timeout 150 "$BIN/gagavatar" reenact --ckpt "$BIN/weights.safetensors" --flame synthetic \
        --source assets/demo/source.png --source-record assets/demo/source.json \
        --driver .dev/driver354.json --max-frames "${REENACT_FRAMES:-354}" \
        --device gpu --gpu-precision "$precision" -o "$BIN/reenact_$precision.mp4" \
        > "$OUT/reenact_$precision.txt" 2>&1
    echo "exit $? (reenact, $precision)" >> "$OUT/summary.txt"
    grep -E "^time:|^wrote|^error" "$OUT/reenact_$precision.txt" >> "$OUT/summary.txt"
done
}

if want tests && [ "${SKIP_TESTS:-0}" != 1 ]; then
    log "GPU parity tests (every one, release size included)"
    GAGAVATAR_REQUIRE_GPU_TESTS=1 timeout 240 "$BIN/gpu_tests" $TESTS --include-ignored \
        --test-threads 1 --nocapture > "$OUT/gpu_tests.txt" 2>&1
    echo "exit $?" >> "$OUT/summary.txt"
    grep -E "test result|panicked|FAILED|^failures|worst|weights within|L1 loss|skipping" "$OUT/gpu_tests.txt" | cut -c1-200 >> "$OUT/summary.txt"
fi

want sweep && {
log "convolution tilings, $SWEEP_FRAMES frames each"
i=0
for entry in "${TUNES[@]}"; do
    precision=${entry%%|*} tune=${entry#*|}
    GAGAVATAR_GPU_TUNE="$tune" timeout 90 "$BIN/gagavatar" bench drive --device gpu \
        --gpu-precision "$precision" --preset "$PRESET" --frames "$SWEEP_FRAMES" \
        --json "$OUT/bench_tune_$i.json" > "$OUT/bench_tune_$i.txt" 2>&1
    rc=$?
    fps=$(grep -o '= [0-9.]* frames/s' "$OUT/bench_tune_$i.txt")
    unet=$(grep -o 'U-Net + SFT *[0-9.]* ms' "$OUT/bench_tune_$i.txt")
    dec=$(grep -o 'mapping + decoder *[0-9.]* ms' "$OUT/bench_tune_$i.txt")
    echo "tune $i [$precision ${tune:-defaults}] exit $rc $fps; $unet; $dec" >> "$OUT/summary.txt"
    [ $rc = 0 ] || tail -3 "$OUT/bench_tune_$i.txt" >> "$OUT/summary.txt"
    i=$((i + 1))
done
}

# One JSON of everything the benches wrote.
{
    echo "{"
    first=1
    for f in "$OUT"/bench_*.json; do
        [ -f "$f" ] || continue
        [ $first = 1 ] || echo ","
        first=0
        printf '"%s": ' "$(basename "$f" .json)"
        cat "$f"
    done
    echo "}"
} > "$OUT/check.json"
log "done"

# Only a few files come back from the device: everything but the summary and check.json goes
# into one archive (PACK=0 keeps the files apart).
if [ "${PACK:-1}" = 1 ]; then
    (cd "$OUT" && find . -maxdepth 1 -type f ! -name summary.txt ! -name check.json \
        ! -name details.tar.gz -printf '%P\n' | tar -czf details.tar.gz -T - --remove-files)
fi
