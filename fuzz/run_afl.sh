#!/usr/bin/env bash
# Long AFL++ campaigns for the fuzz harnesses (not part of CI): each target runs until it has
# made EXECS executions (default 1,000,000), one after another on one core, each case limited
# to 256 MB of address space (-m 256) and 1 s (-t 1000; slower cases count as hangs). The
# summary (executions, crashes, hangs per target) goes to fuzz/afl/out/summary.txt.
#
#   cargo install cargo-afl && cargo afl config --build     # once
#   (cd fuzz/afl && cargo afl build --release)
#   fuzz/run_afl.sh [EXECS] [TARGET ...]
set -euo pipefail
cd "$(dirname "$0")/afl"
execs="${1:-1000000}"
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
    targets=(pickle numpy torch_zip safetensors lmdb mp4 ply records_json driving_json toml_config image onnx)
fi
bin=target/release/gagavatar-fuzz-afl
mkdir -p out
export AFL_SKIP_CPUFREQ=1 AFL_NO_UI=1 AFL_NO_AFFINITY=1 AFL_I_DONT_CARE_ABOUT_MISSING_CRASHES=1
# Loaders that take a path get their scratch files on a RAM disk.
export TMPDIR="${TMPDIR:-/dev/shm}"
for t in "${targets[@]}"; do
    rm -rf "out/$t"
    start=$(date +%s)
    GAGAVATAR_FUZZ_TARGET="$t" cargo afl fuzz -i "../corpus/$t" -o "out/$t" -m 256 -t 1000 \
        -E "$execs" "$bin" > "out/$t.log" 2>&1 || true
    s="out/$t/default/fuzzer_stats"
    get() { awk -v k="$1" '$1 == k { print $3 }' "$s"; }
    printf '%-13s execs %9s  crashes %s  hangs %s  corpus %5s  edges %s  %s s\n' "$t" \
        "$(get execs_done)" "$(get saved_crashes)" "$(get saved_hangs)" "$(get corpus_count)" \
        "$(get edges_found)" "$(( $(date +%s) - start ))" | tee -a out/summary.txt
done
