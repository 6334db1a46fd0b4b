#!/usr/bin/env bash
# The fuzzing part of `scripts/setup.sh test` (it can also be run on its own once the packages,
# clang among them, are installed):
#   scripts/fuzz.sh                build the libFuzzer targets (tests/fuzz) with clang, ASan and
#                                  UBSan in build-asan/ beside BUILD_DIR (scripts/sanitize.sh
#                                  --fuzzers), then run each through CTest (label fuzz) on a fixed
#                                  number of inputs from a fixed seed (about 15 s each; at most
#                                  GS360_FUZZ_SECONDS, default 60)
#   scripts/fuzz.sh NAME SECONDS   the same build, then one target (grbl_line, gcode_line,
#                                  daemon_config, model_bundle, mesh or frame) for longer; its
#                                  corpus keeps growing in build-asan/tests/fuzz/corpus/NAME
# A crash, a sanitizer report, an uncaught exception or a timeout fails the run and leaves the
# input in build-asan/tests/fuzz/fuzz-artifacts/. Environment: BUILD_DIR (default build), JOBS.
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
build_dir=${BUILD_DIR:-$here/build}
jobs=${JOBS:-$(nproc)}

if ! command -v clang++ > /dev/null; then
  echo "fuzz: clang++ is not installed (apt-get install clang; scripts/setup.sh test installs it)" >&2
  exit 1
fi
# In the ASan + UBSan folder of scripts/sanitize.sh (the same clang build of the libraries): only
# what the fuzzers link is built here.
fuzz_dir=$(dirname "$build_dir")/build-asan
"$here/scripts/sanitize.sh" --fuzzers

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
