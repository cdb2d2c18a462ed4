#!/usr/bin/env bash
# Builds irmosaic and runs the whole test suite (what CI runs). Installs dependencies first.
# Usage: scripts/test.sh            (build folder: build/, override with BUILD_DIR)
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install-deps.sh --with-qgis
build_dir=${BUILD_DIR:-build}
cmake -S . -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DIRMOSAIC_WERROR=ON >/dev/null
cmake --build "$build_dir" -j2
ctest --test-dir "$build_dir" --output-on-failure -j2 --timeout 900
