#!/usr/bin/env bash
# Installs every build, test and client dependency of irmosaic from Debian packages.
# Idempotent: when everything is present it only checks and returns in a second or two.
# Usage: sudo scripts/install-deps.sh [--with-qgis]   (QGIS is for the headless client tests)
set -euo pipefail

packages=(
  build-essential cmake ninja-build pkg-config clang-format
  libgdal-dev gdal-bin python3-gdal libproj-dev proj-bin
  libgeographiclib-dev libopencv-dev libeigen3-dev libceres-dev
  libgtest-dev libgmock-dev nlohmann-json3-dev libzstd-dev libtiff-dev
  python3-numpy python3-matplotlib pybind11-dev python3-pytest
  clang libclang-rt-14-dev  # clang++ with libFuzzer and the sanitizers: fuzz.sh, sanitize.sh, tsan.sh
)
if [[ "${1:-}" == "--with-qgis" || "${IRMOSAIC_WITH_QGIS:-0}" == "1" ]]; then
  packages+=(python3-qgis qgis-providers)
fi

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

if ((${#missing[@]} == 0)); then
  echo "install-deps: all ${#packages[@]} packages present"
  exit 0
fi

echo "install-deps: installing ${missing[*]}"
SUDO=""
if [[ $(id -u) -ne 0 ]]; then SUDO="sudo"; fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
echo "install-deps: done"
