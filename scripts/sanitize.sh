#!/usr/bin/env bash
# Runs the whole test suite under AddressSanitizer + UndefinedBehaviorSanitizer (build-asan/),
# then the threaded tests under ThreadSanitizer (scripts/tsan.sh, build-tsan/). Exits non-zero on
# any sanitizer report or test failure. CI runs it (.ci/run); docs/reliability.md says more.
# Usage: scripts/sanitize.sh [asan|tsan|all]        (default all)
#
# Cost: the ASan build is compiled by Clang at -O1 (-g1 for line numbers in reports) without the
# benchmarks; every test program, Python test and QGIS test is built and run. Clang, not GCC:
# the same build took 266 s instead of 490 s on 2 cores (session 44, docs/reliability.md).
set -euo pipefail
cd "$(dirname "$0")/.."
what="${1:-all}"

run_asan() {
  local build="${ASAN_BUILD_DIR:-build-asan}"
  local start=$SECONDS
  # A folder configured by another compiler (GCC before session 44) is made again.
  if [[ -f "$build/CMakeCache.txt" ]] && ! grep -q '^CMAKE_CXX_COMPILER:[A-Z]*=.*clang++' \
    "$build/CMakeCache.txt"; then
    rm -rf "$build"
  fi
  cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCMAKE_CXX_COMPILER=clang++ \
    -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O1 -g1" -DIRMOSAIC_SANITIZE=ON -DIRMOSAIC_WERROR=ON \
    -DIRMOSAIC_BUILD_BENCH=OFF >/dev/null
  cmake --build "$build" -j2
  echo "sanitize: asan build $((SECONDS - start)) s"
  start=$SECONDS
  # UBSan findings abort (-fno-sanitize-recover in CMakeLists.txt); ASan reports abort too.
  export UBSAN_OPTIONS="print_stacktrace=1:halt_on_error=1"
  # Tests hosted by programs that are not instrumented (python3 and QGIS loading the ASan-built
  # module or GDAL plug-in, gdalinfo loading the plug-in, the downstream consumer build): the
  # ASan runtime must be preloaded into them, and their own (Python, QGIS, compiler) leaks at
  # exit are not ours, so leak detection is off for these only.
  # docs_commands runs the README's and the docs' Python blocks (python3 importing the module)
  # and gdalinfo/ogrinfo through the plug-in, so it is hosted too.
  local hosted='^(python_bindings|python_pipeline_sample|qgis_store|qgis_gdal_plugin|install_consumer|docs_commands|GdalDriverTest\.(GdalToolsLoadThePlugInAndAgreeWithMosaicVrt|OgrinfoListsTheFootprintsLayerWithItsFeatureCount))$'
  # Left to the plain suite (scripts/test.sh) and the fault campaign (scripts/faults.sh): the two
  # kill -9 + --resume runs of the CLI, 136-144 s each under ASan (21-24 s plain), the longest
  # of the run (CI of 8ed7454). Their code under ASan is exercised by the resume tests of
  # MosaickerApiTest (AResumedStoreHoldsEveryRecordedPlacement...) and TileStoreTest
  # (KillNineMidPublishLeavesALoadableStoreThatResumes), and the CLI's run by RunCliTest's others.
  # Likewise RunCliTest.AFramesGpkgLockedPastTheEnd... (session 46; 15 s plain, two CLI runs and
  # the store's 10 s closing wait): the store's lock path runs under ASan in
  # TileStoreTest.AFramesGpkgLockedByAnotherProgramDefersItsRecordsNotThePublish.
  # Also left to the plain suite (CI of 9ec6e62, 2013 s in all, over the 30-minute budget):
  # docs_commands, 182 s under ASan (45 s plain), which runs the README's and the docs' commands
  # (the CLI on the sample, python3 blocks, gdalinfo) whose code the CLI, Python and plug-in tests
  # below run under ASan; and TileStoreTest.IndexWrittenPerPublishIsBoundedByTheChangeNotTheStore,
  # 85 s under ASan (8 s plain, ASan's allocator on 2,256 tiles' GDAL writes), which measures
  # index sizes: its publish / block-VRT code runs under ASan in every other TileStoreTest.
  # And TileStoreTest.LiveOverviewUpdatesRunInSlicesAndPublishesGoFirst, 39 s under ASan (3 s
  # plain; CI of b7b2756), which counts slices over 1,300 tile writes: its slice code runs
  # under ASan in TileStoreTest.PaintingDuringOverviewSlicesKeepsTheLastPaintedValues.
  # And (CI of 05074fa, 1936 s) the accuracy tests that repeat the same code over many pairs or
  # frames to measure a statistic, 15-41 s each under ASan (1.5-8 s plain), 195 s of test time
  # in all: ScdTest's two low-overlap campaigns (every other ScdTest runs the correlation under
  # ASan), FineRegistration's noisy thermal campaign (ThermalFramesComposeConsistently registers
  # the same frames under ASan), MapFusionTest's 1000-frame drift run (the corrupted-pair, short
  # solve and seam-lag tests run the optimizer under ASan; TSan runs the drift run itself),
  # MosaickerTest's gain-jump flight (gain compensation is on in every Mosaicker test),
  # RunCliTest's georeferencing check (the CLI's run stays under ASan in the store-refusal and
  # damaged-video tests) and TileStoreTest's manifest-size measurement (as the index-size test
  # above).
  local statistics='ScdTest\.(SimulatorFramesAtLowOverlapAndPsnr20|FifteenToTwentyFivePercentOverlapAtPsnr20)|FineRegistration\.ThermalFramesWithNoiseStayNearTheCleanResult|MapFusionTest\.OptimizationRemovesPosErrorAndDrift|MosaickerTest\.GainJumpsAreCompensatedAcrossOverlaps|RunCliTest\.MosaicIsGeoreferencedWhereTheTruthIs|TileStoreTest\.ManifestSizeFollowsTheBlocksNotTheTiles'
  local plain_only="^(RunCliTest\\.(KillNineThenResume.*|AFramesGpkgLockedPastTheEnd.*)|docs_commands|TileStoreTest\\.(IndexWrittenPerPublishIsBoundedByTheChangeNotTheStore|LiveOverviewUpdatesRunInSlicesAndPublishesGoFirst)|$statistics)\$"
  local status=0
  ASAN_OPTIONS="detect_leaks=1:abort_on_error=1:strict_string_checks=1:detect_stack_use_after_return=1" \
    ctest --test-dir "$build" --output-on-failure -j2 --timeout 900 -E "$hosted|$plain_only" ||
    status=1
  # libstdc++ is preloaded after the ASan runtime: python3 does not link it, and without it the
  # runtime's __cxa_throw interceptor finds no real __cxa_throw when PROJ throws inside QGIS.
  # Clang's shared ASan runtime, the one the build's programs link (CMakeLists.txt).
  LD_PRELOAD="$(clang++ -print-file-name="libclang_rt.asan-$(uname -m).so") $(gcc -print-file-name=libstdc++.so)" \
    ASAN_OPTIONS="detect_leaks=0:abort_on_error=1" \
    ctest --test-dir "$build" --output-on-failure -j2 --timeout 900 -R "$hosted" -E "$plain_only" || status=1
  echo "sanitize: asan+ubsan tests $((SECONDS - start)) s"
  return "$status"
}

run_tsan() {
  local start=$SECONDS
  bash scripts/tsan.sh
  echo "sanitize: tsan build and tests $((SECONDS - start)) s"
}

case "$what" in
  asan) run_asan ;;
  tsan) run_tsan ;;
  all)
    run_asan
    run_tsan
    ;;
  *)
    echo "usage: scripts/sanitize.sh [asan|tsan|all]" >&2
    exit 2
    ;;
esac
echo "sanitize: $what clean"
