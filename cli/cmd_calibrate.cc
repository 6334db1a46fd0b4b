// `gs360 calibrate RUN`: the calibration stages on a run's database, cached like a build.

#include <cstdio>
#include <filesystem>
#include <memory>

#include "cli/calibrate_support.h"
#include "cli/commands.h"
#include "cli/sim_bridge.h"
#include "cli/sim_truth.h"

namespace gs360::cli {
namespace {

struct CalibrateArgs {
  std::string db = "gs360.db";
  std::int64_t run = 0;
  std::string checkerboards;
  std::string from;
  std::string out;
  std::string name;
  std::string version;
  int threads = 2;
  int max_epochs = 0;
  std::vector<int> hidden;
  int samples_per_probe = 0;
  std::int64_t max_samples = -1;
  double edge_exclusion = -1.0;
  double smooth_sigma = -1.0;
  std::vector<double> context_sigmas;
  std::string integration;
  double min_view_angle = -1.0;
  int fourier_frequencies = -1;
  int max_validation_probes = 0;
  std::int64_t sim_truth_seed = -1;
};

}  // namespace

void RegisterCalibrateCommand(CLI::App& app, CommandContext& ctx) {
  static CalibrateArgs a;
  auto* cmd = app.add_subcommand(
      "calibrate",
      "Run the calibration stages on a run: intrinsics, impressions, pose, surface map, render, "
      "dataset, train, validate, export. Stages whose inputs have not changed are skipped.");
  cmd->add_option("run", a.run, "Run id")->required();
  cmd->add_option("--db", a.db, "Run database (SQLite file)")->capture_default_str();
  cmd->add_option("--checkerboards", a.checkerboards,
                  "Directory of checkerboard images for the intrinsics (default: nominal lens)");
  cmd->add_option("--from", a.from,
                  "Re-run this stage and every later one even if cached (intrinsics, "
                  "impressions, pose, surface_map, render, dataset, train, validate, export)");
  cmd->add_option("--out", a.out, "Directory for the model, ONNX and report (default: the db's)");
  cmd->add_option("--name", a.name, "Model name (default: run-<id>)");
  cmd->add_option("--model-version", a.version, "Model version (default: the training's hash)");
  cmd->add_option("--threads", a.threads, "Worker threads")->capture_default_str();
  cmd->add_option("--max-epochs", a.max_epochs, "Training epochs at most (default: the trainer's)");
  cmd->add_option("--hidden", a.hidden,
                  "MLP hidden layer widths, comma separated (default: 128,128,128)")
      ->delimiter(',');
  cmd->add_option("--samples-per-probe", a.samples_per_probe,
                  "Contact pixels sampled per probe for training at most (default: 500)");
  cmd->add_option("--max-samples", a.max_samples,
                  "Training samples in all at most, lowering the per-probe count for large runs "
                  "(default: 1200000; 0 = no limit)");
  cmd->add_option("--edge-exclusion", a.edge_exclusion,
                  "Leave out training pixels within this many mm of the rigid imprint's edge, "
                  "where the gel rounds it off (default: the dataset's)");
  cmd->add_option("--integration", a.integration,
                  "Default integrator of the model: heightfield, discontinuity or poisson "
                  "(validation reports all three)");
  cmd->add_option("--hf-min-view-angle", a.min_view_angle,
                  "Imprints seen more squarely than this (deg) use the discontinuity-aware "
                  "integrator instead of the height field (default 0: the height field always)");
  cmd->add_option("--fourier", a.fourier_frequencies,
                  "Fourier features of the pixel position: frequencies per coordinate "
                  "(default 4; 0 = raw u, v only)");
  cmd->add_option("--context-sigmas", a.context_sigmas,
                  "Scales (px, comma separated, at most 4) of the context features: the colour "
                  "change's image gradient, fed to the MLP with each pixel's colour (default: "
                  "1.5,4,10; 0 = none)")
      ->delimiter(',');
  cmd->add_option("--smooth-sigma", a.smooth_sigma,
                  "Gaussian smoothing (px) of the colour difference before the MLP (default 1)");
  cmd->add_option("--max-validation-probes", a.max_validation_probes,
                  "Held-out probes evaluated at most (default: 400)");
  cmd->add_option("--sim-truth-seed", a.sim_truth_seed,
                  "The run came from the virtual rig with this seed: also validate against its "
                  "physical truth and true camera pose");
  cmd->callback([&ctx] {
    if (!std::filesystem::exists(a.db)) throw std::runtime_error("no database at " + a.db);
    RunDatabase db(a.db);
    const RunConfig config = StoredRunConfig(db, a.run);
    const CalibrationInputs inputs = CalibrationInputsFor(config, a.checkerboards);
    CalibrationOptions options;
    options.from_stage = a.from;
    options.export_dir = a.out;
    options.model_name = a.name;
    options.model_version = a.version;
    options.threads = a.threads;
    options.train.threads = a.threads;
    options.validation.threads = a.threads;
    options.surface_map.threads = a.threads;
    if (a.max_epochs > 0) options.train.max_epochs = a.max_epochs;
    if (!a.hidden.empty()) options.train.hidden = a.hidden;
    if (!a.integration.empty()) {
      options.reconstruction.integration.method = ParseIntegrationMethod(a.integration);
    }
    if (a.smooth_sigma >= 0.0) options.reconstruction.difference.smooth_sigma_px = a.smooth_sigma;
    if (!a.context_sigmas.empty()) {
      options.reconstruction.difference.context_sigmas_px.clear();
      for (double sigma : a.context_sigmas) {
        if (sigma > 0.0) options.reconstruction.difference.context_sigmas_px.push_back(sigma);
      }
    }
    if (a.min_view_angle >= 0.0) {
      options.reconstruction.integration.height_field.min_view_angle_deg = a.min_view_angle;
    }
    if (a.fourier_frequencies == 0) options.train.fourier = {};
    if (a.fourier_frequencies > 0) options.train.fourier.frequencies = a.fourier_frequencies;
    if (a.samples_per_probe > 0)
      options.dataset.max_contact_samples_per_probe = a.samples_per_probe;
    if (a.max_samples >= 0) options.dataset.max_samples = a.max_samples;
    if (a.edge_exclusion >= 0.0) options.dataset.edge_exclusion_mm = a.edge_exclusion;
    if (a.max_validation_probes > 0) options.validation.max_probes = a.max_validation_probes;
    std::unique_ptr<SimValidationTruth> truth;
    if (a.sim_truth_seed >= 0) {
      auto rig = std::make_shared<const SimRig>(
          SimRigOptionsFor(config.rig, static_cast<std::uint64_t>(a.sim_truth_seed)));
      truth = std::make_unique<SimValidationTruth>(rig, TactileCameraOptions{}.gel);
    }
    std::printf("gs360 calibrate: run %lld in %s (%s)\n", static_cast<long long>(a.run),
                a.db.c_str(), inputs.sensor.c_str());
    CalibrateAndPrint(db, a.run, inputs, options, truth.get(), stdout);
    ctx.exit_code = 0;
  });
}

}  // namespace gs360::cli
