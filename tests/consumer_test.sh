#!/usr/bin/env bash
# Installs the build into a temporary prefix, builds samples/consumer against the installed
# CMake package and runs it. Usage: consumer_test.sh BUILD_DIR SOURCE_DIR
set -euo pipefail
build_dir=$1
source_dir=$2
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cmake --install "$build_dir" --prefix "$work/prefix" >/dev/null
cmake -S "$source_dir/samples/consumer" -B "$work/build" -G Ninja \
  -DCMAKE_BUILD_TYPE=Release -DCMAKE_PREFIX_PATH="$work/prefix" >/dev/null
cmake --build "$work/build" -j1 >/dev/null
# The installed CLI must find the installed library through its RPATH.
"$work/prefix/bin/irmosaic" --version
mkdir "$work/out"
"$work/build/consumer" "$work/out"
