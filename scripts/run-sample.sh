#!/usr/bin/env bash
# Installs dependencies, builds irmosaic and runs the main job on the bundled sample.
# Usage: scripts/run-sample.sh [OUTPUT_DIR]     (default: out/sample)
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install-deps.sh
build_dir=${BUILD_DIR:-build}
out=${1:-out/sample}
cmake -S . -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo >/dev/null
cmake --build "$build_dir" -j2 --target irmosaic_cli
mkdir -p "$out"
"$build_dir/cli/irmosaic" footprints --pos samples/pos_only/pos.csv \
  --camera samples/pos_only/camera.json --ground-height 420 --output "$out/footprints.geojson"
echo "run-sample: wrote $out/footprints.geojson"
