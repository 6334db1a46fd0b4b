#pragma once
// Terminal views of the daemon's JSON (docs/api.md): one line per run, the plan summary, a live
// progress bar that follows a run until it stops, and a calibration followed stage by stage.

#include <cstdint>
#include <cstdio>

#include <nlohmann/json.hpp>

#include "cli/daemon_client.h"

namespace gs360::cli {

// "run 3 finger-07  running  812/2011 probes (3 failed, 0 skipped)  elapsed 1h 02m  ETA ..."
void PrintRun(std::FILE* out, const nlohmann::json& run);
// A run that converges: its state and verdict, one line per checkpoint. Nothing for another run.
void PrintConvergence(std::FILE* out, const nlohmann::json& run);
// The plan summary of a created run or of a plan_only answer.
void PrintPlan(std::FILE* out, const nlohmann::json& plan);
// "  not probed: ..." for the five largest of a plan's coverage_gaps (plan/coverage.h's JSON
// array), then how many smaller ones there are. Nothing for an empty or missing array.
void PrintCoverageGaps(std::FILE* out, const nlohmann::json& gaps);

// Draws the run's progress (a bar with rate and ETA on a terminal, a line every 10 s otherwise)
// on `progress_out` until the run is no longer active, then prints its final line on `out`.
// Returns the run's last view. Throws ClientError.
nlohmann::json WatchRun(DaemonClient& client, std::int64_t run_id, std::FILE* out,
                        std::FILE* progress_out);

// Follows the run's calibration until it ends, printing each stage as it starts on `out`, then
// the validation table and the targets. Returns the last calibration view. Throws ClientError.
nlohmann::json WatchCalibration(DaemonClient& client, std::int64_t run_id, std::FILE* out);

// After a start or resume was accepted: follows the run (without printing) until it is probing,
// past the checks that may stop it to ask the user something, or is no longer active. Returns
// its last view. Throws ClientError.
nlohmann::json FollowPastChecks(DaemonClient& client, std::int64_t run_id);

// Whether the run's session is on (starting or running).
bool RunIsActive(const nlohmann::json& run);

// The exit code a watched run ends with: 0 for done, kExitAwaiting when it stopped to ask the
// user to confirm something (PrintRun says what, and the command that answers it),
// kExitRunStopped otherwise.
int ExitCodeOfRun(const nlohmann::json& run);

}  // namespace gs360::cli
