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
status=0
for t in "${targets[@]}"; do
  # Fuzz into a scratch corpus seeded from the committed one, so new inputs do not dirty git.
  work="$build/corpus/$t"
  mkdir -p "$work"
  log="$build/$t.log"
  echo "fuzz: $t for ${seconds}s"
  if ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1 \
    "$build/fuzz/${t}_fuzzer" -max_total_time="$seconds" -timeout=10 -rss_limit_mb=2048 \
    -max_len=65536 -print_final_stats=1 -artifact_prefix="$build/artifacts/${t}-" \
    "$work" "fuzz/corpus/$t" >"$log" 2>&1; then
    # Figures for docs/reliability.md: executions, coverage, corpus size.
    grep -E "stat::number_of_executed_units|stat::average_exec_per_sec|stat::peak_rss_mb" "$log" |
      tr '\n' ' '
    grep -E "^#[0-9]+.*(DONE|pulse|NEW)" "$log" | tail -1 || true
  else
    echo "fuzz: $t FAILED (log: $log)"
    grep -E "ERROR|SUMMARY|Test unit written" "$log" | head -10 || true
    status=1
  fi
done
exit "$status"
