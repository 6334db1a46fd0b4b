#!/usr/bin/env bash
# The sanitizer part of `scripts/setup.sh test`, which runs it after the Release suite (it can also
# be run on its own once the packages are installed):
#   scripts/sanitize.sh [--build] [asan|tsan]...   default: both
#   scripts/sanitize.sh --fuzzers                  only the fuzz targets (scripts/fuzz.sh)
# asan: ASan + UBSan build (clang) in build-asan/, tsan: ThreadSanitizer build (GCC) in
# build-tsan/ (both beside BUILD_DIR; CMake option GS360_SANITIZE). Each builds only the test
# executables it runs, then runs its selection below through CTest. Any sanitizer report, in a
# test or in a process that a test started (gs360d, gs360, the storage kill writer), fails the
# script. The ASan + UBSan folder also builds the libFuzzer targets (scripts/fuzz.sh runs them):
# they need the same clang, ASan and UBSan build of the same libraries, which is then compiled
# once. --build: configure and build only (scripts/setup.sh builds in the background while the
# Release tests run; a later run without it finds everything built).
# Environment: BUILD_DIR (default build), JOBS (default nproc), GS360_FUZZ=0: no fuzz targets,
# GS360_FUZZ_SECONDS (scripts/fuzz.sh).
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
build_dir=${BUILD_DIR:-$here/build}
parent=$(dirname "$build_dir")
jobs=${JOBS:-$(nproc)}

# ---- The selection: which tests run under which sanitizer, and why. -----------------------------
# CTest names are "<module>:<TEST_CASE name>"; -R and -E below are regexes on them. The Python,
# browser and format tests never run here: they exercise no C++ that the C++ tests do not.
#
# ASan + UBSan: the unit tests of the libraries, less the few that repeat one workload for
# minutes (times: under ASan + UBSan on the 2-core VM). Not the cli:, run: and daemon: tests: they run
# the whole pipeline end to end (1-6 min each under ASan) and would need gs360_cli, gs360_daemon,
# gs360 and gs360d built a third time; the daemon's code runs under TSan below.
asan_targets="test_base test_geometry test_storage test_plan test_gcode test_sim test_capture test_recon test_calib"
asan_cmake=(-DGS360_FUZZ=OFF -DGS360_TEST_SOURCES=)
if [ "${GS360_FUZZ:-1}" != 0 ]; then
  asan_targets+=" gs360_fuzzers"
  asan_cmake=(-DGS360_FUZZ=ON -DGS360_FUZZ_SECONDS="${GS360_FUZZ_SECONDS:-60}"
    -DGS360_TEST_SOURCES=)
fi
asan_include='^(base|geometry|storage|plan|gcode|sim|capture|recon|calib):'
asan_exclude=(
  # 230 s: 60 SIGKILLed writer processes; the writer's code runs in the run_database tests.
  '^storage:SIGKILLed writers never leave a half-written probe$'
  # 150 s, 38 s: a fine gel mesh pressed many times, a dense sphere; the same code runs in the
  # smaller recon tests.
  '^recon:Normal indentation: the gel'
  '^recon:A dent in a sphere seen from inside'
  # 100 s, 17 s, 16 s: pose from simulated impressions; the other EstimateCamFromSensor tests
  # cover the code.
  '^calib:EstimateCamFromSensor: (simulated impressions|oblique impressions|the bias model)'
  # 75 s: two whole calibrations; it runs under TSan (the parallel stages), and each stage has
  # its own unit tests here.
  '^calib:calibration stages: a second run is all cache'
  # 31 s, 17 s, 15 s, 11 s: lens calibrations on many rendered boards; "rejects blank images"
  # and the checkerboard corner test run the same code on fewer.
  '^calib:CalibrateIntrinsics (recovers a perturbed|rejects boards only at the centre|rejects too few)'
  '^sim:checkerboard: cv::fisheye::calibrate recovers'
  # 66 s, 16 s: brute force against the BVH over thousands of rays; the other Bvh tests cover
  # the code.
  '^geometry:Bvh (closest hit equals brute force|gives exactly the brute-force)'
  # 27 s, 20 s: every shape rendered, renders repeated; the other tactile camera tests render.
  '^sim:tactile camera: (every built-in shape|the same seed and calls)'
  # 25 s, 17 s, 15 s: whole plans of thousands of candidates; the smaller plan tests run the
  # same filters.
  '^plan:(A plan counts every candidate once|The tour is a deterministic|Unreachable points are dropped)'
  # 203 s, 173 s, 116 s, 81 s, 23 s (3-4 s each in Release: the sanitizers slow the planner's
  # tight loops 40-fold): whole plans of GelTip-like meshes for the reach, travel and stylus
  # advice, and one plan per shape sized in time; "A closed solid's flat base is dropped", "A
  # plan that keeps little says which setting" and the plan-says tests run the same filters,
  # advice and sizing on smaller plans.
  '^plan:(Presses spanning more than the Z travel|A stylus too short for the lower part|A closed GelTip-like solid plans|A finger beyond the machine.s reach|A plan sized in machine time fills)'
  # 117 s, 74 s: pose inputs from many rendered dome and spread impressions; the other
  # FindImpressionRegion and EstimateCamFromSensor tests run the same code on fewer frames.
  '^calib:(FindImpressionRegion: a dome.s face-on|EstimateCamFromSensor: impressions spread far)'
  # 58 s, 33 s: thousands of rendered null frames for a false-accept rate, a dwell's renders
  # compared; the other PressCheck and tactile camera tests run the same code.
  '^capture:PressCheck: frames without an impression pass at the false-accept rate$'
  "^sim:tactile camera: a dwell's frames reuse the patch"
)
# With these left out the ASan + UBSan tests take 290 s on the two cores (a fresh clone's CI,
# docs/benchmarks.md "CI time").
# TSan: the tests whose code runs threads, by name: a TSan process takes 2-5 s to start and a
# run on the virtual rig ~1 min, so rather than whole modules these, one or a few per threaded
# part (the others exercise the same threads again, or none):
tsan_targets="test_storage test_gcode test_sim test_capture test_recon test_calib test_daemon"
tsan_tests=(
  # the daemon: the event hub's waiters; an in-process daemon's engine thread paused and resumed
  # from the HTTP handler threads, two resumes at once; gs360d stopped by SIGTERM. (Not the run_engine
  # tests "the engine runs on its own thread..." and "stop, pause and cancel...": their
  # in-process virtual camera renders too slowly under TSan, every press times out waiting for
  # its frames and the test fails with no TSan report.)
  '^daemon:the event hub delivers in order'
  '^daemon:api: plan, start, pause and resume a run'
  '^daemon:gs360d on SIGTERM'
  # the HTTP server's I/O thread, its two handler pools, event streams woken by publishers, the
  # request-time sweeper, and its stop with streams and handlers under way
  '^daemon:api: idle sockets, slow senders and many event streams'
  '^daemon:api: chunked bodies are cut'
  # the notifiers' threads and queues against receivers that fail, hang or are not there, and a
  # command's child; the feed from the event hub in a running daemon
  '^daemon:notify: a receiver that fails'
  '^daemon:notify: a command gets'
  '^daemon:notify: a run tells the webhook'
  # storage: status readers on their own connections while the writer commits; the background
  # capture committer beside the run loop's own writes
  '^storage:readers on other connections'
  '^storage:the committer commits every capture'
  '^storage:a failed background commit'
  # the GRBL client's reader thread against the virtual CNC's firmware and I/O threads
  '^gcode:client and virtual CNC:'
  # the Marlin machine's worker thread against the virtual printer's firmware and I/O threads
  '^gcode:MarlinMachine: '
  '^gcode:the client streams over TCP'
  '^sim:Fault: '
  # the capture frame server and its socket client
  '^capture:socket frame source'
  # recon: the threaded Poisson solver, the surface map's parallel rows
  '^recon:DST-I Poisson solver is safe from several threads'
  '^recon:Surface map of a flat plate'
  # calibration: the parallel stages of two whole calibrations (the longest, ~4 min), the
  # training and pose thread pools
  '^calib:calibration stages:'
  '^calib:Train is reproducible for a seed and thread count'
  '^calib:Train handles tiny batches and more threads than samples'
  '^calib:EstimateCamFromSensor: exact projections'
  # the virtual camera's parallel render
  '^sim:tactile camera: the same seed and calls give identical images'
)
# The files those tests are in: the TSan build compiles only these of the test folders' *_test.cc
# (CMake's GS360_TEST_SOURCES). A name above that matches no test fails the run.
tsan_sources=(
  daemon_parts_test.cc api_test.cc kill_resume_test.cc http_server_test.cc notifier_test.cc
  notify_run_test.cc concurrency_test.cc capture_committer_test.cc
  virtual_cnc_integration_test.cc marlin_machine_test.cc grbl_client_test.cc virtual_cnc_test.cc
  frame_server_test.cc integration_test.cc surface_map_test.cc stages_test.cc pipeline_test.cc
  train_test.cc pose_test.cc camera_render_test.cc
)
# -------------------------------------------------------------------------------------------------

join() {
  local IFS='|'
  echo "$*"
}

# check_selection DIR PATTERN...: each pattern names at least one of DIR's tests
check_selection() {
  local dir=$1 p n missing=0
  shift
  for p in "$@"; do
    n=$( (cd "$dir" && ctest -N -R "$p") | grep -c 'Test *#' || true)
    if [ "$n" = 0 ]; then
      echo "sanitize: no test matches '$p' (renamed or moved? see scripts/sanitize.sh)" >&2
      missing=1
    fi
  done
  return $missing
}

# build_sanitized NAME SANITIZE "TARGETS" [CMAKE_ARG...]: configures and builds build-NAME
build_sanitized() {
  local name=$1 sanitize=$2 targets=$3
  shift 3
  local dir=$parent/build-$name
  local start=$SECONDS
  echo "sanitize: $name (-fsanitize=$sanitize) in $dir"
  # ASan + UBSan with clang: GCC 12's UBSan instrumentation makes it compile the project in 1.35
  # times clang's time (834 s against 622 s on the 2-core VM), clang's UBSan also checks array
  # bounds through pointers, and the fuzz build uses clang anyway. TSan with GCC: clang is no
  # faster there (653 s against 631 s), and its template code in our binaries, called from
  # Debian's uninstrumented cpp-httplib, gives false reports. A folder configured with the other
  # compiler is configured afresh.
  local cc=gcc cxx=g++
  [ "$name" != asan ] || { cc=clang; cxx=clang++; }
  if [ -f "$dir/CMakeCache.txt" ] &&
    ! grep -q "^CMAKE_CXX_COMPILER:[A-Z]*=.*/$cxx\$" "$dir/CMakeCache.txt"; then
    rm -rf "$dir"
  fi
  # Warnings are the Release build's job (GCC, -Werror).
  CC=$cc CXX=$cxx cmake -S "$here" -B "$dir" -DCMAKE_BUILD_TYPE=Release \
    -DGS360_SANITIZE="$sanitize" -DGS360_WERROR=OFF "$@"
  # shellcheck disable=SC2086
  cmake --build "$dir" -j "$jobs" --target $targets
  echo "sanitize: $name: build $((SECONDS - start)) s"
}

# test_sanitized NAME INCLUDE [EXCLUDE...]: runs the selection in build-NAME
test_sanitized() {
  local name=$1 include=$2
  shift 2
  local dir=$parent/build-$name
  local logs=$dir/sanitizer-reports
  local start=$SECONDS
  rm -rf "$logs" && mkdir -p "$logs"
  local exclude=()
  [ $# -eq 0 ] || exclude=(-E "$(join "$@")")
  local rc=0
  (
    cd "$dir"
    # Reports go to files (log_path), so that those of child processes, whose stderr the tests
    # keep in temporary folders, are seen too.
    common="halt_on_error=1:log_path=$logs/report"
    export ASAN_OPTIONS="$common:detect_leaks=1:check_initialization_order=1"
    export LSAN_OPTIONS="suppressions=$here/tests/lsan.supp:print_suppressions=0"
    export UBSAN_OPTIONS="$common:print_stacktrace=1"
    export TSAN_OPTIONS="$common:suppressions=$here/tests/tsan.supp:second_deadlock_stack=1"
    # Instrumented code on a shared machine runs several times slower: the tests' deadlines that
    # only catch a hang (and the virtual camera's capture timeout) scale by this (tests/wait.h).
    export GS360_TEST_TIME_SCALE=4
    ctest --output-on-failure -j "$jobs" -R "$include" "${exclude[@]}"
  ) || rc=$?
  local reports=("$logs"/report.*)
  if [ -e "${reports[0]}" ]; then
    echo "sanitize: $name: ${#reports[@]} sanitizer report(s):" >&2
    for r in "${reports[@]}"; do
      echo "---- $r" >&2
      cat "$r" >&2
    done
    rc=1
  fi
  echo "sanitize: $name: tests $((SECONDS - start)) s"
  return $rc
}

if [ "${1:-}" = --fuzzers ]; then
  build_sanitized asan address,undefined gs360_fuzzers -DGS360_FUZZ=ON \
    -DGS360_FUZZ_SECONDS="${GS360_FUZZ_SECONDS:-60}"
  exit 0
fi
build_only=0
if [ "${1:-}" = --build ]; then
  build_only=1
  shift
fi
which=("$@")
[ ${#which[@]} -gt 0 ] || which=(asan tsan)
status=0
for w in "${which[@]}"; do
  case "$w" in
    asan)
      build_sanitized asan address,undefined "$asan_targets" ${asan_cmake[@]+"${asan_cmake[@]}"}
      [ $build_only = 1 ] ||
        test_sanitized asan "$asan_include" "${asan_exclude[@]}" || status=1
      ;;
    tsan)
      # Its few test files each on their own: batched, they would make unity batches that no
      # other build compiles (GS360_UNITY_TESTS; a helper's name clash would show only here).
      build_sanitized tsan thread "$tsan_targets" \
        -DGS360_TEST_SOURCES="$(IFS=';' && echo "${tsan_sources[*]}")" -DGS360_UNITY_TESTS=OFF
      if [ $build_only = 0 ]; then
        check_selection "$parent/build-tsan" "${tsan_tests[@]}" || status=1
        test_sanitized tsan "$(join "${tsan_tests[@]}")" || status=1
      fi
      ;;
    *)
      echo "sanitize: unknown '$w' (expected asan or tsan)" >&2
      exit 2
      ;;
  esac
done
exit $status
