#include "run/run_config.h"

#include <stdexcept>
#include <string_view>

#include <nlohmann/json.hpp>

#include "base/format.h"
#include "base/json_reader.h"
#include "base/text.h"
#include "storage/run_database.h"

namespace gs360 {
namespace {

[[noreturn]] void Invalid(const std::string& field, const std::string& value,
                          const std::string& rule) {
  throw std::invalid_argument(field + " " + rule + ", got " + value);
}

// The plan options a user may set, by name and range: the one place their values are checked
// as they are read (JsonReader), before anything plans with them. One table serves both
// directions. The ranges are physical bounds wide enough for any rig, narrow enough that no
// value makes the planner allocate or loop without end.
constexpr double kHalfPi = 1.5707963267948966;
constexpr NumberRange kMm1000{0.0, 1000.0, false, "mm"};
constexpr NumberRange kSeconds{0.0, 3600.0, false, "s"};
struct PlanDoubleField {
  const char* name;
  double PlanOptions::*member;
  NumberRange range;
};
constexpr PlanDoubleField kPlanDoubles[] = {
    {"candidate_factor", &PlanOptions::candidate_factor, {1.0, 100.0}},
    {"machine_hours", &PlanOptions::machine_hours, {0.0, 1000.0, false, "h"}},
    {"ball_radius", &PlanOptions::ball_radius, {0.0, 50.0, true, "mm"}},
    {"press_depth", &PlanOptions::press_depth, {0.0, 10.0, true, "mm"}},
    {"clearance", &PlanOptions::clearance, {0.0, 100.0, true, "mm"}},
    {"stylus_radius", &PlanOptions::stylus_radius, {0.0, 50.0, true, "mm"}},
    {"stylus_length", &PlanOptions::stylus_length, {0.0, 1000.0, true, "mm"}},
    {"holder_radius", &PlanOptions::holder_radius, kMm1000},
    {"holder_length", &PlanOptions::holder_length, kMm1000},
    {"press_feed_mm_per_min",
     &PlanOptions::press_feed_mm_per_min,
     {1.0, 100000.0, false, "mm/min"}},
    {"retract_feed_mm_per_min",
     &PlanOptions::retract_feed_mm_per_min,
     {0.0, 100000.0, false, "mm/min"}},
    {"settle_dwell_s", &PlanOptions::settle_dwell_s, kSeconds},
    {"capture_time_s", &PlanOptions::capture_time_s, kSeconds},
    {"status_poll_latency_s", &PlanOptions::status_poll_latency_s, kSeconds},
    {"host_latency_s", &PlanOptions::host_latency_s, kSeconds},
    {"reference_dwell_s", &PlanOptions::reference_dwell_s, kSeconds},
    {"fov_margin_rad", &PlanOptions::fov_margin_rad, {0.0, kHalfPi, false, "rad"}},
    {"image_margin_px", &PlanOptions::image_margin_px, {0.0, 10000.0, false, "px"}},
    {"max_view_angle_rad", &PlanOptions::max_view_angle_rad, {0.0, kHalfPi, true, "rad"}},
    {"travel_clearance", &PlanOptions::travel_clearance, {0.0, 100.0, false, "mm"}},
    {"travel_limit_margin", &PlanOptions::travel_limit_margin, kMm1000},
};
struct PlanIntField {
  const char* name;
  int PlanOptions::*member;
  IntRange range;
};
constexpr IntRange kProbeCountRange{1, 1000000};
constexpr PlanIntField kPlanInts[] = {
    {"probe_count", &PlanOptions::probe_count, kProbeCountRange},
    {"reference_every", &PlanOptions::reference_every, {0, 1000000}},
    {"neighbours", &PlanOptions::neighbours, {1, 100}},
    {"max_improvement_passes", &PlanOptions::max_improvement_passes, {0, 1000}},
    {"checkpoint_probes", &PlanOptions::checkpoint_probes, {0, 1000000}},
};
// Candidates drawn: probe_count x candidate_factor, at most this many (the sampler holds them
// all in memory).
constexpr double kMaxCandidates = 1e7;

nlohmann::json PlanOptionsToJson(const PlanOptions& p) {
  nlohmann::json j;
  for (const auto& f : kPlanDoubles) j[f.name] = p.*(f.member);
  for (const auto& f : kPlanInts) j[f.name] = p.*(f.member);
  j["seed"] = p.seed;
  j["count_is_kept"] = p.count_is_kept;
  j["optimise_order"] = p.optimise_order;
  j["return_to_start"] = p.return_to_start;
  j["start_machine"] = {p.start_machine.x(), p.start_machine.y(), p.start_machine.z()};
  const auto vec = [](const Eigen::Vector3d& v) { return nlohmann::json{v.x(), v.y(), v.z()}; };
  j["machine"] = {{"max_rate_mm_per_min", vec(p.machine.max_rate_mm_per_min)},
                  {"acceleration_mm_per_s2", vec(p.machine.acceleration_mm_per_s2)},
                  {"max_travel_mm", vec(p.machine.max_travel_mm)},
                  {"junction_deviation_mm", p.machine.junction_deviation_mm},
                  {"planner_blocks", p.machine.planner_blocks}};
  if (p.machine.travel_min_mm) j["machine"]["travel_min_mm"] = vec(*p.machine.travel_min_mm);
  return j;
}

}  // namespace

static void ReadMachineSettings(JsonReader& r, MachineSettings& m) {
  r.Get("max_rate_mm_per_min", m.max_rate_mm_per_min, {0.0, 1e6, true, "mm/min"});
  r.Get("acceleration_mm_per_s2", m.acceleration_mm_per_s2, {0.0, 1e7, true, "mm/s^2"});
  r.Get("max_travel_mm", m.max_travel_mm, {0.0, 1e5, true, "mm"});
  if (r.Raw("travel_min_mm") != nullptr) {
    Eigen::Vector3d v = Eigen::Vector3d::Zero();
    r.Get("travel_min_mm", v, {-1e5, 1e5, false, "mm"});
    m.travel_min_mm = v;
  }
  r.Get("junction_deviation_mm", m.junction_deviation_mm, {0.0, 10.0, false, "mm"});
  r.Get("planner_blocks", m.planner_blocks, IntRange{1, 1000});
}

void ReadProbeCount(JsonReader& r, const char* key, PlanOptions& p) {
  if (r.Raw(key) == nullptr) return;
  r.Get(key, p.probe_count, kProbeCountRange);
  p.machine_hours = 0.0;  // a count asked for is the count planned
}

void ReadPlanOptions(JsonReader& r, PlanOptions& p, bool machine) {
  if (machine) r.Object("machine", [&](JsonReader& o) { ReadMachineSettings(o, p.machine); });
  for (const auto& f : kPlanDoubles) r.Get(f.name, p.*(f.member), f.range);
  for (const auto& f : kPlanInts) r.Get(f.name, p.*(f.member), f.range);
  // A probe count without machine_hours is the count planned; a configuration stored before
  // the option existed reads the same way, so its plan and hash stay what they were.
  if (r.Raw("probe_count") != nullptr && r.Raw("machine_hours") == nullptr) p.machine_hours = 0.0;
  if (p.probe_count * p.candidate_factor > kMaxCandidates) {
    r.Fail("candidate_factor",
           "probe_count x candidate_factor (the candidates drawn) must be at "
           "most 10000000, got " +
               std::to_string(p.probe_count) + " x " + FormatFixed(p.candidate_factor, 2));
  }
  r.Get("seed", p.seed);
  r.Get("count_is_kept", p.count_is_kept);
  r.Get("optimise_order", p.optimise_order);
  r.Get("return_to_start", p.return_to_start);
  r.Get("start_machine", p.start_machine, NumberRange{-1e5, 1e5, false, "mm"});
}

void MachineConfig::Check() const {
  if (uri.empty()) Invalid("machine.uri", "\"\"", "must name the controller's port");
  if (baud <= 0) Invalid("machine.baud", std::to_string(baud), "must be > 0");
  if (!(verify_tolerance_mm > 0.0)) {
    Invalid("machine.verify_tolerance_mm", std::to_string(verify_tolerance_mm), "must be > 0");
  }
  if (status_interval_ms < 1 || status_interval_ms > 1000) {
    Invalid("machine.status_interval_ms", std::to_string(status_interval_ms), "must be in 1..1000");
  }
}

void CameraConfig::Check() const {
  if (uri.empty()) Invalid("camera.uri", "\"\"", "must name the frame source");
  controls.Check();
  capture.Check();
}

void EngineConfig::Check() const {
  if (max_attempts < 1)
    Invalid("engine.max_attempts", std::to_string(max_attempts), "must be >= 1");
  if (recheck_probes < 0) {
    Invalid("engine.recheck_probes", std::to_string(recheck_probes), "must be >= 0");
  }
  if (!(recheck_max_shift_px > 0.0)) {
    Invalid("engine.recheck_max_shift_px", std::to_string(recheck_max_shift_px), "must be > 0");
  }
  if (!(recheck_min_peak_dn > 0.0 && recheck_min_peak_dn < 442.0)) {
    Invalid("engine.recheck_min_peak_dn", std::to_string(recheck_min_peak_dn),
            "must be in (0, 442) DN");
  }
  if (!(sync_timeout_s > 0.0)) {
    Invalid("engine.sync_timeout_s", std::to_string(sync_timeout_s), "must be > 0");
  }
  if (!(reconnect_timeout_s >= 0.0)) {
    Invalid("engine.reconnect_timeout_s", std::to_string(reconnect_timeout_s), "must be >= 0");
  }
  if (max_recoveries < 0) {
    Invalid("engine.max_recoveries", std::to_string(max_recoveries), "must be >= 0");
  }
  if (!(impression_min_snr >= 0.0 && impression_min_snr <= 1e6)) {
    Invalid("engine.impression_min_snr", std::to_string(impression_min_snr),
            "must be in [0, 1e6] (0: derived from the session)");
  }
  if (!(impression_min_contrast == 0.0 ||
        (impression_min_contrast >= 1.0 && impression_min_contrast <= 1e6))) {
    Invalid("engine.impression_min_contrast", std::to_string(impression_min_contrast),
            "must be 0 (not used) or in [1, 1e6]");
  }
  if (!(impression_radius_px > 0.0)) {
    Invalid("engine.impression_radius_px", std::to_string(impression_radius_px), "must be > 0");
  }
  if (unverified_resume != "ask" && unverified_resume != "continue") {
    Invalid("engine.unverified_resume", "\"" + unverified_resume + "\"", "must be ask or continue");
  }
}

void ConvergeConfig::Check() const {
  if (!(min_improvement >= 0.0 && min_improvement < 1.0)) {
    Invalid("converge.min_improvement", std::to_string(min_improvement), "must be in [0, 1)");
  }
}

namespace {

// The parts' Check()s name a field by its type ("PlanOptions.probe_count"); a run
// configuration's errors name it by its path in the configuration ("plan.probe_count").
struct FieldPrefix {
  std::string_view type;
  std::string_view path;
};
constexpr FieldPrefix kFieldPrefixes[] = {
    {"PlanOptions.", "plan."},
    {"MachineSettings.", "plan.machine."},
    {"RigConfig.", "rig."},
    {"SensorShapeOptions.", "rig.shape."},
    {"CylinderCapOptions.", "rig.shape.cylinder."},
    {"ConeOptions.", "rig.shape.cone."},
    {"SplineOptions.", "rig.shape.spline."},
    {"TessellationOptions.", "rig.shape."},
    {"FinOptions.", "rig.fins."},
    {"FinOptions: ", "rig.fins: "},
    {"FisheyeIntrinsics.", "rig.camera."},
    {"CameraControls.", "camera."},
    {"PressCaptureOptions.timeout ", "camera.capture_timeout_ms "},
    {"PressCaptureOptions.", "camera."},
};

std::string WithConfigPath(std::string message) {
  for (const auto& [type, path] : kFieldPrefixes) {
    if (message.rfind(type, 0) == 0) return std::string(path) + message.substr(type.size());
  }
  return message;
}

template <typename F>
void CheckPart(const F& check) {
  try {
    check();
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(WithConfigPath(e.what()));
  }
}

}  // namespace

std::string WithRunConfigPath(const std::string& message) {
  return WithConfigPath(message);
}

std::string RunConfigField(const std::string& message) {
  const std::string renamed = WithConfigPath(message);
  const std::string first = renamed.substr(0, renamed.find_first_of(" [=:"));
  const bool path =
      !first.empty() &&
      first.find_first_not_of("abcdefghijklmnopqrstuvwxyz0123456789_.") == std::string::npos;
  return path ? first : std::string();
}

std::string CheckRunName(const std::string& name) {
  const std::string problem = PrintableTextProblem(name, kMaxRunNameChars);
  if (problem.empty()) return "";
  return "must be printable UTF-8 without control characters, at most " +
         std::to_string(kMaxRunNameChars) + " characters (" + problem + "), got \"" +
         EscapeControlCharacters(name.substr(0, 4 * kMaxRunNameChars)) + "\"";
}

void RunConfig::Check() const {
  CheckPart([&] { rig.Check(); });
  CheckPart([&] { plan.Check(); });
  CheckPart([&] { machine.Check(); });
  CheckPart([&] { camera.Check(); });
  CheckPart([&] { engine.Check(); });
  CheckPart([&] { converge.Check(); });
  if (!(plan.press_depth < rig.gel_thickness)) {
    Invalid("plan.press_depth", std::to_string(plan.press_depth),
            "must be less than rig.gel_thickness (" + std::to_string(rig.gel_thickness) + ")");
  }
  if (std::abs(plan.ball_radius - rig.ball_radius) > 1e-9) {
    Invalid("plan.ball_radius", std::to_string(plan.ball_radius),
            "must equal rig.ball_radius (" + std::to_string(rig.ball_radius) + ")");
  }
}

nlohmann::json RunConfigToJson(const RunConfig& c) {
  nlohmann::json out = {
      {"name", c.name},
      {"rig", RigConfigToJson(c.rig)},
      {"plan", PlanOptionsToJson(c.plan)},
      {"machine",
       {{"uri", c.machine.uri},
        {"baud", c.machine.baud},
        {"firmware", std::string(MachineFirmwareName(c.machine.firmware))},
        {"home", c.machine.home},
        {"verify_tolerance_mm", c.machine.verify_tolerance_mm},
        {"status_interval_ms", c.machine.status_interval_ms}}},
      {"camera",
       {{"uri", c.camera.uri},
        {"exposure_us", c.camera.controls.exposure_us},
        {"analogue_gain", c.camera.controls.analogue_gain},
        {"colour_gains", {c.camera.controls.colour_gains[0], c.camera.controls.colour_gains[1]}},
        {"lock", c.camera.controls.lock},
        {"width", c.camera.controls.width},
        {"height", c.camera.controls.height},
        {"frames_to_average", c.camera.capture.frames_to_average},
        {"capture_timeout_ms", c.camera.capture.timeout.count()},
        {"max_stale_frames", c.camera.capture.max_stale_frames},
        {"reject_outliers", c.camera.capture.reject_outliers},
        {"outlier_dn", c.camera.capture.outlier_dn},
        {"outlier_fraction", c.camera.capture.outlier_fraction},
        {"max_outlier_frames", c.camera.capture.max_outlier_frames}}},
      {"engine",
       {{"max_attempts", c.engine.max_attempts},
        {"recheck_probes", c.engine.recheck_probes},
        {"recheck_max_shift_px", c.engine.recheck_max_shift_px},
        {"recheck_min_peak_dn", c.engine.recheck_min_peak_dn},
        {"sync_timeout_s", c.engine.sync_timeout_s},
        {"reconnect_timeout_s", c.engine.reconnect_timeout_s},
        {"max_recoveries", c.engine.max_recoveries},
        {"require_impression", c.engine.require_impression},
        {"impression_min_snr", c.engine.impression_min_snr},
        {"impression_radius_px", c.engine.impression_radius_px},
        {"unverified_resume", c.engine.unverified_resume}}},
      {"converge",
       {{"enabled", c.converge.enabled}, {"min_improvement", c.converge.min_improvement}}},
  };
  // Only a run stored before the signal-to-noise check has it (EngineConfig).
  if (c.engine.impression_min_contrast > 0.0) {
    out["engine"]["impression_min_contrast"] = c.engine.impression_min_contrast;
  }
  return out;
}

void ReadConvergeConfig(JsonReader& r, ConvergeConfig& c) {
  r.Get("enabled", c.enabled);
  r.Get("min_improvement", c.min_improvement);
}

void ReadRunConfig(JsonReader& r, RunConfig& c) {
  r.Get("name", c.name);
  r.Object("rig", [&](JsonReader& o) { ReadRigConfig(o, c.rig); });
  r.Object("plan", [&](JsonReader& o) { ReadPlanOptions(o, c.plan, /*machine=*/true); });
  c.plan.ball_radius = c.rig.ball_radius;
  r.Object("machine", [&](JsonReader& o) {
    o.Get("uri", c.machine.uri);
    o.Get("baud", c.machine.baud);
    if (o.Raw("firmware") != nullptr) {
      std::string name;
      o.Get("firmware", name);
      const auto firmware = ParseMachineFirmware(name);
      if (!firmware)
        o.Fail("firmware", "expected \"auto\", \"grbl\" or \"marlin\", got \"" + name + "\"");
      c.machine.firmware = *firmware;
    }
    o.Get("home", c.machine.home);
    o.Get("verify_tolerance_mm", c.machine.verify_tolerance_mm);
    o.Get("status_interval_ms", c.machine.status_interval_ms);
  });
  r.Object("camera", [&](JsonReader& o) {
    o.Get("uri", c.camera.uri);
    o.Get("exposure_us", c.camera.controls.exposure_us);
    o.Get("analogue_gain", c.camera.controls.analogue_gain);
    if (const auto* g = o.Raw("colour_gains")) {
      if (!g->is_array() || g->size() != 2 || !(*g)[0].is_number() || !(*g)[1].is_number()) {
        o.Fail("colour_gains", "expected [red, blue], got " + g->dump());
      }
      c.camera.controls.colour_gains = {(*g)[0].get<double>(), (*g)[1].get<double>()};
    }
    o.Get("lock", c.camera.controls.lock);
    o.Get("width", c.camera.controls.width);
    o.Get("height", c.camera.controls.height);
    o.Get("frames_to_average", c.camera.capture.frames_to_average);
    int timeout_ms = static_cast<int>(c.camera.capture.timeout.count());
    o.Get("capture_timeout_ms", timeout_ms);
    c.camera.capture.timeout = std::chrono::milliseconds(timeout_ms);
    o.Get("max_stale_frames", c.camera.capture.max_stale_frames);
    o.Get("reject_outliers", c.camera.capture.reject_outliers);
    o.Get("outlier_dn", c.camera.capture.outlier_dn);
    o.Get("outlier_fraction", c.camera.capture.outlier_fraction);
    o.Get("max_outlier_frames", c.camera.capture.max_outlier_frames);
  });
  r.Object("engine", [&](JsonReader& o) {
    o.Get("max_attempts", c.engine.max_attempts);
    o.Get("recheck_probes", c.engine.recheck_probes);
    o.Get("recheck_max_shift_px", c.engine.recheck_max_shift_px);
    o.Get("recheck_min_peak_dn", c.engine.recheck_min_peak_dn);
    o.Get("sync_timeout_s", c.engine.sync_timeout_s);
    o.Get("reconnect_timeout_s", c.engine.reconnect_timeout_s);
    o.Get("max_recoveries", c.engine.max_recoveries);
    o.Get("require_impression", c.engine.require_impression);
    o.Get("impression_min_snr", c.engine.impression_min_snr);
    o.Get("impression_radius_px", c.engine.impression_radius_px);
    o.Get("impression_min_contrast", c.engine.impression_min_contrast);
    o.Get("unverified_resume", c.engine.unverified_resume);
  });
  r.Object("converge", [&](JsonReader& o) { ReadConvergeConfig(o, c.converge); });
}

RunConfig RunConfigFromJson(const nlohmann::json& json, const std::string& where) {
  RunConfig c;
  JsonReader r(json, where);
  ReadRunConfig(r, c);
  r.RejectUnknown();
  try {
    c.Check();
  } catch (const std::invalid_argument& e) {
    throw ConfigError(where + ": " + e.what());
  }
  return c;
}

RunConfig LoadRunConfigFile(const std::string& path) {
  return RunConfigFromJson(ParseJsonFile(path), path);
}

RunConfig StoredRunConfig(const RunDatabase& db, std::int64_t run_id) {
  const auto run = db.GetRun(run_id);
  if (!run) {
    throw std::runtime_error("no run " + std::to_string(run_id) + " in " + db.path().string());
  }
  const std::string where = db.path().string() + ": run " + std::to_string(run_id);
  return RunConfigFromJson(ParseJsonText(run->config_json, where), where);
}

}  // namespace gs360
