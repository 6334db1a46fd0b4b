#!/usr/bin/env bash
# The kill loop: gs360d SIGKILLed at random moments of an acquisition on the virtual rig, resumed
# each time, then run to the end; every reachable probe must have exactly one frame, taken where
# the machine truly stood, and no resume may ask the user to confirm a position (nothing moved
# the machine by hand). It replays the CTest case "gs360d SIGKILLed at random moments" with other
# kill schedules:
#   scripts/kill_loop.sh [FIRST_SEED] [SEEDS] [ROUNDS]   default: 1 4 25 (100 kills)
#   scripts/kill_loop.sh --calibration [FIRST_SEED] [SEEDS] [ROUNDS]   default: 1 10 10 (100 kills)
# With --calibration it replays "gs360d SIGKILLed during calibrations" instead: one acquisition,
# calibrated once without a kill, then again with gs360d killed ROUNDS times at a random moment
# of a random stage; the final results must equal the uninterrupted calibration's.
# Each seed is one run of a few hundred probes (5-10 min on the 2-core VM). On a failure the
# test's folder (database, gs360d.log) is kept under /tmp/gs360-kill*, and the script stops.
# Environment: BUILD_DIR (default build; `scripts/setup.sh build` makes it).
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
build_dir=${BUILD_DIR:-$here/build}
test_name="gs360d SIGKILLed at random moments*"
what="every probe exactly once"
default_seeds=4
default_rounds=25
if [ "${1:-}" = "--calibration" ]; then
  shift
  test_name="gs360d SIGKILLed during calibrations*"
  what="calibration results equal to an uninterrupted calibration's"
  default_seeds=10
  default_rounds=10
fi
first=${1:-1}
seeds=${2:-$default_seeds}
rounds=${3:-$default_rounds}
test_bin=$build_dir/tests/daemon/test_daemon
[ -x "$test_bin" ] || { echo "kill_loop: $test_bin not built (scripts/setup.sh build)" >&2; exit 2; }

kills=0
for ((seed = first; seed < first + seeds; ++seed)); do
  start=$SECONDS
  log=$(mktemp /tmp/gs360-kill-loop-XXXXXX.log)
  GS360_KILL_SEED=$seed GS360_KILL_ROUNDS=$rounds GS360_KEEP_TEST_DIRS=1 \
    "$test_bin" "$test_name" >"$log" 2>&1 &
  pid=$!
  if wait $pid; then
    kills=$((kills + rounds))
    echo "seed $seed: $rounds kills, passed ($((SECONDS - start)) s)"
    rm -rf "$log" "${TMPDIR:-/tmp}"/gs360-kill*-$pid-*
  else
    echo "seed $seed: FAILED after $((SECONDS - start)) s; output in $log, the run's folder in" \
      "${TMPDIR:-/tmp}/gs360-kill*-$pid-0" >&2
    grep -E "FAILED|round [0-9]+:" "$log" | head -6 >&2 || true
    exit 1
  fi
done
echo "kill_loop: $kills kills over $seeds seeds, $what"
