#include "cli/sim_args.h"

#include <cmath>
#include <stdexcept>

#include "base/format.h"
#include "base/json_reader.h"
#include "cli/daemon_client.h"
#include "daemon/daemon_config.h"

namespace gs360::cli {

namespace {

// Each knob's bounds, shared by its command-line option and its key in the file's [sim].
struct Bounds {
  double lo;
  double hi;
};
constexpr Bounds kPerturbation{0.0, 15.0};
constexpr Bounds kReadNoise{0.0, 50.0};
constexpr Bounds kShotGain{0.0, 10.0};
constexpr Bounds kDrift{0.0, 0.5};
constexpr Bounds kTilt{0.0, 30.0};
constexpr Bounds kOffset{0.0, 5.0};
constexpr Bounds kFraction{0.0, 1.0};
constexpr Bounds kIntensity{0.0, 1000.0};
constexpr Bounds kBlueLeds{1.0, 64.0};
constexpr Bounds kFaultEvery{2.0, 100000.0};

CLI::Range RangeOf(Bounds b) {
  return CLI::Range(b.lo, b.hi);
}

}  // namespace

CncFirmware ParseCncFirmware(const std::string& name) {
  if (name == "grbl") return CncFirmware::kGrbl11h;
  if (name == "grblhal") return CncFirmware::kGrblHal;
  if (name == "marlin") return CncFirmware::kMarlin;
  throw ClientError("--firmware: unknown firmware '" + name + "' (grbl, grblhal or marlin)",
                    kExitUsage);
}

void AddFirmwareOption(CLI::App* cmd, std::string* firmware, const std::string& marlin) {
  cmd->add_option("--firmware", *firmware,
                  "The virtual controller: grbl (GRBL 1.1h), grblhal, or marlin (" + marlin + ")")
      ->check(CLI::IsMember({"grbl", "grblhal", "marlin"}))
      ->capture_default_str();
}

void ApplyPrinterDefaults(RunConfig* config) {
  MachineSettings& m = config->plan.machine;
  const GrblSettings printer = GrblSettings::PrinterDefaults();
  m.max_rate_mm_per_min = printer.max_rate_mm_per_min;
  m.acceleration_mm_per_s2 = printer.acceleration_mm_per_s2;
  m.max_travel_mm = printer.max_travel_mm;
  m.travel_min_mm = Eigen::Vector3d::Zero();
  m.junction_deviation_mm = printer.junction_deviation_mm;
  m.planner_blocks = 15;
  config->rig.base_in_machine = Eigen::Vector3d(117.5, 117.5, 0.0);
  // Z 0 where the ball rests on the bed (the Z endstop set so).
  config->rig.tool_offset = Eigen::Vector3d(0.0, 0.0, config->rig.ball_radius);
  config->plan.start_machine = Eigen::Vector3d(117.5, 117.5, 60.0);
}

void AddSimArgs(CLI::App* cmd, SimArgs* args) {
  AddFirmwareOption(cmd, &args->firmware,
                    "a Marlin 2.1 printer; without --config the rig sits on an Ender-3-class "
                    "printer's bed");
  cmd->add_option("--config", args->config,
                  "A gs360d.toml whose [rig] (shape or mesh, fins, lens, camera height) and [plan] "
                  "describe the virtual rig, and whose [sim] sets the options below (the command "
                  "line wins); its [machine] and [camera] are the virtual rig's")
      ->check(CLI::ExistingFile);
  cmd->add_option("--perturbation", args->perturbation,
                  "How far the hidden true camera lies from the nominal one, as a multiple of the "
                  "default offsets (0.3 mm, 1 deg, 1% focal length, 3 px, k1/k2); 0: exact")
      ->check(RangeOf(kPerturbation))
      ->capture_default_str();
  cmd->add_flag("--no-noise", args->no_noise, "Noise-free camera frames");
  cmd->add_option("--read-noise", args->read_noise, "Camera read noise, DN (default 1.0)")
      ->check(RangeOf(kReadNoise));
  cmd->add_option("--shot-gain", args->shot_gain,
                  "Camera shot noise: DN per electron (default 0.05)")
      ->check(RangeOf(kShotGain));
  cmd->add_option("--led-drift", args->drift,
                  "LED drift amplitude, relative gain over hours (default 0.015)")
      ->check(RangeOf(kDrift));
  cmd->add_option("--camera-tilt", args->camera_tilt_deg,
                  "The hidden true camera's tilt off the nominal one, deg (random axis; default "
                  "1 x --perturbation)")
      ->check(RangeOf(kTilt));
  cmd->add_option("--camera-offset", args->camera_offset_mm,
                  "The hidden true camera centre's distance from the nominal one, mm (random "
                  "direction; default 0.3 x --perturbation)")
      ->check(RangeOf(kOffset));
  cmd->add_option("--led-heights", args->led_heights,
                  "Fin LED heights as fractions of the sensor height (default 0.12,0.32)")
      ->delimiter(',')
      ->check(RangeOf(kFraction));
  cmd->add_option("--led-radial", args->led_radial,
                  "Fin LEDs' place across the fin, fraction of its half-width (default 0.55)")
      ->check(RangeOf(kFraction));
  cmd->add_option("--led-intensity", args->led_intensity,
                  "Red, green and blue LED intensities (default 1,1,10)")
      ->delimiter(',')
      ->expected(3)
      ->check(RangeOf(kIntensity));
  cmd->add_option("--blue-leds", args->blue_leds, "LEDs on the blue ring (default 12)")
      ->check(RangeOf(kBlueLeds));
  cmd->add_option("--blue-ring-radius", args->blue_ring_radius,
                  "The blue ring's radius, fraction of the base radius (default 0.35)")
      ->check(RangeOf(kFraction));
  AddFaultArgs(cmd, &args->faults, &args->fault_every);
  cmd->add_flag("--reset-on-open", args->reset_on_open,
                "The controller reboots whenever a host opens its port (DTR), 0.5 s of bootloader "
                "before it answers");
}

void AddFaultArgs(CLI::App* cmd, std::string* faults, double* every) {
  cmd->add_option("--faults", *faults,
                  "Faults to inject, comma-separated: drop, garble, garble-reply, stall, unplug, "
                  "reset, alarm, lost-position, power-cycle, hold, lost-reply, frame-drop, "
                  "frame-corrupt, or all")
      ->check(CLI::Validator(
          [](std::string& list) {
            try {
              ParseRigFaults(list);
              return std::string();
            } catch (const std::invalid_argument& e) {
              return std::string(e.what());
            }
          },
          "KIND,..."));
  cmd->add_option("--fault-every", *every, "Mean presses between faults (uniform 0.5-1.5x)")
      ->check(RangeOf(kFaultEvery))
      ->capture_default_str();
}

std::unique_ptr<RigFaultSchedule> StartFaults(const SimArgs& args, VirtualRig& rig,
                                              std::uint64_t seed) {
  if (args.faults.empty()) return nullptr;
  RigFaultScheduleOptions options;
  options.faults = ParseRigFaults(args.faults);
  options.every_probes = args.fault_every;
  options.seed = seed;
  return std::make_unique<RigFaultSchedule>(rig, options);
}

std::string DescribeFaults(const std::map<std::string, int>& injected) {
  int total = 0;
  std::string kinds;
  for (const auto& [kind, n] : injected) {
    total += n;
    kinds += (kinds.empty() ? "" : ", ") + std::to_string(n) + " " + kind;
  }
  return std::to_string(total) + " fault" + (total == 1 ? "" : "s") +
         (kinds.empty() ? "" : " (" + kinds + ")");
}

namespace {

// The LED options of `args` over `lighting`; checked by the caller.
void ApplyLedArgs(const SimArgs& args, LightingOptions* lighting) {
  if (!args.led_heights.empty()) lighting->fin_led_heights = args.led_heights;
  if (args.led_radial) lighting->fin_led_radial = *args.led_radial;
  if (!args.led_intensity.empty()) {
    if (args.led_intensity.size() != 3) {
      throw std::invalid_argument("--led-intensity takes three values (red, green, blue), got " +
                                  std::to_string(args.led_intensity.size()));
    }
    lighting->red_intensity = args.led_intensity[0];
    lighting->green_intensity = args.led_intensity[1];
    lighting->blue_intensity = args.led_intensity[2];
  }
  if (args.blue_leds) lighting->blue_ring_count = *args.blue_leds;
  if (args.blue_ring_radius) lighting->blue_ring_radius = *args.blue_ring_radius;
}

}  // namespace

namespace {

// The [sim] table of a gs360d.toml, read into a SimArgs for every knob the command line left
// alone (the command line wins). Each value is checked against its option's bounds, and an error
// names the file, the line and the key.
class SimSectionReader {
 public:
  SimSectionReader(JsonReader& r, const CLI::App& cmd) : r_(r), cmd_(cmd) {}

  void Number(const char* key, const char* flag, Bounds b, double& out) {
    double v = out;
    r_.Get(key, v);
    Check(key, v, b);
    if (!Given(flag)) out = v;
  }
  template <typename T>
  void Number(const char* key, const char* flag, Bounds b, std::optional<T>& out) {
    if (r_.Raw(key) == nullptr) return;
    T v{};
    r_.Get(key, v);
    Check(key, static_cast<double>(v), b);
    if (!Given(flag)) out = v;
  }
  void List(const char* key, const char* flag, Bounds b, std::size_t size,
            std::vector<double>& out) {
    std::vector<double> v;
    r_.Get(key, v);
    if (v.empty()) return;
    if (size != 0 && v.size() != size) {
      r_.Fail(key, "takes " + std::to_string(size) + " values, got " + std::to_string(v.size()));
    }
    for (double x : v) Check(key, x, b);
    if (!Given(flag)) out = v;
  }
  void Faults(std::string& out) {
    if (r_.Raw("faults") == nullptr) return;
    std::string v;
    r_.Get("faults", v);
    try {
      ParseRigFaults(v);
    } catch (const std::invalid_argument& e) {
      r_.Fail("faults", e.what());
    }
    if (!Given("--faults")) out = v;
  }
  void Noise(bool& no_noise) {
    bool noise = !no_noise;
    r_.Get("noise", noise);
    if (!Given("--no-noise")) no_noise = !noise;
  }
  void Seed(std::uint64_t& out) {
    std::uint64_t v = out;
    r_.Get("seed", v);
    if (!Given("--seed")) out = v;
  }

 private:
  bool Given(const char* flag) const { return cmd_.count(flag) > 0; }
  void Check(const char* key, double v, Bounds b) const {
    if (!(v >= b.lo && v <= b.hi)) {
      r_.Fail(key, "must be in " + FormatFixed(b.lo, 3) + ".." + FormatFixed(b.hi, 3) + ", got " +
                       FormatFixed(v, 3));
    }
  }

  JsonReader& r_;
  const CLI::App& cmd_;
};

}  // namespace

RunConfig LoadSimConfig(const CLI::App& cmd, SimArgs* args, std::uint64_t* seed) {
  if (args->config.empty()) {
    RunConfig config;
    if (ParseCncFirmware(args->firmware) == CncFirmware::kMarlin) ApplyPrinterDefaults(&config);
    return config;
  }
  const auto read_sim = [&](JsonReader& r) {
    SimSectionReader s(r, cmd);
    s.Seed(*seed);
    s.Number("perturbation", "--perturbation", kPerturbation, args->perturbation);
    s.Noise(args->no_noise);
    s.Number("read_noise", "--read-noise", kReadNoise, args->read_noise);
    s.Number("shot_gain", "--shot-gain", kShotGain, args->shot_gain);
    s.Number("led_drift", "--led-drift", kDrift, args->drift);
    s.Number("camera_tilt", "--camera-tilt", kTilt, args->camera_tilt_deg);
    s.Number("camera_offset", "--camera-offset", kOffset, args->camera_offset_mm);
    s.List("led_heights", "--led-heights", kFraction, 0, args->led_heights);
    s.Number("led_radial", "--led-radial", kFraction, args->led_radial);
    s.List("led_intensity", "--led-intensity", kIntensity, 3, args->led_intensity);
    s.Number("blue_leds", "--blue-leds", kBlueLeds, args->blue_leds);
    s.Number("blue_ring_radius", "--blue-ring-radius", kFraction, args->blue_ring_radius);
    s.Faults(args->faults);
    s.Number("fault_every", "--fault-every", kFaultEvery, args->fault_every);
  };
  return LoadDaemonConfig(args->config, read_sim).run;
}

void ApplySimArgs(const SimArgs& args, VirtualRigOptions* options) {
  if (!std::isfinite(args.perturbation) || args.perturbation < 0.0) {
    throw std::invalid_argument("--perturbation must be >= 0, got " +
                                FormatFixed(args.perturbation, 3));
  }
  options->cnc.firmware = ParseCncFirmware(args.firmware);
  if (args.reset_on_open) {
    options->cnc.reset_on_open = true;
    options->cnc.boot_delay = std::chrono::milliseconds(500);
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
  if (args.camera_tilt_deg) p.rotation_deg = *args.camera_tilt_deg;
  if (args.camera_offset_mm) p.translation_mm = *args.camera_offset_mm;
  ApplyLedArgs(args, &options->camera.lighting);
  SensorModelOptions& sensor = options->camera.sensor;
  if (args.no_noise) sensor.noise = false;
  if (args.read_noise) sensor.read_noise = *args.read_noise;
  if (args.shot_gain) sensor.shot_gain = *args.shot_gain;
  if (args.drift) sensor.drift_amplitude = *args.drift;
  try {
    p.Check();
    sensor.Check();
    options->camera.lighting.Check();
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(std::string(e.what()) + " (from --perturbation " +
                                FormatFixed(s, 2) + ", the camera, noise or LED options)");
  }
}

}  // namespace gs360::cli
