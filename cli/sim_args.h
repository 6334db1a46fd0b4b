#pragma once
// The virtual rig's knobs a user turns from `gs360 demo` and `gs360 sim-rig`: the rig itself,
// described by a lab's gs360d.toml (its [rig]: shape or mesh, spline points, fins, lens, camera
// height, mount; its [plan] and [plan.machine]), how far the hidden true camera lies from that
// nominal description, the sensor's noise and the LEDs' drift.

#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "run/run_config.h"
#include "sim/rig_faults.h"
#include "sim/virtual_rig.h"

namespace gs360::cli {

struct SimArgs {
  std::string config;         // a gs360d.toml; empty: the built-in defaults
  double perturbation = 1.0;  // scales the hidden camera's offsets (0: exactly the nominal one)
  bool no_noise = false;
  std::optional<double> read_noise;  // DN (sigma)
  std::optional<double> shot_gain;   // DN per electron
  std::optional<double> drift;       // LED drift amplitude (relative gain)
  // The hidden true camera's orientation and centre off the nominal ones (deg, mm; random axis
  // and direction from the seed), instead of perturbation x the defaults.
  std::optional<double> camera_tilt_deg;
  std::optional<double> camera_offset_mm;
  // The LEDs (sim/lighting.h): fin LED heights (fractions of the sensor height), their radial
  // place on the fin (fraction of its half-width), the intensities of the red, green and blue
  // LEDs, the blue ring's LED count and radius (fraction of the base radius).
  std::vector<double> led_heights;
  std::optional<double> led_radial;
  std::vector<double> led_intensity;
  std::optional<int> blue_leds;
  std::optional<double> blue_ring_radius;
  // Faults injected while the rig serves (sim/rig_faults.h): kinds, comma-separated ("" none,
  // "all"), one every ~fault_every presses.
  std::string faults;
  double fault_every = 50.0;
  // The board reboots whenever a host opens its port (an Arduino's DTR reset), after 0.5 s of
  // bootloader: each session meets a freshly booted controller.
  bool reset_on_open = false;
  // The virtual controller's firmware: "grbl", "grblhal" or "marlin" (a printer; without
  // --config the rig is mounted on an Ender-3-class printer: ApplyPrinterDefaults).
  std::string firmware = "grbl";
};

// "grbl", "grblhal", "marlin" -> the virtual controller's firmware. Throws ClientError (usage)
// naming the three for anything else.
CncFirmware ParseCncFirmware(const std::string& name);
// Adds `--firmware grbl|grblhal|marlin` (checked against the three) to `cmd`; `marlin` says what
// the command then runs on.
void AddFirmwareOption(CLI::App* cmd, std::string* firmware, const std::string& marlin);

// The built-in rig mounted on a Marlin printer of the Ender-3 class (GrblSettings::
// PrinterDefaults): [plan.machine] 500/500/5 mm/s, 500/500/100 mm/s^2, travel 0..235 x 0..235 x
// 0..250 mm; the ball in the hotend's place, machine Z 0 where it rests on the bed (the Z endstop
// or offset set so), the sensor's base on the bed at X 117.5 Y 117.5, the run starting 60 mm
// above it.
void ApplyPrinterDefaults(RunConfig* config);

// Adds --firmware, --config, --perturbation, --camera-tilt, --camera-offset, --no-noise,
// --read-noise,
// --shot-gain, --led-drift, --led-heights, --led-radial, --led-intensity, --blue-leds,
// --blue-ring-radius, --faults, --fault-every to `cmd`.
void AddSimArgs(CLI::App* cmd, SimArgs* args);

// Adds `--faults LIST` (checked with ParseRigFaults: an unknown kind is a usage error naming the
// known ones) and `--fault-every N` to `cmd`.
void AddFaultArgs(CLI::App* cmd, std::string* faults, double* every);

// The fault schedule `args` asks for on `rig` (seeded with `seed`), or null without --faults.
std::unique_ptr<RigFaultSchedule> StartFaults(const SimArgs& args, VirtualRig& rig,
                                              std::uint64_t seed);
// "12 faults (3 drop, 9 stall)".
std::string DescribeFaults(const std::map<std::string, int>& injected);

// The run configuration the virtual rig is built from: the file's (its [machine] and [camera]
// are replaced by the virtual rig's), else the defaults. The file's [sim] table sets every knob of
// `args` (and `seed`) that `cmd`'s command line did not give (docs/virtual_rig.md). Call it once,
// after parsing. Throws ConfigError naming the file, the line and the field.
RunConfig LoadSimConfig(const CLI::App& cmd, SimArgs* args, std::uint64_t* seed);

// Applies the perturbation scale and the noise settings to the rig's options (as the `tweak` of
// MakeVirtualSetup). Throws std::invalid_argument naming the option when the result is invalid
// (a perturbation large enough to fold the lens, a negative noise).
void ApplySimArgs(const SimArgs& args, VirtualRigOptions* options);

}  // namespace gs360::cli
