#!/usr/bin/env bash
# Builds the threaded tests with ThreadSanitizer and runs them (map fusion's optimizer thread,
# the pipeline, the store's writer thread). Third-party OpenMP code is suppressed
# (tests/tsan.supp says why). Usage: scripts/tsan.sh   (build folder: build-tsan/)
set -euo pipefail
cd "$(dirname "$0")/.."
build_dir=${BUILD_DIR:-build-tsan}
# -O1 -g1 (line tables only), as the ASan build: on this 2-core machine the TSan build of the
# library and map_fusion_test took 128 s instead of ~215 s at -O2 -g, and the run 64 s against
# 62 s (session 6, docs/reliability.md).
cmake -S . -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O1 -g1" -DIRMOSAIC_TSAN=ON -DIRMOSAIC_BUILD_BENCH=OFF >/dev/null
targets=(map_fusion_test)
cmake --build "$build_dir" -j2 --target "${targets[@]}"
export TSAN_OPTIONS="suppressions=$PWD/tests/tsan.supp halt_on_error=1"
for t in "${targets[@]}"; do
  "$build_dir/tests/$t"
done
echo "tsan: ${targets[*]} clean"
