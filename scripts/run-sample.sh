#!/usr/bin/env bash
# Installs dependencies, builds irmosaic and runs the main job on the bundled sample:
#   1. renders the sample flight (samples/sample_flight: a real NAIP image as ground, an oblique
#      sweeping 640x512 infrared camera, POS with 2 m / 0.3 deg errors) with `irmosaic synth`,
#   2. mosaics it into a live georeferenced store with `irmosaic run`,
#   3. exports a Cloud Optimized GeoTIFF in the UTM zone with `irmosaic export`,
#   4. scores the placements against the simulator's truth with `irmosaic eval`.
# Usage: scripts/run-sample.sh [OUTPUT_DIR]     (default: out/sample)
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install-deps.sh
build_dir=${BUILD_DIR:-build}
out=${1:-out/sample}
cmake -S . -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo >/dev/null
cmake --build "$build_dir" -j2 --target irmosaic_cli
irmosaic="$build_dir/cli/irmosaic"
mkdir -p "$out"
"$irmosaic" synth --config samples/sample_flight/flight.json --out "$out/flight"
"$irmosaic" run --frames "$out/flight/frames.csv" --pos "$out/flight/pos.csv" \
  --camera "$out/flight/camera.json" --out "$out/flight.irmosaic" --overwrite
"$irmosaic" export "$out/flight.irmosaic" "$out/mosaic_utm.tif"
"$irmosaic" eval --truth "$out/flight/truth.json" "$out/flight.irmosaic/placements.json" \
  "$out/flight/pos_only.json" --json "$out/eval.json" --plot "$out/eval.png"
echo "run-sample: live store $out/flight.irmosaic (mosaic.vrt, or the .qlr in QGIS)"
echo "run-sample: exported $out/mosaic_utm.tif; accuracy $out/eval.json and $out/eval.png"
