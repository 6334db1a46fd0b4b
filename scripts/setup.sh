#!/usr/bin/env bash
# gs360 set-up: installs the Debian packages the project needs (only the missing ones), builds in
# Release, then does what was asked:
#   scripts/setup.sh test    build and run the whole test suite through CTest, then the
#                            ASan+UBSan and TSan builds on their selections (scripts/sanitize.sh)
#                            and a bounded run of each libFuzzer target (scripts/fuzz.sh)
#   scripts/setup.sh demo    build and run `gs360 demo` (the simulated rig, end to end)
#   scripts/setup.sh build   install and build only
#   scripts/setup.sh package build the .deb to distribute (build-package/gs360_<version>_<arch>.deb:
#                            a portable build, GS360_NATIVE=OFF, prefix /usr) and check it
#                            (scripts/check_package.sh)
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
# The package's checks (scripts/check_package.sh): lintian, dpkg-shlibdeps for its dependencies,
# systemd-analyze for its unit and man for its pages.
if [ "$mode" = test ] || [ "$mode" = package ]; then
  packages+=(lintian dpkg-dev systemd man-db)
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

if [ "$mode" = package ]; then
  # Its own build folder: the binaries of a package must run on any x86-64 CPU, not only this
  # one's (GS360_NATIVE=OFF), and only what is installed is built.
  package_dir=${PACKAGE_BUILD_DIR:-$here/build-package}
  cmake -S "$here" -B "$package_dir" -DCMAKE_BUILD_TYPE=Release -DGS360_NATIVE=OFF \
    -DGS360_BUILD_TESTS=OFF -DCMAKE_INSTALL_PREFIX=/usr
  cmake --build "$package_dir" -j "$jobs" --target gs360_installables
  (cd "$package_dir" && cpack --config CPackConfig.cmake)
  deb=$(ls "$package_dir"/gs360_*.deb)
  "$here/scripts/check_package.sh" "$package_dir" "$deb"
  echo "setup: package $deb"
  exit 0
fi

# The test mode's sequence. The Release tests leave a third of the two cores idle (processes
# starting, daemons waiting for the virtual rig) and the sanitizer tests some too: the sanitizer
# builds use that, in the background at the lowest priority (their own session's scheduling
# group at nice 19, so that the tests' deadlines see no difference), one after the other: ASan +
# UBSan with the fuzz targets, then TSan. Each part's tests start once its build is there.
background_builds() {
  local builds=()
  if [ "${GS360_SANITIZERS:-1}" != 0 ]; then
    builds=(asan tsan)
  elif [ "${GS360_FUZZ:-1}" != 0 ]; then
    builds=(fuzzers)
  fi
  [ ${#builds[@]} -gt 0 ] || return 0
  mkdir -p "$bg_dir"
  rm -f "$bg_dir"/*.rc "$bg_dir"/*.log
  # shellcheck disable=SC2016
  setsid bash -c '
    echo 19 > /proc/self/autogroup 2> /dev/null || true
    for b in "${@:2}"; do
      if [ "$b" = fuzzers ]; then arg=(--fuzzers); else arg=(--build "$b"); fi
      rc=0
      nice -n 19 "$1/scripts/sanitize.sh" "${arg[@]}" > "$BG_DIR/$b.log" 2>&1 || rc=$?
      echo $rc > "$BG_DIR/$b.rc"
      [ $rc = 0 ] || exit $rc
    done' _ "$here" "${builds[@]}" &
  bg_pid=$!
}

# await_build NAME: waits for the background build NAME, shows its log, fails if it failed
await_build() {
  [ -n "$bg_pid" ] || return 0
  local waited=$SECONDS
  while [ ! -f "$bg_dir/$1.rc" ]; do
    if ! kill -0 "$bg_pid" 2> /dev/null; then
      echo "setup: the background $1 build stopped without a status" >&2
      return 1
    fi
    sleep 2
  done
  cat "$bg_dir/$1.log"
  echo "setup: waited $((SECONDS - waited)) s for the $1 build"
  [ "$(cat "$bg_dir/$1.rc")" = 0 ] || { echo "setup: the $1 build failed" >&2; return 1; }
}

stop_background() {
  [ -z "$bg_pid" ] || kill -- -"$bg_pid" 2> /dev/null || true
}

run_tests() {
  bg_dir=$(dirname "$build_dir")/build-background
  bg_pid=
  export BG_DIR=$bg_dir
  trap stop_background EXIT
  trap 'exit 130' INT
  trap 'exit 143' TERM
  background_builds
  (cd "$build_dir" && ctest --output-on-failure -j "$jobs" "$@")
  # Then the sanitizer builds' selections of the tests (scripts/sanitize.sh), and each fuzz
  # target on its seed corpus for a bounded time (scripts/fuzz.sh).
  if [ "${GS360_SANITIZERS:-1}" != 0 ]; then
    await_build asan
    "$here/scripts/sanitize.sh" asan
    if [ "${GS360_FUZZ:-1}" != 0 ]; then
      "$here/scripts/fuzz.sh"
    fi
    await_build tsan
    "$here/scripts/sanitize.sh" tsan
  elif [ "${GS360_FUZZ:-1}" != 0 ]; then
    await_build fuzzers
    "$here/scripts/fuzz.sh"
  fi
}

cmake -S "$here" -B "$build_dir" -DCMAKE_BUILD_TYPE=Release
cmake --build "$build_dir" -j "$jobs"

case "$mode" in
  build) ;;
  test)
    run_tests "$@"
    ;;
  demo)
    "$build_dir/cli/gs360" demo "$@"
    ;;
  *)
    echo "setup: unknown mode '$mode' (expected build, test, demo or package)" >&2
    exit 2
    ;;
esac
