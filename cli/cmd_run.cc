// `gs360 run start|resume|status|list`: the overnight run from a shell.

#include <csignal>
#include <cstdio>
#include <filesystem>

#include "cli/commands.h"
#include "cli/progress.h"
#include "cli/report.h"
#include "daemon/run_config.h"
#include "daemon/run_engine.h"

namespace gs360::cli {
namespace {

std::atomic<RunEngine*> g_engine{nullptr};

extern "C" void OnStopSignal(int) {
  // Async-signal-safe: one atomic store. The run finishes its probe, retracts, commits, exits.
  if (RunEngine* e = g_engine.load()) e->RequestStop();
}

int ExecuteWithProgress(RunEngine& engine, std::int64_t run_id,
                        const SessionOverrides& overrides = {}) {
  ProgressPrinter printer;
  engine.SetProgressCallback([&](const RunProgress& p) { printer.Update(p); });
  g_engine = &engine;
  struct sigaction sa {};
  sa.sa_handler = OnStopSignal;
  sigemptyset(&sa.sa_mask);
  struct sigaction old_term {
  }, old_int{};
  sigaction(SIGTERM, &sa, &old_term);
  sigaction(SIGINT, &sa, &old_int);
  RunReport report;
  try {
    // The run has its own thread; this one only waits (signals set a flag the run polls).
    engine.Start(run_id, overrides);
    report = engine.Wait();
  } catch (...) {
    g_engine = nullptr;
    sigaction(SIGTERM, &old_term, nullptr);
    sigaction(SIGINT, &old_int, nullptr);
    printer.Finish();
    throw;
  }
  g_engine = nullptr;
  sigaction(SIGTERM, &old_term, nullptr);
  sigaction(SIGINT, &old_int, nullptr);
  printer.Finish();
  std::printf(
      "run %lld %s: %s\n  this session: %lld captured, %lld failed attempts, %d recoveries, %s\n",
      static_cast<long long>(run_id), std::string(ToString(report.outcome)).c_str(),
      report.message.c_str(), static_cast<long long>(report.captured),
      static_cast<long long>(report.failed), report.recoveries,
      FormatDuration(report.seconds).c_str());
  switch (report.outcome) {
    case RunOutcome::kDone:
    case RunOutcome::kPaused:
    case RunOutcome::kCancelled:
      return 0;
    case RunOutcome::kStopped:
      return 3;  // resumable
    case RunOutcome::kFailed:
      return 2;
  }
  return 2;
}

}  // namespace

void RegisterRunCommands(CLI::App& app, CommandContext& ctx) {
  auto* run = app.add_subcommand("run", "Create, execute, resume and inspect calibration runs");
  run->require_subcommand(1);
  static std::string db = "gs360.db";
  run->add_option("--db", db, "Run database (SQLite file)")->capture_default_str();

  auto* start = run->add_subcommand("start", "Plan a new run from a config file, then execute it");
  static std::string config_path;
  static std::string name;
  static bool plan_only = false;
  start->add_option("config", config_path, "Run configuration (JSON)")->required();
  start->add_option("--name", name, "Run name (default: the config's)");
  start->add_flag("--plan-only", plan_only, "Store the plan and stop; no motion");
  start->callback([&ctx] {
    RunConfig config = LoadRunConfigFile(config_path);
    if (!name.empty()) config.name = name;
    RunEngine engine(db);
    ProbePlan plan;
    const auto run_id = engine.CreateRun(config, &plan);
    std::printf("created run %lld in %s\n", static_cast<long long>(run_id), db.c_str());
    PrintPlanSummary(stdout, plan);
    if (plan_only) return;
    ctx.exit_code = ExecuteWithProgress(engine, run_id);
  });

  auto* resume = run->add_subcommand("resume", "Continue an interrupted or paused run");
  static std::int64_t run_id = 0;
  static SessionOverrides overrides;
  resume->add_option("run", run_id, "Run id")->required();
  resume->add_option("--machine", overrides.machine_uri,
                     "Controller for this session if it moved (e.g. /dev/ttyUSB1)");
  resume->add_option("--camera", overrides.camera_uri, "Camera URI for this session if it moved");
  resume->callback([&ctx] {
    RunEngine engine(db);
    ctx.exit_code = ExecuteWithProgress(engine, run_id, overrides);
  });

  auto* status = run->add_subcommand("status", "Progress of every run (or one)");
  static std::int64_t status_run = 0;
  status->add_option("run", status_run, "Run id (default: all)");
  status->callback([] {
    if (!std::filesystem::exists(db)) throw std::runtime_error("no database at " + db);
    RunDatabaseOptions options;
    options.read_only = true;
    RunDatabase database(db, options);
    for (const RunRecord& r : database.ListRuns()) {
      if (status_run != 0 && r.id != status_run) continue;
      PrintRunStatus(stdout, database.GetRunStatus(r.id));
    }
  });
}

}  // namespace gs360::cli
