#pragma once
// The virtual rig's knobs a user turns from `gs360 demo` and `gs360 sim-rig`: the rig itself,
// described by a lab's gs360d.toml (its [rig]: shape or mesh, spline points, fins, lens, camera
// height, mount; its [plan] and [plan.machine]), how far the hidden true camera lies from that
// nominal description, the sensor's noise and the LEDs' drift.

#include <optional>
#include <string>

#include <CLI/CLI.hpp>

#include "daemon/run_config.h"
#include "sim/virtual_rig.h"

namespace gs360::cli {

struct SimArgs {
  std::string config;         // a gs360d.toml; empty: the built-in defaults
  double perturbation = 1.0;  // scales the hidden camera's offsets (0: exactly the nominal one)
  bool no_noise = false;
  std::optional<double> read_noise;  // DN (sigma)
  std::optional<double> shot_gain;   // DN per electron
  std::optional<double> drift;       // LED drift amplitude (relative gain)
};

// Adds --config, --perturbation, --no-noise, --read-noise, --shot-gain, --led-drift to `cmd`.
void AddSimArgs(CLI::App* cmd, SimArgs* args);

// The run configuration the virtual rig is built from: the file's (its [machine] and [camera]
// are replaced by the virtual rig's), else the defaults. Throws ConfigError naming the file, the
// line and the field.
RunConfig BaseRunConfig(const SimArgs& args);

// Applies the perturbation scale and the noise settings to the rig's options (as the `tweak` of
// MakeVirtualSetup). Throws std::invalid_argument naming the option when the result is invalid
// (a perturbation large enough to fold the lens, a negative noise).
void ApplySimArgs(const SimArgs& args, VirtualRigOptions* options);

}  // namespace gs360::cli
