#!/usr/bin/env bash
# Issue 11's fault campaign (tests/faults/fault_campaign.cc): 20 runs of `irmosaic run` on a
# simulated 40-frame flight killed with kill -9 at seeded random moments, each store read in GDAL
# (mosaic.vrt and the IRMOSAIC plug-in), resumed with --resume and compared with an
# uninterrupted run (0.5 px); then 4 reader processes reading the store during a run.
# Usage: scripts/faults.sh [RUNS] [SEED]     (build folder: build/, override with BUILD_DIR)
set -euo pipefail
cd "$(dirname "$0")/.."
build_dir=${BUILD_DIR:-build}
runs=${1:-20}
seed=${2:-11}
cmake --build "$build_dir" -j2 --target fault_campaign irmosaic_cli gdal_IRMOSAIC
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$build_dir/tests/fault_campaign" --cli "$build_dir/cli/irmosaic" \
  --plugin-dir "$build_dir/gdalplugins" --work "$work/campaign" --runs "$runs" --seed "$seed" \
  --json "$build_dir/fault_campaign.json"
