#pragma once
// gs360d's state: one rig, one data folder, one database, at most one run moving the machine and
// at most one calibration at a time. The HTTP API (daemon/http_api.h) is a thin layer over this.
//
// The data folder (DaemonConfig::data_dir) holds everything the daemon writes:
//   gs360.db            runs, probes, frames, events, calibration artifacts, models
//   gs360d.lock         held while the daemon runs (a second daemon refuses to start)
//   daemon.json         pid and URL of the running daemon (for clients on the same host)
//   log/gs360d.log      rotating log
//   meshes/ID.EXT       uploaded sensor meshes, by content id
//   runs/ID/            per run: calibration.json (the job's state), model/ (the exports)
// Requests name runs and meshes by id, never by path.
//
// Start-up never moves the machine: a run left `running` by a daemon that died becomes
// `interrupted` and waits for an explicit resume; the controller's port is locked but not opened
// until a run starts. Shutdown() finishes the current probe, retracts and leaves the run
// `interrupted` (resumable); a calibration is stopped at its next step (its finished stages stay
// cached).
//
// Threads: every public method may be called from any thread. Expected outcomes (no such run, a
// state that does not allow the action) are ActionResult values; bad requests throw ConfigError
// naming the field; I/O problems throw StorageError / std::runtime_error.

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "daemon/daemon_config.h"
#include "daemon/event_hub.h"
#include "daemon/instance_lock.h"
#include "daemon/notifier.h"
#include "daemon/notify_feed.h"
#include "run/run_engine.h"

namespace gs360 {

enum class ActionStatus { kAccepted, kNotFound, kConflict };

struct ActionResult {
  ActionStatus status = ActionStatus::kAccepted;
  std::string message;  // what happened or why not
  std::string state;    // the run's state after the call (or as it is, for a conflict)
};

// The binary files the API serves for a run.
enum class RunFile { kModel, kOnnx, kReport, kValidation };

class CalibrationJobs;
class ConvergenceWatch;

class Daemon {
 public:
  // Takes the data folder's lock (and the machine port's), opens or creates the database, marks
  // runs the previous daemon left running as interrupted, and starts the event pump. Throws
  // LockHeldError (naming the holder), StorageError, std::runtime_error.
  explicit Daemon(DaemonConfig config);
  ~Daemon();
  Daemon(const Daemon&) = delete;
  Daemon& operator=(const Daemon&) = delete;

  // Stops an active run (finish the probe, retract, interrupted) and the calibration, waits for
  // both, closes the event stream. Idempotent.
  void Shutdown();

  const DaemonConfig& config() const { return config_; }
  EventHub& events() { return hub_; }
  // Called once the server listens: records the URL in daemon.json and the lock's holder line.
  void SetUrl(const std::string& url);
  // The machine port's lock follows the device the configured URI names now: a symlink that
  // moved to a replugged controller's new pty takes the lock along and frees the old name for
  // another machine. Cheap (one canonical() call); the event pump calls it every 200 ms.
  void FollowPortLock();
  // One line for sd_notify's STATUS= and the log: "run 3: 812/2011 probes, ETA 1h 02m".
  std::string StatusLine() const;

  // ---- reads ----
  nlohmann::json Info() const;
  nlohmann::json ListRuns() const;
  std::optional<nlohmann::json> GetRun(std::int64_t run_id) const;
  // Probes in plan order: index, sensor-frame point and normal, state, attempts, last_error.
  std::optional<nlohmann::json> ListProbes(std::int64_t run_id) const;
  // The run's log (events), oldest first, ids > after, at most `limit`.
  std::optional<nlohmann::json> RunLog(std::int64_t run_id, std::int64_t after, int limit) const;
  // PNG bytes: the latest frame of the run (any kind), or the press frame of plan index n.
  std::optional<std::vector<std::uint8_t>> LatestFramePng(std::int64_t run_id) const;
  std::optional<std::vector<std::uint8_t>> ProbeFramePng(std::int64_t run_id, int plan_index) const;
  std::optional<nlohmann::json> Calibration(std::int64_t run_id) const;
  // The file on disk, when the calibration has produced it.
  std::optional<std::filesystem::path> FileOf(std::int64_t run_id, RunFile file) const;
  nlohmann::json ListMeshes() const;
  // The configured notifiers (without secrets), their counts and last deliveries.
  nlohmann::json NotifyView() const;
  // Sends a test notification to every notifier (about `run` when not 0): {"sent_to": N};
  // nullopt when there is no such run.
  std::optional<nlohmann::json> NotifyTest(std::int64_t run);

  // ---- actions ----
  // Plans a run from a request ({"name", "shape" | "mesh", "probes", "plan", "plan_only"}; see
  // docs/api.md) on top of the daemon's defaults. Returns the run's view, or with plan_only the
  // plan's summary without storing anything (*created = false). Throws ConfigError naming the
  // field (unknown key, wrong type, invalid value, a plan that breaks a safety limit),
  // MeshError, std::runtime_error (nothing reachable).
  nlohmann::json CreateRun(const nlohmann::json& request, bool* created);
  // created -> running, and paused / interrupted -> running. `confirm`: what the user has
  // checked, answering the run's `awaiting` ("position", "sensor", or ""); a confirmation of
  // something else than what the run waits for is a conflict.
  ActionResult Start(std::int64_t run_id, const std::string& confirm = "");
  ActionResult Resume(std::int64_t run_id, const std::string& confirm = "");
  ActionResult Pause(std::int64_t run_id);   // running: after the current probe
  ActionResult Cancel(std::int64_t run_id);  // running (after the probe, then park) or idle
  ActionResult Delete(std::int64_t run_id);  // not running, not calibrating
  // Starts the calibration of a run that is not moving; `options` as docs/api.md.
  ActionResult Calibrate(std::int64_t run_id, const nlohmann::json& options);
  // Stores an uploaded mesh (bytes of an STL, OBJ or PLY file, `format` its extension) after
  // checking that it loads; returns its view ({"id", "triangles", ...}). Throws ConfigError when
  // the bytes are not a usable mesh (the loader's reason in the message).
  nlohmann::json UploadMesh(const std::string& bytes, const std::string& format);

 private:
  RunDatabase& Reader() const;
  void MarkDeadRunsInterrupted();
  void StartNotifications();
  ActionResult Launch(std::int64_t run_id, bool resume, const std::string& confirm);
  void WatchSession(std::int64_t run_id);
  void PumpEvents();
  // A run that converges (daemon/convergence.h): its checkpoints, and its end once converged.
  void ConvergenceTick();
  void OnProgress(const RunProgress& progress);
  nlohmann::json RunView(const RunRecord& run, const ProbeCounts& counts) const;
  std::filesystem::path RunDir(std::int64_t run_id) const;
  std::optional<std::filesystem::path> MeshPath(const std::string& id) const;
  // What never changes about a run (its sensor, candidates, estimate), read once: a status poll
  // must not parse the stored plan.
  nlohmann::json RunStatic(RunDatabase& db, std::int64_t run_id) const;

  DaemonConfig config_;
  InstanceLock data_lock_;
  InstanceLock port_lock_;
  std::mutex port_lock_mutex_;  // guards port_lock_ after construction
  std::string holder_;          // the locks' holder line
  std::filesystem::path port_lock_warned_;
  double started_at_ = 0.0;
  EventHub hub_;
  // Declared after the hub they read and before what they ask: destroyed first.
  std::unique_ptr<Notifier> notifier_;
  std::unique_ptr<NotifyFeed> notify_feed_;
  std::vector<std::int64_t> unclean_runs_;  // runs the previous daemon left running
  std::unique_ptr<CalibrationJobs> calibration_;
  std::unique_ptr<ConvergenceWatch> convergence_;

  mutable std::mutex mutex_;  // guards the fields below
  std::unique_ptr<RunEngine> engine_;
  std::int64_t active_run_ = 0;  // 0: no run moving
  std::thread watcher_;
  RunProgress progress_;  // of the active run
  double last_progress_event_ = 0.0;
  std::string url_;
  mutable std::map<std::int64_t, nlohmann::json> run_static_;

  std::atomic<bool> stopping_{false};
  std::mutex pump_mutex_;
  std::condition_variable pump_wake_;
  std::thread pump_;
};

}  // namespace gs360
