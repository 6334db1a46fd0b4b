#!/usr/bin/env bash
# gs360 set-up: installs the Debian packages the project needs (only the missing ones), builds in
# Release, then does what was asked:
#   scripts/setup.sh test    build and run the whole test suite through CTest, then the
#                            ASan+UBSan and TSan builds on their selections (scripts/sanitize.sh)
#                            and a bounded run of each libFuzzer target (scripts/fuzz.sh)
#   scripts/setup.sh demo    build and run `gs360 demo` (the simulated rig, end to end)
#   scripts/setup.sh build   install and build only
# Idempotent: a second run installs nothing and rebuilds only what changed.
# Environment: BUILD_DIR (default build), JOBS (default nproc), GS360_SKIP_APT=1 to skip apt,
# GS360_SANITIZERS=0 to skip the sanitizer builds in test mode, GS360_FUZZ=0 the fuzz targets.
set -euo pipefail

mode=${1:-build}
shift || true
here=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
build_dir=${BUILD_DIR:-$here/build}
jobs=${JOBS:-$(nproc)}

packages=(
  build-essential cmake pkg-config git
  catch2
  libeigen3-dev libspdlog-dev libfmt-dev
  libsqlite3-dev
  libopencv-dev
  libassimp-dev
  libserialport-dev
  libcamera-dev
  libfftw3-dev
  libonnx-dev libprotobuf-dev
  nlohmann-json3-dev libcpp-httplib-dev libmicrohttpd-dev libcli11-dev libtomlplusplus-dev
  libsystemd-dev
  pybind11-dev python3-dev python3-numpy
  curl
)
# Only the test mode needs these: the headless browser for the dashboard's test (tests/browser),
# clang-format for the format check (tests/CMakeLists.txt) and clang with its runtime libraries
# (libFuzzer, the sanitizers: only recommended by clang) for tests/fuzz.
if [ "$mode" = test ]; then
  packages+=(chromium clang-format clang libclang-rt-14-dev)
fi

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed'; then
    missing+=("$p")
  fi
done
if [ ${#missing[@]} -gt 0 ] && [ "${GS360_SKIP_APT:-0}" != 1 ]; then
  echo "setup: installing ${#missing[@]} Debian packages: ${missing[*]}"
  sudo_cmd=()
  [ "$(id -u)" -eq 0 ] || sudo_cmd=(sudo)
  export DEBIAN_FRONTEND=noninteractive
  "${sudo_cmd[@]}" apt-get update -q
  "${sudo_cmd[@]}" apt-get install -y -q --no-install-recommends "${missing[@]}"
fi

cmake -S "$here" -B "$build_dir" -DCMAKE_BUILD_TYPE=Release
cmake --build "$build_dir" -j "$jobs"

case "$mode" in
  build) ;;
  test)
    (cd "$build_dir" && ctest --output-on-failure -j "$jobs" "$@")
    # Then the sanitizer builds and their selections of the tests (scripts/sanitize.sh).
    if [ "${GS360_SANITIZERS:-1}" != 0 ]; then
      "$here/scripts/sanitize.sh"
    fi
    # And each fuzz target on its seed corpus for a bounded time (scripts/fuzz.sh).
    if [ "${GS360_FUZZ:-1}" != 0 ]; then
      "$here/scripts/fuzz.sh"
    fi
    ;;
  demo)
    "$build_dir/cli/gs360" demo "$@"
    ;;
  *)
    echo "setup: unknown mode '$mode' (expected build, test or demo)" >&2
    exit 2
    ;;
esac
