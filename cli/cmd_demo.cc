// `gs360 demo`: the whole product on the virtual rig, end to end, through gs360d like any lab:
// the virtual rig (a GRBL CNC on a pty, the tactile camera on a socket) here, gs360d started on a
// free loopback port with a configuration pointing at it, then plan, probe, calibrate and export
// through the API, with the dashboard's URL printed while it runs. At the end the daemon is
// stopped and the validation is repeated here against the simulator's physical truth (which only
// the demo, the tests and the benchmarks may see).

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <thread>

#include "base/format.h"
#include "calib/report.h"
#include "cli/calibrate_support.h"
#include "cli/commands.h"
#include "cli/daemon_client.h"
#include "cli/daemon_process.h"
#include "cli/progress.h"
#include "cli/run_view.h"
#include "cli/sim_args.h"
#include "cli/sim_bridge.h"
#include "cli/sim_truth.h"
#include "daemon/daemon_config.h"
#include "gcode/grbl_client.h"
#include "run/calibration_inputs.h"
#include "run/run_engine.h"
#include "sim/virtual_rig.h"

namespace gs360::cli {
namespace {

using Json = nlohmann::json;

struct DemoOptions {
  std::string shape = "cylinder";
  // About 1,000 kept probes: the fewest at which the calibration meets every accuracy target on
  // the default cylinder (docs/benchmarks.md, "The demo"); fewer fit in a minute but miss them.
  int probes = 1400;
  double time_scale = 0.0;
  std::string data_dir;
  std::uint64_t seed = 1;
  int max_epochs = 0;
  bool no_calibrate = false;
  bool until_converged = false;
  SimArgs sim;
};

double Since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// The user's gs360d.toml (--config) or the defaults, with the virtual rig's machine and camera,
// this folder for data and a free loopback port. Its [[notify]] webhooks keep their whole URLs
// (their paths hold the receivers' topics and tokens).
void WriteDaemonConfig(const std::filesystem::path& path, const VirtualSetup& setup,
                       const SimArgs& sim) {
  DaemonConfig daemon;
  if (!sim.config.empty()) daemon = LoadDaemonConfig(sim.config);
  daemon.run = setup.config;
  daemon.data_dir = ".";
  daemon.server.listen = "127.0.0.1";
  daemon.server.port = 0;
  daemon.server.token.clear();
  daemon.calibration.checkerboards = "checkerboards";
  if (sim.config.empty() && setup.config.machine.firmware == MachineFirmware::kMarlin) {
    // The built-in printer's envelope is its travel (ApplyPrinterDefaults).
    daemon.limits.envelope_min = setup.config.plan.machine.TravelMin();
    daemon.limits.envelope_max = setup.config.plan.machine.TravelMax();
  }
  std::ofstream out(path);
  out << "# gs360d for `gs360 demo`: the virtual rig of this process"
      << (sim.config.empty() ? std::string() : ", described by " + sim.config) << ".\n"
      << DaemonConfigToToml(daemon, /*keep_secrets=*/true);
  if (!out.flush()) throw std::runtime_error("cannot write " + path.string());
}

// The validation again, here, against the simulator's physical truth (the daemon is stopped:
// this process may then open its database). Every stage but validate is cached.
void ValidateAgainstTruth(const std::filesystem::path& db_path, std::int64_t run_id,
                          const VirtualRig& rig, int max_epochs, int plan_index_limit) {
  RunDatabase db(db_path);
  CalibrationOptions options;
  if (max_epochs > 0) options.train.max_epochs = max_epochs;
  options.plan_index_limit = plan_index_limit;
  options.export_dir = db_path.parent_path() / "runs" / std::to_string(run_id) / "model";
  const SimValidationTruth truth(rig.rig(), rig.options().camera.gel);
  const CalibrationResult result = RunCalibration(
      db, run_id, CalibrationInputsFor(db, run_id, db_path.parent_path() / "checkerboards"),
      options, &truth);
  std::printf("\nvalidation against the virtual rig's physical truth (held-out probes):\n%s",
              FormatValidationTable(result.validation).c_str());
  std::printf("%s", FormatTargetsAndWarnings(result.validation).c_str());
}

// The planner's machine time, at the run's feeds, for the probes the run pressed (captured or
// failed, in plan order; the skipped ones left out): what a run that stopped early cost.
double PressedMachineSeconds(const std::filesystem::path& db_path, std::int64_t id) {
  RunDatabaseOptions ro;
  ro.read_only = true;
  RunDatabase db(db_path, ro);
  const ProbePlan plan = RunEngine::LoadPlan(db, id);
  const RunConfig config = StoredRunConfig(db, id);
  std::vector<PlannedProbe> pressed;
  for (const ProbeRecord& p : db.ListProbes(id)) {
    if (p.state != ProbeState::kSkipped)
      pressed.push_back(plan.probes.at(static_cast<std::size_t>(p.plan_index)));
  }
  return EstimatePlan(pressed, {plan.start_machine}, config.plan).Total();
}

// With faults: resumes a stopped run as a user would (confirming what it asks about), until it
// is done or kMaxResumes sessions have not finished it.
Json ResumeUntilDone(DaemonClient& client, std::int64_t id, Json run, VirtualRig& rig) {
  constexpr int kMaxResumes = 500;
  const std::string path = "/api/v1/runs/" + std::to_string(id);
  const auto asked = [](const Json& r) {
    return r["state"] == "interrupted" ||
           (r["state"] == "created" && r.contains("awaiting") && r["awaiting"].is_string());
  };
  for (int resumes = 0; asked(run) && resumes < kMaxResumes; ++resumes) {
    Json body = Json::object();
    const bool has_error = run.contains("last_error") && run["last_error"].is_string();
    const std::string error = has_error ? run["last_error"].get<std::string>() : std::string();
    if (error.find("printer halted") != std::string::npos) {
      // A halted printer answers nothing until reset: the user presses its reset button.
      std::printf("  resetting the halted printer as the user would\n");
      rig.cnc().PowerCycle();
    }
    if (run.contains("awaiting") && run["awaiting"].is_string()) {
      body["confirm"] = run["awaiting"];
      std::printf("  resuming, confirming the %s as the user would\n",
                  run["awaiting"].get<std::string>().c_str());
    }
    client.Post(path + "/resume", body);
    run = WatchRun(client, id, stdout, stderr);
  }
  return run;
}

// Every stored press frame against the virtual rig's truth (the daemon may still run: read only).
CaptureTruth PrintTruthCheck(const std::filesystem::path& db_path, const VirtualRig& rig,
                             std::int64_t id) {
  RunDatabaseOptions ro;
  ro.read_only = true;
  RunDatabase db(db_path, ro);
  const CaptureTruth truth = CheckCapturesAgainstTruth(rig, db, id);
  std::printf(
      "  truth check: %d frames, %d taken off the press point, %d unverifiable; max |true "
      "- planned| = %.4f mm, max |reported - true| = %.4f mm\n",
      truth.frames, truth.off_target, truth.unverified, truth.max_error_mm,
      truth.max_reported_error_mm);
  return truth;
}

// The run's calibration on gs360d, followed to its end; true when it is done.
bool CalibrateOnDaemon(DaemonClient& client, const std::string& url, std::int64_t id,
                       int max_epochs) {
  Json request = Json::object();
  if (max_epochs > 0) request["max_epochs"] = max_epochs;
  client.Post("/api/v1/runs/" + std::to_string(id) + "/calibrate", request);
  const Json view = WatchCalibration(client, id, stdout);
  std::printf("\nmodel: %s/api/v1/runs/%lld/model (or `gs360 export %lld --out DIR --daemon %s`)\n",
              url.c_str(), static_cast<long long>(id), static_cast<long long>(id), url.c_str());
  return view["state"] == "done";
}

// A run that converges calibrates itself: waits for its last checkpoint, prints the curve and
// that calibration. True when it produced a model; `*plan_index_limit` is its probes' bound.
bool FollowConvergence(DaemonClient& client, std::int64_t id, int* plan_index_limit) {
  const std::string path = "/api/v1/runs/" + std::to_string(id);
  Json run = client.Get(path);
  while (run["convergence"].is_object() && run["convergence"]["state"] == "calibrating") {
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
    run = client.Get(path);
  }
  std::printf("\n");
  PrintConvergence(stdout, run);
  const Json& list = run["convergence"].is_object()
                         ? run["convergence"].value("checkpoints", Json::array())
                         : Json::array();
  if (list.empty() || !list.back().is_object()) return false;
  *plan_index_limit = list.back().value("plan_index_limit", 0);
  std::printf("\nthe model is the last checkpoint's calibration:\n");
  return WatchCalibration(client, id, stdout)["state"] == "done";
}

// The demo's run on gs360d, created from its options; prints its id and plan. Returns the
// API's answer (the run's "id" and "plan").
Json CreateDemoRun(DaemonClient& client, const DemoOptions& o) {
  // With --config the daemon's own [rig] is the sensor: the request names no shape.
  Json run_request = {{"name", "demo-" + (o.sim.config.empty() ? o.shape : std::string("config"))},
                      {"probes", o.probes},
                      {"plan", {{"seed", o.seed}}}};
  if (o.sim.config.empty()) run_request["shape"] = {{"type", o.shape}};
  if (o.until_converged) run_request["until_converged"] = true;
  const Json created = client.Post("/api/v1/runs", run_request);
  const std::int64_t id = created["id"].get<std::int64_t>();
  std::printf("created run %lld\n", static_cast<long long>(id));
  PrintPlan(stdout, created["plan"]);
  return created;
}

// What the probes pressed (or the whole plan, with instant motion) take on a real rig.
void PrintRealMachineTime(const DemoOptions& o, const Json& run, const Json& plan,
                          const std::filesystem::path& db, std::int64_t id) {
  if (o.until_converged) {
    std::printf(
        "on a real rig at [plan.machine]'s feeds the %lld probes pressed take about %s "
        "(the whole plan %s)\n",
        static_cast<long long>(run.value("probes_done", 0) + run.value("probes_failed", 0)),
        FormatDuration(PressedMachineSeconds(db, id)).c_str(),
        FormatDuration(plan.value("estimate_s", 0.0)).c_str());
  } else if (o.time_scale == 0.0) {
    std::printf("on a real rig at [plan.machine]'s feeds the acquisition would take about %s\n",
                FormatDuration(plan.value("estimate_s", 0.0)).c_str());
  }
}

int RunDemo(const DemoOptions& o, RunConfig config) {
  const auto t0 = std::chrono::steady_clock::now();
  const std::filesystem::path dir = std::filesystem::absolute(
      o.data_dir.empty()
          ? std::filesystem::temp_directory_path() / ("gs360-demo-" + std::to_string(::getpid()))
          : std::filesystem::path(o.data_dir));
  std::filesystem::create_directories(dir);
  std::printf("gs360 demo: %s sensor, %d candidate probes, virtual machine at %s\n",
              o.sim.config.empty() ? o.shape.c_str() : o.sim.config.c_str(), o.probes,
              o.time_scale > 0.0 ? (FormatFixed(o.time_scale, 1) + "x real time").c_str()
                                 : "instant motion");
  if (o.sim.config.empty()) config.rig.shape.shape = ParseSensorShape(o.shape);
  // With faults the CNC may come back under a new pty (unplug): the daemon finds it by symlink.
  VirtualSetup setup =
      MakeVirtualSetup(config, o.time_scale, o.seed, dir / "camera.sock",
                       o.sim.faults.empty() ? std::string() : (dir / "ttyCNC").string(),
                       [&](VirtualRigOptions& rig_options) { ApplySimArgs(o.sim, &rig_options); });
  config = setup.config;
  VirtualRig& rig = *setup.rig;
  std::printf("virtual rig: CNC on %s, camera on %s (%s)\n", rig.PtyPath().c_str(),
              rig.FrameUri().c_str(), rig.rig()->Describe().c_str());
  // The lab's checkerboard shots, taken through the (hidden) true lens before assembly.
  const int boards = WriteSimCheckerboards(*rig.rig(), dir / "checkerboards", 16, o.seed);
  WriteDaemonConfig(dir / "gs360d.toml", setup, o.sim);
  DaemonProcess daemon(FindGs360d(), dir / "gs360d.toml", dir, dir / "gs360d.log");
  std::printf("gs360d: %s (data folder %s, log gs360d.log)\ndashboard: %s/\n\n",
              daemon.url().c_str(), dir.c_str(), daemon.url().c_str());

  DaemonClient client(daemon.url(), "");
  const Json created = CreateDemoRun(client, o);
  const std::int64_t id = created["id"].get<std::int64_t>();
  std::unique_ptr<RigFaultSchedule> faults = StartFaults(o.sim, rig, o.seed);
  if (faults) {
    std::printf("faults: %s, one every ~%.0f presses\n", o.sim.faults.c_str(), o.sim.fault_every);
  }
  client.Post("/api/v1/runs/" + std::to_string(id) + "/start");
  Json run = WatchRun(client, id, stdout, stderr);
  // A printer rebooted by the open asks before its first homing (docs/running.md): the demo
  // answers as its user would, as it does after a fault.
  const bool asked_at_start = run.contains("awaiting") && run["awaiting"].is_string();
  if (faults || asked_at_start) {
    run = ResumeUntilDone(client, id, run, rig);
  }
  if (faults) {
    std::printf("  injected: %s\n", DescribeFaults(faults->Injected()).c_str());
    faults.reset();  // the calibration runs on a quiet rig
  }
  const double acquisition_s = Since(t0);

  const CaptureTruth truth = PrintTruthCheck(dir / "gs360.db", rig, id);
  const bool acquired = run["state"] == "done" && truth.off_target == 0 && truth.unverified == 0;
  bool calibrated = o.no_calibrate;
  int plan_index_limit = 0;
  if (acquired && !o.no_calibrate && o.until_converged) {
    calibrated = FollowConvergence(client, id, &plan_index_limit);
  } else if (acquired && !o.no_calibrate) {
    std::printf("\ncalibration on gs360d (%d checkerboard images of the lens):\n", boards);
    calibrated = CalibrateOnDaemon(client, daemon.url(), id, o.max_epochs);
  }
  const int stopped = daemon.Stop();
  if (stopped != 0)
    std::printf("gs360d exited with %d (see %s/gs360d.log)\n", stopped, dir.c_str());
  if (acquired && calibrated && !o.no_calibrate) {
    ValidateAgainstTruth(dir / "gs360.db", id, rig, o.max_epochs, plan_index_limit);
  }
  std::printf("demo finished in %s (acquisition %s); data in %s\n",
              FormatDuration(Since(t0)).c_str(), FormatDuration(acquisition_s).c_str(),
              dir.c_str());
  PrintRealMachineTime(o, run, created["plan"], dir / "gs360.db", id);
  return acquired && calibrated && stopped == 0 ? kExitOk : kExitError;
}

}  // namespace

void RegisterDemoCommand(CLI::App& app, CommandContext& ctx) {
  static DemoOptions o;
  auto* demo = app.add_subcommand(
      "demo",
      "The whole product on the simulated rig, through gs360d: plan, probe, capture, store, "
      "calibrate, validate");
  auto* shape = demo->add_option("--shape", o.shape, "Sensor: cylinder, cone or spline")
                    ->capture_default_str();
  demo->add_option("--probes", o.probes, "Candidate points sampled on the sensor")
      ->capture_default_str();
  demo->add_option("--time-scale", o.time_scale,
                   "Virtual machine speed: 1 = real time, 0 = instant motion")
      ->capture_default_str();
  demo->add_option("--data-dir", o.data_dir,
                   "The daemon's data folder (default: a new folder in the temp directory)");
  demo->add_option("--seed", o.seed, "Seed of the sampling, the hidden true camera and the noise")
      ->capture_default_str();
  demo->add_option("--max-epochs", o.max_epochs,
                   "Training epochs at most (default: the trainer's)");
  demo->add_flag("--no-calibrate", o.no_calibrate, "Stop after the acquisition");
  demo->add_flag("--until-converged", o.until_converged,
                 "The run calibrates itself after each round of probes and ends once converged "
                 "(give it a --time-scale: at instant motion the probes outrun the calibrations)");
  AddSimArgs(demo, &o.sim);
  shape->excludes("--config");
  demo->callback([&ctx, demo] {
    RunConfig config = LoadSimConfig(*demo, &o.sim, &o.seed);
    ctx.exit_code = RunDemo(o, std::move(config));
  });
}

}  // namespace gs360::cli
