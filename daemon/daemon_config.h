#pragma once
// gs360d's configuration: one TOML file (docs/daemon.md lists every key with its default), then
// command-line overrides. One rig per daemon: the [rig], [machine], [camera], [engine] and [plan]
// sections are the defaults every run of this daemon starts from (the run's own request may
// change the sensor shape and the plan, never the machine, the camera or the limits).
//
// Errors: ConfigError (base/json_reader.h) naming the file, the line and the dotted key, for
// TOML syntax, unknown keys, wrong types and invalid values.

#include <Eigen/Core>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <string>
#include <string_view>
#include <vector>

#include "daemon/notifier.h"
#include "run/run_config.h"
#include "run/safety.h"

namespace gs360 {

struct ServerConfig {
  // Address to bind. Anything but a loopback address needs a token.
  std::string listen = "127.0.0.1";
  int port = 7360;  // 0: any free port (the chosen one is written to DATA/daemon.json)
  // Bearer token every API request must carry; empty = none (loopback only). The environment
  // variable GS360D_TOKEN, when set, takes precedence over the file.
  std::string token;
  std::int64_t max_body_bytes = 1 << 20;     // JSON request bodies
  std::int64_t max_upload_bytes = 64 << 20;  // mesh uploads
  // Threads that run slow requests (planning, uploads, files); two more run the quick ones
  // (status, pause, resume, cancel). Connections themselves take no thread (docs/daemon.md).
  int threads = 4;
  int max_connections = 2048;     // open sockets of every kind; more are closed at once
  int max_event_streams = 256;    // GET /api/v1/events streams; more get 503
  double request_timeout_s = 15;  // to send a whole request (headers and body)
  int idle_timeout_s = 10;        // silence after which a connection is closed
  void Check() const;
};

struct LogConfig {
  std::string level = "info";  // trace, debug, info, warn, error
  std::int64_t file_max_bytes = 10 << 20;
  int files = 5;  // rotated files kept in DATA/log/
  void Check() const;
};

struct CalibrationDefaults {
  // Folder of checkerboard images of this rig's lens (taken before assembly); empty = the
  // nominal intrinsics. Named by the operator in the file, never by a request.
  std::string checkerboards;
  int threads = 2;
  void Check() const;
};

// A run's plan, unless its configuration or request says otherwise: about an hour of machine
// time on any rig.
inline constexpr double kDefaultMachineHours = 1.0;
inline RunConfig DefaultDaemonRun() {
  RunConfig run;
  run.plan.machine_hours = kDefaultMachineHours;
  return run;
}

struct DaemonConfig {
  std::filesystem::path data_dir = "gs360-data";  // database, logs, meshes, models
  ServerConfig server;
  LogConfig log;
  SafetyLimits limits;
  CalibrationDefaults calibration;
  // [[notify]]: where the run's events are sent (daemon/notifier.h); none by default.
  std::vector<NotifyTarget> notify;
  // The rig, machine, camera, engine and plan defaults of every run (machine.uri and camera.uri
  // may stay empty: the daemon then serves its data but refuses to start runs). Its plan is
  // sized in machine time (plan.machine_hours = kDefaultMachineHours) unless a count is given.
  RunConfig run = DefaultDaemonRun();
  // Throws ConfigError naming the key (no file line: for values changed after loading).
  void Check() const;
  // The path of the run database inside data_dir.
  std::filesystem::path DatabasePath() const { return data_dir / "gs360.db"; }
};

// Parses TOML text. `where` names the source in messages (the file's path). Relative paths in
// the file (data_dir, rig.mesh_path, calibration.checkerboards) are taken relative to `base_dir`.
// The file's [sim] table holds the virtual rig's knobs (noise, LEDs, faults; docs/virtual_rig.md).
// gs360d does not read it; `gs360 sim-rig` and `gs360 demo` pass `read_sim`, which reads it with
// the same checks (unknown keys, types, the file's line in every error).
DaemonConfig DaemonConfigFromToml(std::string_view text, const std::string& where,
                                  const std::filesystem::path& base_dir = {},
                                  const std::function<void(JsonReader&)>& read_sim = {});
DaemonConfig LoadDaemonConfig(const std::filesystem::path& path,
                              const std::function<void(JsonReader&)>& read_sim = {});
// The configuration as TOML (every key, with its value): `gs360d --print-config`, which shows
// webhooks by their scheme and host and the token as "(set)". With `keep_secrets`, both as they
// are: a configuration written for another gs360d to read (`gs360 demo --config`).
std::string DaemonConfigToToml(const DaemonConfig& config, bool keep_secrets = false);

// True for 127.0.0.0/8, ::1 and "localhost".
bool IsLoopbackAddress(std::string_view address);

}  // namespace gs360
