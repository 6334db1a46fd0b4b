#include "cli/run_view.h"

#include <chrono>
#include <cmath>
#include <string>
#include <thread>

#include "base/format.h"
#include "base/text.h"
#include "calib/report.h"
#include "cli/progress.h"
#include "gcode/grbl_client.h"
#include "run/run_engine.h"

namespace gs360::cli {
namespace {

using Json = nlohmann::json;

double Number(const Json& j, const char* key, double fallback = -1.0) {
  return j.contains(key) && j[key].is_number() ? j[key].get<double>() : fallback;
}

long long Count(const Json& j, const char* key) {
  return j.contains(key) && j[key].is_number_integer() ? j[key].get<long long>() : 0;
}

std::string Text(const Json& j, const char* key) {
  return j.contains(key) && j[key].is_string() ? j[key].get<std::string>() : std::string();
}

bool Active(const Json& run) {
  const std::string state = Text(run, "state");
  return state == "running" || state == "starting";
}

// The API's view as the ProgressPrinter's input.
RunProgress ProgressOf(const Json& run) {
  RunProgress p;
  p.run_id = Count(run, "id");
  p.counts.total = Count(run, "probes_total") + Count(run, "probes_skipped");
  p.counts.captured = Count(run, "probes_done");
  p.counts.failed = Count(run, "probes_failed");
  p.counts.skipped = Count(run, "probes_skipped");
  p.elapsed_s = Number(run, "elapsed_s", 0.0);
  p.eta_s = Number(run, "eta_s");
  p.probes_per_hour = Number(run, "rate_per_h", 0.0);
  p.phase = Text(run, "phase");
  if (p.phase.empty()) p.phase = Text(run, "state");
  return p;
}

}  // namespace

// One checkpoint of a run that converges: "checkpoint at 750 probes: mean 0.0251 mm, > 50 deg
// 0.0412 mm, every target met (41 s)".
std::string CheckpointLine(const Json& c) {
  std::string line = "checkpoint at " + std::to_string(Count(c, "probes")) + " probes: ";
  if (Text(c, "state") != "done") return line + "failed: " + Text(c, "error");
  std::string met = "every target met";
  if (c.contains("targets") && c["targets"].is_array()) {
    for (const Json& t : c["targets"]) {
      if (!t.is_object()) continue;
      const std::string name = Text(t, "name");
      const double value = Number(t, "value", std::nan(""));
      if (name == "mean depth error") line += "mean " + FormatFixed(value, 4) + " mm, ";
      if (name == "depth error seen > 50 deg")
        line += "> 50 deg " + FormatFixed(value, 4) + " mm, ";
      if (!t.value("pass", false))
        met = (met == "every target met" ? "misses " : met + ", ") + name;
    }
  }
  return line + met + " (" + FormatDuration(Number(c, "seconds", 0.0)) + ")";
}

void PrintConvergence(std::FILE* out, const Json& run) {
  if (!run.contains("convergence") || !run["convergence"].is_object()) return;
  const Json& c = run["convergence"];
  std::fprintf(out, "  until converged (rounds of %lld probes): %s%s%s\n",
               Count(c, "checkpoint_probes"), Text(c, "state").c_str(),
               Text(c, "verdict").empty() ? "" : ": ", Text(c, "verdict").c_str());
  if (c.contains("checkpoints") && c["checkpoints"].is_array()) {
    for (const Json& cp : c["checkpoints"]) {
      if (cp.is_object()) std::fprintf(out, "    %s\n", CheckpointLine(cp).c_str());
    }
  }
}

void PrintRun(std::FILE* out, const Json& run) {
  // Names and errors come from the database: an older one may hold control characters.
  std::string line = "run " + std::to_string(Count(run, "id")) + " " +
                     EscapeControlCharacters(Text(run, "name")) + "  " + Text(run, "state") + "  " +
                     std::to_string(Count(run, "probes_done")) + "/" +
                     std::to_string(Count(run, "probes_total")) + " probes (" +
                     std::to_string(Count(run, "probes_failed")) + " failed, " +
                     std::to_string(Count(run, "probes_skipped")) + " skipped)  elapsed " +
                     FormatDuration(Number(run, "elapsed_s", 0.0));
  if (Number(run, "eta_s") >= 0 && Text(run, "state") != "done") {
    line += "  ETA " + FormatDuration(Number(run, "eta_s"));
  }
  if (Number(run, "rate_per_h") > 0) {
    line += "  " + std::to_string(static_cast<long long>(Number(run, "rate_per_h"))) + " probes/h";
  }
  if (!Text(run, "machine_state").empty()) line += "  machine " + Text(run, "machine_state");
  if (!Text(run, "calibration").empty()) line += "  calibration " + Text(run, "calibration");
  std::fprintf(out, "%s\n", line.c_str());
  if (!Text(run, "last_error").empty()) {
    std::fprintf(out, "  last error: %s\n",
                 EscapeControlCharacters(Text(run, "last_error")).c_str());
  }
  PrintConvergence(out, run);
  if (!Text(run, "awaiting").empty()) {
    std::fprintf(out,
                 "  waiting for you to confirm its %s: after checking, `gs360 run resume %lld "
                 "--confirm %s`\n",
                 Text(run, "awaiting").c_str(), Count(run, "id"), Text(run, "awaiting").c_str());
  }
}

void PrintPlan(std::FILE* out, const Json& plan) {
  std::fprintf(out, "plan: %lld probes of %lld candidates, estimated %s of machine time\n",
               Count(plan, "probes_total"), Count(plan, "candidates"),
               FormatDuration(Number(plan, "estimate_s", 0.0)).c_str());
  if (plan.contains("dropped") && plan["dropped"].is_object()) {
    std::string dropped;
    for (const auto& [reason, n] : plan["dropped"].items()) {
      if (n.is_number_integer() && n.get<long long>() > 0) {
        dropped += " " + reason + " " + std::to_string(n.get<long long>());
      }
    }
    if (!dropped.empty()) std::fprintf(out, "  dropped:%s\n", dropped.c_str());
  }
  if (plan.contains("advice") && plan["advice"].is_array()) {
    for (const Json& line : plan["advice"]) {
      if (line.is_string()) std::fprintf(out, "  advice: %s\n", line.get<std::string>().c_str());
    }
  }
  if (plan.contains("coverage_gaps")) PrintCoverageGaps(out, plan["coverage_gaps"]);
}

void PrintCoverageGaps(std::FILE* out, const Json& gaps) {
  if (!gaps.is_array()) return;
  // Where nothing will be probed, before the run: the model will not know those parts.
  constexpr std::size_t kShown = 5;  // the largest; the rest are patches of a few candidates
  for (std::size_t i = 0; i < gaps.size() && i < kShown; ++i) {
    std::fprintf(out, "  not probed: %s\n", Text(gaps[i], "text").c_str());
  }
  if (gaps.size() > kShown) {
    std::fprintf(out, "  not probed: %zu more places, smaller (the plan's coverage_gaps)\n",
                 gaps.size() - kShown);
  }
}

int ExitCodeOfRun(const Json& run) {
  if (Text(run, "state") == "done") return kExitOk;
  return Text(run, "awaiting").empty() ? kExitRunStopped : kExitAwaiting;
}

bool RunIsActive(const Json& run) {
  return Active(run);
}

Json FollowPastChecks(DaemonClient& client, std::int64_t run_id) {
  const std::string path = "/api/v1/runs/" + std::to_string(run_id);
  Json run = client.Get(path);
  // Connecting, homing or verifying the position, re-checking probes: each may end the session
  // with a question. Once a probe is being pressed the resume has taken.
  while (Active(run) && Text(run, "phase") != "probing") {
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    run = client.Get(path);
  }
  return run;
}

Json WatchRun(DaemonClient& client, std::int64_t run_id, std::FILE* out, std::FILE* progress_out) {
  ProgressPrinter printer(progress_out);
  const std::string path = "/api/v1/runs/" + std::to_string(run_id);
  Json run = client.Get(path);
  // A start was just accepted: give the daemon a moment to mark the run running.
  for (int i = 0; i < 20 && !Active(run) && Text(run, "state") == "created"; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    run = client.Get(path);
  }
  std::size_t checkpoints = 0;  // of a run that converges: each new one is said as it comes
  const auto new_checkpoints = [&] {
    if (!run.contains("convergence") || !run["convergence"].is_object()) return;
    const Json& list = run["convergence"].value("checkpoints", Json::array());
    for (; checkpoints < list.size(); ++checkpoints) {
      if (!list[checkpoints].is_object()) continue;
      std::fprintf(progress_out, "\n  %s\n", CheckpointLine(list[checkpoints]).c_str());
    }
  };
  while (Active(run)) {
    new_checkpoints();
    printer.Update(ProgressOf(run));
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
    run = client.Get(path);
  }
  printer.Finish();
  PrintRun(out, run);
  return run;
}

Json WatchCalibration(DaemonClient& client, std::int64_t run_id, std::FILE* out) {
  const std::string path = "/api/v1/runs/" + std::to_string(run_id) + "/calibration";
  const auto t0 = std::chrono::steady_clock::now();
  std::string last_stage;
  Json view;
  for (;;) {
    view = client.Get(path);
    const std::string stage = Text(view, "stage");
    if (!stage.empty() && stage != last_stage) {
      std::string state;
      for (const auto& s : view.value("stages", Json::array())) {
        if (Text(s, "name") == stage) state = Text(s, "state");
      }
      const double t = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      std::fprintf(out, "  [%7.1f s] %-12s %s\n", t, stage.c_str(), state.c_str());
      std::fflush(out);
      last_stage = stage;
    }
    if (Text(view, "state") != "running") break;
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
  }
  std::fprintf(out, "\nstages:\n");
  for (const auto& s : view.value("stages", Json::array())) {
    std::fprintf(out, "  %-12s %-8s %8.2f s\n", Text(s, "name").c_str(), Text(s, "state").c_str(),
                 Number(s, "seconds", 0.0));
  }
  for (const auto& s : view.value("stages", Json::array())) {
    const std::string lens = s.contains("metrics") ? FormatIntrinsics(s["metrics"]) : "";
    if (Text(s, "name") == "intrinsics" && !lens.empty()) std::fprintf(out, "\n%s", lens.c_str());
  }
  const bool validated =
      view.contains("validation") && view["validation"].is_object() && !view["validation"].empty();
  if (Text(view, "state") == "done" && !validated) {
    std::fprintf(out, "\ncalibration done up to the stage asked for; no model exported\n");
  } else if (Text(view, "state") == "done") {
    std::fprintf(out, "\n%s", FormatValidationTable(view["validation"]).c_str());
    std::fprintf(out, "\n%s", FormatTargetsAndWarnings(view["validation"]).c_str());
  } else {
    std::fprintf(out, "\ncalibration %s: %s\n", Text(view, "state").c_str(),
                 Text(view, "error").c_str());
  }
  return view;
}

}  // namespace gs360::cli
