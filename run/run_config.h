#pragma once
// Everything a calibration run needs, stored as JSON in the run's database row so that a resume
// uses exactly what the run started with.

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <string>

#include <nlohmann/json_fwd.hpp>

#include "capture/capture_press.h"
#include "capture/frame_source.h"
#include "gcode/machine.h"
#include "plan/plan.h"
#include "rig/rig_config.h"

namespace gs360 {

struct MachineConfig {
  std::string uri;  // serial device, pty path, "serial:VID:PID" or "tcp://host:port"
  int baud = 115200;
  // What the controller speaks (gcode/machine.h): "auto" tells from what it says when the port
  // opens (a GRBL welcome, Marlin's "start"), or asks it (M115).
  MachineFirmware firmware = MachineFirmware::kAuto;
  // $H at the start of a run (and after a reset or reconnect). Without homing the operator
  // vouches that MPos is right (verify_position then only checks the controller answers).
  bool home = true;
  double verify_tolerance_mm = 0.02;
  // The least time between two status queries ('?'), 1..1000 ms: GRBL on an AVR asks for at
  // most 5 Hz (200); grblHAL and the virtual CNC take far more.
  int status_interval_ms = 200;
  void Check() const;
};

struct CameraConfig {
  std::string uri;  // "libcamera:0", "v4l2:/dev/video0", "replay:DIR", "socket:PATH"
  CameraControls controls;
  PressCaptureOptions capture;  // K frames averaged, stale-frame rules
  void Check() const;
};

struct EngineConfig {
  int max_attempts = 2;    // per probe, across the whole run (resume included)
  int recheck_probes = 3;  // committed probes re-pressed on resume (0 = none)
  // Impression shift (MeasureImpressionShift, capture/impression.h) that means the sensor moved.
  // The same press captured twice, each against its own reference and under other noise and LED
  // drift, lands at most 0.20 px apart on the virtual rig (14,058 pairs over 213 probes: median
  // 0.02, 99.9th percentile 0.16 px; tests/run/recheck_limit_test.cc): the limit is about 5x
  // (4.9x) that worst case, about 0.17 mm of sideways sensor move (5.9 px/mm at the median probe).
  double recheck_max_shift_px = 1.0;
  // Only clear impressions are compared: a peak colour difference of at least this many DN
  // (8-bit scale) in a blob smaller than a quarter of the frame each way. A faint one (a probe at
  // a fin's edge) has a centroid that noise and LED drift move by tens of pixels.
  double recheck_min_peak_dn = 20.0;
  double sync_timeout_s = 120.0;      // longest wait for a press's G4 ok
  double reconnect_timeout_s = 60.0;  // how long a vanished port is waited for
  int max_recoveries = 10;            // resets / reconnects handled in one session before giving up
  // A press frame must show an impression within impression_radius_px of where the probe's
  // point projects (through the nominal camera): PressCheck (capture/press_check.h), against the
  // session's reference frame and the noise and null distribution measured in the session. A
  // frame that does not is a probe failure that is not retried (a second press would show the
  // same); a frozen camera or a frame changed everywhere is retried.
  bool require_impression = true;
  // > 0: the signal-to-noise ratio an impression must reach, instead of the one the session
  // derives from its own frames (a user's override).
  double impression_min_snr = 0.0;
  double impression_radius_px = 40.0;
  // Runs stored before the check above: their ImpressionContrast threshold (capture/impression.h),
  // kept with its retries so that such a run resumes as it started. 0 (new runs): not used.
  double impression_min_contrast = 0.0;
  // When the resume check could compare no re-pressed probe: "ask" (stop, awaiting "sensor") or
  // "continue" (a warning in the log).
  std::string unverified_resume = "ask";
  void Check() const;
};

// Stopping a run once it has learnt enough (docs/running.md, "Until converged"): at the end of
// each round of plan.checkpoint_probes probes the daemon calibrates on what is captured, in the
// background; the run ends when the held-out error meets every target at two checkpoints in a
// row and the last one improved on the one before by less than min_improvement.
struct ConvergeConfig {
  bool enabled = false;
  // Relative improvement of the mean and of the > 50 deg band error (the larger counts) below
  // which the error has stopped improving.
  double min_improvement = 0.1;
  void Check() const;
};

// The round size of a run that converges when its plan sets none (plan.checkpoint_probes).
inline constexpr int kDefaultConvergeRound = 250;

struct RunConfig {
  std::string name;
  RigConfig rig;
  PlanOptions plan;
  MachineConfig machine;
  CameraConfig camera;
  EngineConfig engine;
  ConvergeConfig converge;
  // Throws std::invalid_argument naming the field by its path here ("plan.probe_count",
  // "rig.shape.cylinder.radius"), the rule and the value.
  void Check() const;
};

// A new run's name: printable UTF-8 (no control character, no bidirectional override) of at
// most this many characters; names are printed on terminals (`gs360 run list`) and in logs.
// Checked where runs are created (not by RunConfig::Check(), so that a run an older daemon
// stored still resumes; what prints names escapes them).
inline constexpr std::size_t kMaxRunNameChars = 100;
// Empty for a valid name, else the rule it breaks and the name, escaped ("must be printable
// UTF-8 ... (control character U+001B at character 1), got "\e[2J"").
std::string CheckRunName(const std::string& name);
// The field a RunConfig::Check() message names ("plan.probe_count must be ..." ->
// "plan.probe_count"), also for a part's own message ("PlanOptions.probe_count ..."); "" when
// it names none.
std::string RunConfigField(const std::string& check_message);
// `message` with a leading type-named field renamed to its path ("PlanOptions.seed ..." ->
// "plan.seed ..."); other messages unchanged.
std::string WithRunConfigPath(const std::string& message);

class JsonReader;

nlohmann::json RunConfigToJson(const RunConfig& config);
// The "converge" object of a request or a configuration ({enabled, min_improvement}).
void ReadConvergeConfig(JsonReader& reader, ConvergeConfig& converge);
// Reads the sections present (name, rig, plan, machine, camera, engine, converge) into `config`;
// absent
// keys keep its values; no Check(). For larger documents (the daemon's configuration).
void ReadRunConfig(JsonReader& reader, RunConfig& config);
// The plan options a user may set (docs/running.md), read into `plan`. With `machine`, also the
// "machine" object (the controller's rates, accelerations and travel: gs360d.toml's
// [plan.machine], never a run's request).
void ReadPlanOptions(JsonReader& reader, PlanOptions& plan, bool machine = false);
// plan.probe_count alone, under another key (a request's "probes"), with the same range.
void ReadProbeCount(JsonReader& reader, const char* key, PlanOptions& plan);
// Strict: unknown keys, wrong types and invalid values are ConfigError naming `where` and the
// field path. Absent keys keep their defaults.
RunConfig RunConfigFromJson(const nlohmann::json& json, const std::string& where);
// A JSON file; syntax errors name the line and column.
RunConfig LoadRunConfigFile(const std::string& path);

class RunDatabase;
// A stored run's configuration. Throws std::runtime_error naming the run and the database when
// it has no such run, ConfigError naming them when its stored configuration is not valid.
RunConfig StoredRunConfig(const RunDatabase& db, std::int64_t run_id);

}  // namespace gs360
