#!/usr/bin/env bash
# Builds the threaded tests with ThreadSanitizer and runs them (map fusion's optimizer thread,
# the helper threads that register a frame's pairs, the store's writer thread against a painter). Third-party code is suppressed where TSan
# cannot see its synchronisation (tests/tsan.supp says why).
# Usage: scripts/tsan.sh [full]   (build folder: build-tsan/)
#   full: also the whole Mosaicker (mosaicker_test, ~7 min under TSan on 2 cores; not in CI).
set -euo pipefail
cd "$(dirname "$0")/.."
build_dir=${BUILD_DIR:-build-tsan}
# -O1 -g1 (line tables only), as the ASan build: on this 2-core machine the TSan build of the
# library and map_fusion_test took 128 s instead of ~215 s at -O2 -g, and the run 64 s against
# 62 s (session 6, docs/reliability.md).
# Clang, as the ASan build (scripts/sanitize.sh): it compiles in less time than GCC. A folder
# configured by another compiler (GCC before session 44) is made again.
if [[ -f "$build_dir/CMakeCache.txt" ]] && ! grep -q '^CMAKE_CXX_COMPILER:[A-Z]*=.*clang++' \
  "$build_dir/CMakeCache.txt"; then
  rm -rf "$build_dir"
fi
cmake -S . -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCMAKE_CXX_COMPILER=clang++ \
  -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O1 -g1" -DIRMOSAIC_TSAN=ON -DIRMOSAIC_BUILD_BENCH=OFF >/dev/null
targets=(map_fusion_test helper_threads_test tile_store_test)
[[ "${1:-}" == full ]] && targets+=(mosaicker_test)
cmake --build "$build_dir" -j2 --target "${targets[@]}"
export TSAN_OPTIONS="suppressions=$PWD/tests/tsan.supp halt_on_error=1"
# The programs run side by side, map_fusion_test in two GoogleTest shards: one after the other
# they took 133 s (map_fusion_test 99 s wall for 79 s of CPU, the store tests 33 s wall for 10 s
# of CPU waiting on the writer), so the two cores idled. Each job's output goes to a log, printed
# when all have ended; a report or failure in any fails the script.
logs=$(mktemp -d "${TMPDIR:-/tmp}/irmosaic_tsan_XXXXXX")
pids=()
for shard in 0 1; do
  GTEST_TOTAL_SHARDS=2 GTEST_SHARD_INDEX=$shard \
    "$build_dir/tests/map_fusion_test" >"$logs/map_fusion_$shard.log" 2>&1 &
  pids+=($!)
done
"$build_dir/tests/helper_threads_test" >"$logs/helper_threads.log" 2>&1 &
pids+=($!)
# The painter against the writer's publishes (copy-on-write tiles) and its overview slices; the
# other store tests fork readers and kill -9 writers, which TSan does not follow.
"$build_dir/tests/tile_store_test" \
  --gtest_filter='TileStoreTest.PaintingDuring*' >"$logs/tile_store.log" 2>&1 &
pids+=($!)
status=0
for pid in "${pids[@]}"; do wait "$pid" || status=1; done
for log in "$logs"/*.log; do
  echo "== $(basename "$log" .log)"
  cat "$log"
done
rm -rf "$logs"
if [[ $status -ne 0 ]]; then
  echo "tsan: a test failed or TSan reported (logs above)" >&2
  exit 1
fi
[[ "${1:-}" == full ]] && "$build_dir/tests/mosaicker_test"
echo "tsan: ${targets[*]} clean"
