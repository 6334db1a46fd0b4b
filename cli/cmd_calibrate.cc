// `gs360 calibrate RUN`: the calibration stages of a run, on gs360d (default) or, with --db, here
// on a database file no daemon holds. Stages whose inputs have not changed are taken from the
// cache, like a build.

#include <cstdio>
#include <filesystem>
#include <memory>

#include "base/json_reader.h"
#include "cli/calibrate_support.h"
#include "cli/commands.h"
#include "cli/daemon_client.h"
#include "cli/run_view.h"
#include "cli/sim_bridge.h"
#include "cli/sim_truth.h"
#include "daemon/calibration_jobs.h"
#include "daemon/instance_lock.h"

namespace gs360::cli {
namespace {

using Json = nlohmann::json;

struct CalibrateArgs {
  std::int64_t run = 0;
  std::string db;
  std::string checkerboards;
  std::string out;
  int threads = 2;
  bool no_wait = false;
  std::int64_t sim_truth_seed = -1;
  Json request = Json::object();  // the options, as POST /runs/ID/calibrate takes them
};

// Each option fills one key of the request; the daemon and the local mode read the same keys.
template <typename T>
void Key(CLI::App* cmd, const std::string& flag, const std::string& key, const std::string& help,
         Json* request) {
  auto* opt = cmd->add_option_function<T>(
      flag, [request, key](const T& v) { (*request)[key] = v; }, help);
  if constexpr (std::is_same_v<T, std::vector<int>> || std::is_same_v<T, std::vector<double>>) {
    opt->delimiter(',');
  }
}

void AddOptions(CLI::App* cmd, Json* r) {
  Key<std::string>(cmd, "--from", "from",
                   "Re-run this stage and every later one even if cached (intrinsics, "
                   "impressions, pose, surface_map, render, dataset, train, validate, export)",
                   r);
  Key<std::string>(cmd, "--to", "to", "Stop after this stage (the later ones are not run)", r);
  Key<std::string>(cmd, "--only", "only",
                   "Run only this stage (again), its inputs from the cache; an input that is "
                   "not cached is an error naming the --to that computes it",
                   r);
  Key<std::string>(cmd, "--name", "model_name", "Model name (default: run-<id>)", r);
  Key<std::string>(cmd, "--model-version", "model_version",
                   "Model version (default: the training's hash)", r);
  Key<int>(cmd, "--board-cols", "board_cols",
           "Checkerboard inner corners along its x, for the lens intrinsics (default: 9)", r);
  Key<int>(cmd, "--board-rows", "board_rows", "Checkerboard inner corners along its y (default: 6)",
           r);
  Key<double>(cmd, "--square-mm", "square_mm", "Checkerboard square side in mm (default: 5)", r);
  Key<int>(cmd, "--max-epochs", "max_epochs", "Training epochs at most (default: the trainer's)",
           r);
  Key<std::vector<int>>(cmd, "--hidden", "hidden",
                        "MLP hidden layer widths, comma separated (default: 128,128,128)", r);
  Key<int>(cmd, "--samples-per-probe", "samples_per_probe",
           "Contact pixels sampled per probe for training at most (default: 500)", r);
  Key<int>(cmd, "--small-probe-repeat", "small_probe_repeat",
           "Times a probe with fewer contact pixels than the cap is sampled, up to the cap "
           "(default 2; 1 = each pixel once)",
           r);
  Key<std::int64_t>(cmd, "--max-samples", "max_samples",
                    "Training samples in all at most (default: 1200000; 0 = no limit)", r);
  Key<double>(cmd, "--edge-exclusion", "edge_exclusion",
              "Leave out training pixels within this many mm of the rigid imprint's edge", r);
  Key<std::string>(cmd, "--integration", "integration",
                   "Default integrator of the model: heightfield, discontinuity or poisson", r);
  Key<double>(cmd, "--hf-min-view-angle", "hf_min_view_angle",
              "Imprints seen more squarely than this (deg) use the discontinuity-aware "
              "integrator (default 0: the height field always)",
              r);
  Key<int>(cmd, "--fourier", "fourier",
           "Fourier features of the pixel position: frequencies per coordinate (default 4; 0 = "
           "none)",
           r);
  Key<std::vector<double>>(cmd, "--context-sigmas", "context_sigmas",
                           "Scales (px, comma separated, at most 4) of the context features "
                           "(default 1.5,4,10; 0 = none)",
                           r);
  Key<double>(cmd, "--smooth-sigma", "smooth_sigma",
              "Gaussian smoothing (px) of the colour difference before the MLP (default 1)", r);
  Key<int>(cmd, "--max-validation-probes", "max_validation_probes",
           "Held-out probes evaluated at most (default: 400)", r);
}

// --db: the stages here, on a file no daemon holds.
void CalibrateLocally(const CalibrateArgs& a, CommandContext& ctx) {
  const std::filesystem::path db_path = std::filesystem::absolute(a.db);
  if (!std::filesystem::exists(db_path)) {
    throw ClientError("no database at " + db_path.string(), kExitUsage);
  }
  // A daemon holding this folder owns the file: calibrate through it instead.
  const InstanceLock lock = [&] {
    try {
      return InstanceLock::Acquire(db_path.parent_path() / "gs360d.lock",
                                   "the data folder " + db_path.parent_path().string(),
                                   "gs360 calibrate --db");
    } catch (const LockHeldError& e) {
      throw ClientError(std::string(e.what()) + "; use `gs360 calibrate " + std::to_string(a.run) +
                            "` (through the daemon) instead",
                        kExitConflict);
    }
  }();
  RunDatabase db(db_path);
  const RunConfig config = StoredRunConfig(db, a.run);
  const CalibrationInputs inputs = CalibrationInputsFor(db, a.run, a.checkerboards);
  CalibrationOptions options;
  JsonReader reader(a.request, "options");
  ReadCalibrationRequest(reader, options);
  options.export_dir = a.out.empty() ? db_path.parent_path() : std::filesystem::path(a.out);
  options.threads = a.threads;
  options.train.threads = a.threads;
  options.validation.threads = a.threads;
  options.surface_map.threads = a.threads;
  std::unique_ptr<SimValidationTruth> truth;
  if (a.sim_truth_seed >= 0) {
    auto rig = std::make_shared<const SimRig>(
        SimRigOptionsFor(config.rig, static_cast<std::uint64_t>(a.sim_truth_seed)));
    truth = std::make_unique<SimValidationTruth>(rig, TactileCameraOptions{}.gel);
  }
  std::printf("gs360 calibrate: run %lld in %s (%s)\n", static_cast<long long>(a.run),
              db_path.c_str(), inputs.sensor.c_str());
  CalibrateAndPrint(db, a.run, inputs, options, truth.get(), stdout);
  ctx.exit_code = kExitOk;
}

void CalibrateOnDaemon(const CalibrateArgs& a, CommandContext& ctx) {
  DaemonClient client(ctx.daemon_url, ctx.token);
  const std::string path = "/api/v1/runs/" + std::to_string(a.run);
  const Json accepted = client.Post(path + "/calibrate", a.request);
  if (a.no_wait) {
    if (ctx.json) return (void)std::printf("%s\n", accepted.dump(2).c_str());
    std::printf("run %lld: %s\n", static_cast<long long>(a.run),
                accepted["message"].get<std::string>().c_str());
    return;
  }
  if (!ctx.json)
    std::printf("gs360 calibrate: run %lld on %s\n", static_cast<long long>(a.run),
                client.url().c_str());
  const Json view = WatchCalibration(client, a.run, ctx.json ? stderr : stdout);
  if (ctx.json) std::printf("%s\n", view.dump(2).c_str());
  ctx.exit_code = view.value("state", "") == "done" ? kExitOk : kExitRunStopped;
}

}  // namespace

void RegisterCalibrateCommand(CLI::App& app, CommandContext& ctx) {
  static CalibrateArgs a;
  auto* cmd = app.add_subcommand(
      "calibrate",
      "Run the calibration stages of a run (intrinsics, impressions, pose, surface map, render, "
      "dataset, train, validate, export) on gs360d, and follow them. Stages whose inputs have "
      "not changed are skipped.");
  cmd->add_option("run", a.run, "Run id")->required();
  cmd->add_flag("--no-wait", a.no_wait, "Start the calibration and return");
  AddOptions(cmd, &a.request);
  auto* local = cmd->add_option_group("local", "Without a daemon, on a database file here");
  local->add_option("--db", a.db, "Calibrate here, on this run database (no daemon may hold it)");
  local->add_option("--checkerboards", a.checkerboards,
                    "With --db: directory of checkerboard images for the intrinsics");
  local->add_option("--out", a.out, "With --db: directory for the model files (default: the db's)");
  local->add_option("--threads", a.threads, "With --db: worker threads")->capture_default_str();
  local->add_option("--sim-truth-seed", a.sim_truth_seed,
                    "With --db: the run came from the virtual rig with this seed; also validate "
                    "against its physical truth");
  cmd->callback([&ctx] {
    if (!a.db.empty()) return CalibrateLocally(a, ctx);
    if (!a.checkerboards.empty() || !a.out.empty() || a.sim_truth_seed >= 0) {
      throw ClientError(
          "--checkerboards, --out and --sim-truth-seed need --db (the daemon takes them from "
          "its configuration; `gs360 export` downloads the model)",
          kExitUsage);
    }
    CalibrateOnDaemon(a, ctx);
  });
}

}  // namespace gs360::cli
