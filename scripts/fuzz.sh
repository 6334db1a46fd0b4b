#!/usr/bin/env bash
# The fuzzing part of `scripts/setup.sh test` (it can also be run on its own once the packages,
# clang among them, are installed):
#   scripts/fuzz.sh                build the libFuzzer targets (tests/fuzz) with clang, ASan and
#                                  UBSan in build-fuzz/ beside BUILD_DIR, then run each through
#                                  CTest (label fuzz) on a fixed number of inputs from a fixed
#                                  seed (about 15 s each; at most GS360_FUZZ_SECONDS, default 60)
#   scripts/fuzz.sh NAME SECONDS   the same build, then one target (grbl_line, gcode_line,
#                                  daemon_config, model_bundle, mesh or frame) for longer; its
#                                  corpus keeps growing in build-fuzz/tests/fuzz/corpus/NAME
# A crash, a sanitizer report, an uncaught exception or a timeout fails the run and leaves the
# input in build-fuzz/tests/fuzz/fuzz-artifacts/. Environment: BUILD_DIR (default build), JOBS.
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
build_dir=${BUILD_DIR:-$here/build}
fuzz_dir=$(dirname "$build_dir")/build-fuzz
jobs=${JOBS:-$(nproc)}
seconds=${GS360_FUZZ_SECONDS:-60}

if ! command -v clang++ > /dev/null; then
  echo "fuzz: clang++ is not installed (apt-get install clang; scripts/setup.sh test installs it)" >&2
  exit 1
fi
# Not the tests, the Python module or libcamera: only what the fuzzers link is built.
mkdir -p "$fuzz_dir"
CC=clang CXX=clang++ cmake -S "$here" -B "$fuzz_dir" -DCMAKE_BUILD_TYPE=Release -DGS360_FUZZ=ON \
  -DGS360_BUILD_TESTS=OFF -DGS360_WITH_LIBCAMERA=OFF -DGS360_NATIVE=OFF -DGS360_WERROR=OFF \
  -DGS360_FUZZ_SECONDS="$seconds" > "$fuzz_dir/configure.log" ||
  { cat "$fuzz_dir/configure.log"; exit 1; }
cmake --build "$fuzz_dir" -j "$jobs" --target gs360_fuzzers

export ASAN_OPTIONS=detect_leaks=1
export UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
export LSAN_OPTIONS="suppressions=$here/tests/lsan.supp:print_suppressions=0"
if [ $# -ge 1 ]; then
  name=$1
  run_seconds=${2:-600}
  target="$fuzz_dir/tests/fuzz/fuzz_$name"
  [ -x "$target" ] || { echo "fuzz: no target '$name'" >&2; exit 2; }
  work="$fuzz_dir/tests/fuzz/corpus/$name"
  artifacts="$fuzz_dir/tests/fuzz/fuzz-artifacts"
  mkdir -p "$work" "$artifacts"
  exec "$target" -max_total_time="$run_seconds" -timeout=10 -rss_limit_mb=2048 -max_len=65536 \
    -print_final_stats=1 -artifact_prefix="$artifacts/$name-" "$work" "$here/tests/fuzz/corpus/$name"
fi
(cd "$fuzz_dir" && ctest --output-on-failure -L fuzz -j "$jobs")
