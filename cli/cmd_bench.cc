// `gs360 bench acquisition`: the overnight run on the virtual rig, measured. Prints the wall
// time of the probing phase against the planner's estimate, the host time per probe, and the
// database size. See docs/benchmarks.md for figures.

#include <sys/resource.h>

#include <chrono>
#include <cstdio>
#include <filesystem>

#include "cli/commands.h"
#include "cli/progress.h"
#include "cli/report.h"
#include "cli/sim_args.h"
#include "cli/sim_bridge.h"
#include "run/run_engine.h"
#include "sim/virtual_rig.h"

namespace gs360::cli {
namespace {

struct BenchOptions {
  std::string shape = "cylinder";
  int probes = 50;
  bool kept = true;
  double time_scale = 1.0;
  std::string db;
  std::uint64_t seed = 1;
  std::string firmware = "grbl";
};

double CpuSeconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_utime.tv_sec + u.ru_stime.tv_sec) +
         1e-6 * static_cast<double>(u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

// `bench acquisition`: one run on the virtual rig, timed against the planner's estimate.
int RunAcquisitionBench(const BenchOptions& o) {
  RunConfig config;
  const CncFirmware firmware = ParseCncFirmware(o.firmware);
  if (firmware == CncFirmware::kMarlin) ApplyPrinterDefaults(&config);
  config.name = "bench";
  config.rig.shape.shape = ParseSensorShape(o.shape);
  config.plan.probe_count = o.probes;
  config.plan.count_is_kept = o.kept;
  config.plan.seed = o.seed;
  VirtualSetup setup = MakeVirtualSetup(config, o.time_scale, o.seed, {}, "",
                                        [&](VirtualRigOptions& r) { r.cnc.firmware = firmware; });
  config = setup.config;
  VirtualRig& rig = *setup.rig;
  const bool temp_db = o.db.empty();
  const std::filesystem::path db = temp_db
                                       ? std::filesystem::temp_directory_path() /
                                             ("gs360-bench-" + std::to_string(::getpid()) + ".db")
                                       : std::filesystem::path(o.db);
  RunEngine engine(db);
  ProbePlan plan;
  const auto run_id = engine.CreateRun(config, &plan);
  PrintPlanSummary(stdout, plan);

  using Clock = std::chrono::steady_clock;
  std::optional<Clock::time_point> probing_start;
  ProgressPrinter printer(stderr, 30.0);
  engine.SetProgressCallback([&](const RunProgress& p) {
    if (!probing_start && p.phase == "probing") probing_start = Clock::now();
    printer.Update(p);
  });
  const double cpu0 = CpuSeconds();
  const auto t0 = Clock::now();
  const RunReport report = engine.Execute(run_id);
  const auto t1 = Clock::now();
  const double cpu = CpuSeconds() - cpu0;
  printer.Finish();
  const double session = std::chrono::duration<double>(t1 - t0).count();
  const double probing =
      probing_start ? std::chrono::duration<double>(t1 - *probing_start).count() : 0.0;
  const double n = static_cast<double>(std::max<std::int64_t>(1, report.captured));
  RunDatabaseOptions ro;
  ro.read_only = true;
  RunDatabase database(db, ro);
  const CaptureTruth truth = CheckCapturesAgainstTruth(rig, database, run_id);
  const double mb = static_cast<double>(std::filesystem::file_size(db)) / 1e6;
  std::printf("\nbench acquisition: %s on %s, %lld probes, time scale %s\n", o.shape.c_str(),
              o.firmware.c_str(), static_cast<long long>(report.captured),
              o.time_scale > 0 ? std::to_string(o.time_scale).c_str() : "instant");
  std::printf("  outcome              %s (%s)\n", std::string(ToString(report.outcome)).c_str(),
              report.message.c_str());
  std::printf("  session wall         %.2f s (connect + home + probing + park)\n", session);
  std::printf("  probing wall         %.2f s\n", probing);
  std::printf("  planner estimate     %.2f s   ratio wall/estimate %.4f\n", plan.estimate.Total(),
              plan.estimate.Total() > 0 ? probing / plan.estimate.Total() : 0.0);
  std::printf("  per probe            %.1f ms wall, %.1f ms CPU (whole process, rig included)\n",
              1000.0 * probing / n, 1000.0 * cpu / n);
  std::printf("  database             %.1f MB (%.1f MB per 1,000 probes)\n", mb, mb * 1000.0 / n);
  std::printf(
      "  truth                %d frames, %d off the press point, %d unverifiable, max "
      "error %.4f mm\n",
      truth.frames, truth.off_target, truth.unverified, truth.max_error_mm);
  if (temp_db) {
    std::error_code ec;
    std::filesystem::remove(db, ec);
    std::filesystem::remove(db.string() + "-wal", ec);
    std::filesystem::remove(db.string() + "-shm", ec);
  }
  return report.outcome == RunOutcome::kDone && truth.off_target == 0 && truth.unverified == 0 ? 0
                                                                                               : 1;
}

}  // namespace

void RegisterDaemonBench(CLI::App& bench, CommandContext& ctx);    // bench_daemon.cc
void RegisterReconBench(CLI::App& bench, CommandContext& ctx);     // bench_recon.cc
void RegisterSweepBench(CLI::App& bench, CommandContext& ctx);     // bench_sweep.cc
void RegisterStressBench(CLI::App& bench, CommandContext& ctx);    // bench_stress.cc
void RegisterSoakBench(CLI::App& bench, CommandContext& ctx);      // bench_soak.cc
void RegisterConvergeBench(CLI::App& bench, CommandContext& ctx);  // bench_converge.cc
void RegisterHeldoutBench(CLI::App& bench, CommandContext& ctx);   // bench_heldout.cc

void RegisterBenchCommands(CLI::App& app, CommandContext& ctx) {
  static BenchOptions o;
  auto* bench = app.add_subcommand("bench", "Benchmarks on the virtual rig (figures, not tests)");
  bench->require_subcommand(1);
  RegisterDaemonBench(*bench, ctx);
  RegisterReconBench(*bench, ctx);
  RegisterSweepBench(*bench, ctx);
  RegisterStressBench(*bench, ctx);
  RegisterSoakBench(*bench, ctx);
  RegisterConvergeBench(*bench, ctx);
  RegisterHeldoutBench(*bench, ctx);
  auto* acq = bench->add_subcommand(
      "acquisition",
      "Time a run: probing wall time vs the planner's estimate, host time per probe");
  acq->add_option("--shape", o.shape, "cylinder, cone or spline")->capture_default_str();
  acq->add_option("--probes", o.probes, "Probes")->capture_default_str();
  acq->add_flag("--candidates{false}", o.kept,
                "Count --probes as sampled candidates instead of kept probes");
  acq->add_option("--time-scale", o.time_scale, "1 = real time, 0 = instant motion")
      ->capture_default_str();
  acq->add_option("--db", o.db, "Database (default: temp file, removed afterwards)");
  acq->add_option("--seed", o.seed, "Seed")->capture_default_str();
  AddFirmwareOption(acq, &o.firmware, "the rig on an Ender-3-class printer's bed");
  acq->callback([&ctx] { ctx.exit_code = RunAcquisitionBench(o); });
}

}  // namespace gs360::cli
