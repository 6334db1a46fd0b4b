#include "cli/sim_args.h"

#include <cmath>
#include <stdexcept>

#include "base/format.h"
#include "daemon/daemon_config.h"

namespace gs360::cli {

void AddSimArgs(CLI::App* cmd, SimArgs* args) {
  cmd->add_option("--config", args->config,
                  "A gs360d.toml whose [rig] (shape or mesh, fins, lens, camera height) and [plan] "
                  "describe the virtual rig; its [machine] and [camera] are the virtual rig's")
      ->check(CLI::ExistingFile);
  cmd->add_option("--perturbation", args->perturbation,
                  "How far the hidden true camera lies from the nominal one, as a multiple of the "
                  "default offsets (0.3 mm, 1 deg, 1% focal length, 3 px, k1/k2); 0: exact")
      ->check(CLI::Range(0.0, 15.0))
      ->capture_default_str();
  cmd->add_flag("--no-noise", args->no_noise, "Noise-free camera frames");
  cmd->add_option("--read-noise", args->read_noise, "Camera read noise, DN (default 1.0)")
      ->check(CLI::Range(0.0, 50.0));
  cmd->add_option("--shot-gain", args->shot_gain,
                  "Camera shot noise: DN per electron (default 0.05)")
      ->check(CLI::Range(0.0, 10.0));
  cmd->add_option("--led-drift", args->drift,
                  "LED drift amplitude, relative gain over hours (default 0.015)")
      ->check(CLI::Range(0.0, 0.5));
}

RunConfig BaseRunConfig(const SimArgs& args) {
  if (args.config.empty()) return RunConfig{};
  return LoadDaemonConfig(args.config).run;
}

void ApplySimArgs(const SimArgs& args, VirtualRigOptions* options) {
  if (!std::isfinite(args.perturbation) || args.perturbation < 0.0) {
    throw std::invalid_argument("--perturbation must be >= 0, got " +
                                FormatFixed(args.perturbation, 3));
  }
  TruePerturbationOptions& p = options->rig.perturbation;
  const double s = args.perturbation;
  p.translation_mm *= s;
  p.rotation_deg *= s;
  p.focal_relative *= s;
  p.aspect_relative *= s;
  p.principal_point_px *= s;
  p.k1 *= s;
  p.k2 *= s;
  SensorModelOptions& sensor = options->camera.sensor;
  if (args.no_noise) sensor.noise = false;
  if (args.read_noise) sensor.read_noise = *args.read_noise;
  if (args.shot_gain) sensor.shot_gain = *args.shot_gain;
  if (args.drift) sensor.drift_amplitude = *args.drift;
  try {
    p.Check();
    sensor.Check();
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(std::string(e.what()) + " (from --perturbation " +
                                FormatFixed(s, 2) + " or the noise options)");
  }
}

}  // namespace gs360::cli
