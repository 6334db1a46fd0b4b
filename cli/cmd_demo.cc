// `gs360 demo`: the whole product on the virtual rig, end to end, with nothing attached.

#include <chrono>
#include <cstdio>
#include <filesystem>

#include "cli/calibrate_support.h"
#include "cli/commands.h"
#include "cli/progress.h"
#include "cli/report.h"
#include "cli/sim_bridge.h"
#include "cli/sim_truth.h"
#include "daemon/run_engine.h"
#include "sim/virtual_rig.h"

namespace gs360::cli {
namespace {

struct DemoOptions {
  std::string shape = "cylinder";
  int probes = 200;
  double time_scale = 0.0;
  std::string db;
  std::uint64_t seed = 1;
  int max_epochs = 0;
  bool no_calibrate = false;
};

}  // namespace

void RegisterDemoCommand(CLI::App& app, CommandContext& ctx) {
  static DemoOptions o;
  auto* demo = app.add_subcommand(
      "demo", "Run the whole pipeline on the simulated rig: plan, stream, capture, store");
  demo->add_option("--shape", o.shape, "Sensor: cylinder, cone or spline")->capture_default_str();
  demo->add_option("--probes", o.probes, "Candidate points sampled on the sensor")
      ->capture_default_str();
  demo->add_option("--time-scale", o.time_scale,
                   "Virtual machine speed: 1 = real time, 0 = instant motion")
      ->capture_default_str();
  demo->add_option("--db", o.db, "Run database (default: a new file in the temp directory)");
  demo->add_option("--seed", o.seed, "Seed of the sampling, the hidden true camera and the noise")
      ->capture_default_str();
  demo->add_option("--max-epochs", o.max_epochs,
                   "Training epochs at most (default: the trainer's)");
  demo->add_flag("--no-calibrate", o.no_calibrate, "Stop after the acquisition");
  demo->callback([&ctx] {
    const auto t0 = std::chrono::steady_clock::now();
    RunConfig config;
    config.name = "demo-" + o.shape;
    config.rig.shape.shape = ParseSensorShape(o.shape);
    config.plan.probe_count = o.probes;
    config.plan.seed = o.seed;

    std::printf("gs360 demo: %s sensor, %d candidate probes, virtual machine at %s\n",
                o.shape.c_str(), o.probes,
                o.time_scale > 0.0 ? (std::to_string(o.time_scale) + "x real time").c_str()
                                   : "instant motion");
    VirtualSetup setup = MakeVirtualSetup(config, o.time_scale, o.seed);
    config = setup.config;
    VirtualRig& rig = *setup.rig;
    std::printf("virtual rig: CNC on %s, camera on %s (%s)\n", rig.PtyPath().c_str(),
                rig.FrameUri().c_str(), rig.rig()->Describe().c_str());

    const std::filesystem::path db = o.db.empty()
                                         ? std::filesystem::temp_directory_path() /
                                               ("gs360-demo-" + std::to_string(::getpid()) + ".db")
                                         : std::filesystem::path(o.db);
    RunEngine engine(db);
    ProbePlan plan;
    const auto run_id = engine.CreateRun(config, &plan);
    PrintPlanSummary(stdout, plan);

    ProgressPrinter printer;
    engine.SetProgressCallback([&](const RunProgress& p) { printer.Update(p); });
    const RunReport report = engine.Execute(run_id);
    printer.Finish();

    RunDatabaseOptions ro;
    ro.read_only = true;
    RunDatabase database(db, ro);
    const RunStatus status = database.GetRunStatus(run_id);
    const CaptureTruth truth = CheckCapturesAgainstTruth(rig, database, run_id);
    const double wall =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::printf("\nacquisition: %s (%s)\n", std::string(ToString(report.outcome)).c_str(),
                report.message.c_str());
    PrintRunStatus(stdout, status);
    std::printf(
        "  %lld frames in %s of run time (%.0f ms per probe), database %s: %.1f MB\n",
        static_cast<long long>(report.captured), FormatDuration(report.seconds).c_str(),
        report.captured > 0 ? 1000.0 * report.seconds / static_cast<double>(report.captured) : 0.0,
        db.string().c_str(), static_cast<double>(std::filesystem::file_size(db)) / 1e6);
    std::printf(
        "  truth check: %d frames, %d taken off the press point, %d unverifiable; max |true - "
        "planned| = %.4f mm, max |reported - true| = %.4f mm\n",
        truth.frames, truth.off_target, truth.unverified, truth.max_error_mm,
        truth.max_reported_error_mm);
    const bool acquired =
        report.outcome == RunOutcome::kDone && truth.off_target == 0 && truth.unverified == 0;
    if (acquired && !o.no_calibrate) {
      // The lab's checkerboard shots, taken through the (hidden) true lens before assembly.
      const std::filesystem::path boards =
          db.parent_path() / (db.stem().string() + "-checkerboards");
      const int n_boards = WriteSimCheckerboards(*rig.rig(), boards, 16, o.seed);
      std::printf("\ncalibration: %d checkerboard images in %s\n", n_boards, boards.c_str());
      RunDatabase writable(db);
      CalibrationOptions options;
      if (o.max_epochs > 0) options.train.max_epochs = o.max_epochs;
      const SimValidationTruth sim_truth(rig.rig(), rig.options().camera.gel);
      CalibrateAndPrint(writable, run_id, CalibrationInputsFor(config, boards), options, &sim_truth,
                        stdout);
    }
    const double total =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::printf("demo finished in %s (acquisition %s)\n", FormatDuration(total).c_str(),
                FormatDuration(wall).c_str());
    ctx.exit_code = acquired ? 0 : 1;
  });
}

}  // namespace gs360::cli
