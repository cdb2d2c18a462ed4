#!/usr/bin/env bash
# Builds the libFuzzer targets (fuzz/) with clang++, ASan and UBSan in build-fuzz/ and runs each
# for SECONDS (default 30) from its seed corpus (fuzz/corpus/<target>/). Exits non-zero if a
# target crashes, leaks, hangs or fails to build; the reproducer is left in build-fuzz/artifacts/.
# Usage: scripts/fuzz.sh [SECONDS] [TARGET...]     (targets: pos_csv camera_json store_manifest
#                                                  gdal_driver)
set -euo pipefail
cd "$(dirname "$0")/.."
seconds="${1:-30}"
shift || true
targets=("$@")
if ((${#targets[@]} == 0)); then targets=(pos_csv camera_json store_manifest gdal_driver); fi
build="${IRMOSAIC_FUZZ_BUILD:-build-fuzz}"

cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DCMAKE_CXX_COMPILER=clang++ -DIRMOSAIC_BUILD_FUZZERS=ON \
  -DIRMOSAIC_BUILD_TESTS=OFF -DIRMOSAIC_BUILD_BENCH=OFF >/dev/null
cmake --build "$build" -j2 --target "${targets[@]/%/_fuzzer}"

mkdir -p "$build/artifacts"
# One target: fuzz into a scratch corpus seeded from the committed one, so new inputs do not dirty
# git; prints its figures (for docs/reliability.md: executions, coverage, corpus size) or its
# failure, and exits non-zero on a crash, leak, hang or sanitizer report.
fuzz_one() {
  local t=$1
  local work="$build/corpus/$t" log="$build/$t.log"
  mkdir -p "$work"
  if ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1 \
    "$build/fuzz/${t}_fuzzer" -max_total_time="$seconds" -timeout=10 -rss_limit_mb=2048 \
    -max_len=65536 -print_final_stats=1 -artifact_prefix="$build/artifacts/${t}-" \
    "$work" "fuzz/corpus/$t" >"$log" 2>&1; then
    echo "fuzz: $t for ${seconds}s: $(grep -E "stat::number_of_executed_units|stat::average_exec_per_sec|stat::peak_rss_mb" "$log" | tr '\n' ' ')$(grep -E "^#[0-9]+.*(DONE|pulse|NEW)" "$log" | tail -1 || true)"
  else
    echo "fuzz: $t FAILED (log: $log)"
    grep -E "ERROR|SUMMARY|Test unit written" "$log" | head -10 || true
    return 1
  fi
}

# Two targets at a time (each fuzzer is one single-threaded process; the machine has 2 cores).
status=0
pids=()
for t in "${targets[@]}"; do
  fuzz_one "$t" &
  pids+=($!)
  if ((${#pids[@]} == 2)); then
    for p in "${pids[@]}"; do wait "$p" || status=1; done
    pids=()
  fi
done
for p in "${pids[@]}"; do wait "$p" || status=1; done
exit "$status"
