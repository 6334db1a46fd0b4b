#pragma once
// The overnight run: plan, stream, capture at each press, store, resume.
//
// CreateRun() plans the probes and stores the run (config, plan, probe rows); it never moves
// the machine. Execute() connects to the controller and the camera, homes (if configured), and
// probes every pending probe in plan order, one database transaction per committed probe:
//
//   travel -> approach -> press (G1) -> G4 P<settle>  ... wait for the G4 `ok` (the sync point)
//   -> K frames exposed after that ok, averaged -> status MPos -> COMMIT -> retract (G0)
//
// Motion between presses is streamed ahead (character counting); only the retract waits for
// the frame. A no-contact reference frame is taken at the start of every session and every
// `plan.reference_every` probes.
//
// What stops a run, and what it leaves:
// - the probe's own failure (error:N on one of its lines, no frame in time): the probe is
//   marked failed (retried until engine.max_attempts), the run goes on;
// - a controller reset or a vanished port: reconnect, re-establish the position (below),
//   continue (at most engine.max_recoveries times per session);
// - an alarm (limit, abort): the machine is left alone, the run becomes `interrupted` with the
//   alarm's text; Execute() returns kFailed;
// - RequestStop() (SIGTERM), RequestPause(), RequestCancel(), RequestFinish(): the current probe
//   is finished, retracted and committed first; the run becomes interrupted / paused / cancelled
//   / done (a cancelled or finished run also parks the tool at the plan's start position; a
//   finished one skips what is left of its plan);
// - a line that breaks the safety limits (SetSafetyLimits, run/safety.h): it is not sent, the
//   run stops (interrupted, kFailed) naming the line and the limit.
// Nothing committed is ever lost or probed again. On resume, Execute() first re-presses up to
// engine.recheck_probes committed probes and measures how far their impressions lie from the
// stored frames' (MeasureImpressionShift, capture/impression.h); if more than
// engine.recheck_max_shift_px, the sensor has moved and it refuses to continue (kFailed, with the
// measured shift); if no impression could be compared it stops and asks (kAwaiting "sensor")
// unless engine.unverified_resume is "continue".
//
// Position (docs/running.md, "Faults"): at the start of every session and after every reset or
// reconnect, the tool's position is known only through homing or a check. A controller that
// lost its position (in alarm) is homed when machine.home is set and the tool was last sent
// nowhere near the gel, otherwise the run stops and asks (kAwaiting "position"). A controller
// that kept it must report the position the tool was last sent to (stored with the run);
// otherwise the run stops and asks, never moves. Without homing, a first start asks too. Once
// the position is known, a tool in or near the gel backs out along the probe's own axis before
// anything else moves. $X is sent only with the user's confirmation, and said in the run's log.
// A press frame without an impression is a probe failure (retried).
//
// Threads: Execute() blocks its caller; Start() runs it on the engine's own thread. The Request*()
// calls and Progress() may come from any thread (RequestStop() is async-signal-safe). One run at a
// time per engine.

#include <atomic>
#include <cstdint>
#include <exception>
#include <filesystem>
#include <functional>
#include <mutex>
#include <optional>
#include <string>
#include <thread>

#include "plan/plan.h"
#include "run/run_config.h"
#include "run/safety.h"
#include "storage/run_database.h"

namespace gs360 {

// kAwaiting: the run stopped without moving because it cannot go on safely until the user has
// checked something (RunRecord::awaiting says what, last_error why); resume with
// SessionOverrides::confirm set to that.
enum class RunOutcome { kDone, kPaused, kStopped, kCancelled, kFailed, kAwaiting };
std::string_view ToString(RunOutcome outcome);

struct RunProgress {
  std::int64_t run_id = 0;
  ProbeCounts counts;
  double elapsed_s = 0.0;        // time spent running, all sessions
  double eta_s = -1.0;           // remaining time; -1 unknown
  double probes_per_hour = 0.0;  // recent rate of this session
  int plan_index = -1;           // probe in progress
  std::string phase;             // connecting, homing, rechecking, probing, parking, idle
  // The controller as last seen (status reports): connected, GRBL state ("Idle", "Run", "Alarm",
  // ...; empty when unknown) and machine position (MPos, mm).
  bool machine_connected = false;
  std::string machine_state;
  std::optional<Eigen::Vector3d> machine_position;
};

struct RunReport {
  RunOutcome outcome = RunOutcome::kFailed;
  std::string message;
  std::int64_t captured = 0;  // committed in this session
  std::int64_t failed = 0;    // failed attempts in this session
  int recoveries = 0;         // resets / reconnects handled
  double seconds = 0.0;       // wall time of this session
  ProbeCounts counts;         // of the whole run, at the end
};

// Connection settings that may change between sessions of one run (the controller came back as
// /dev/ttyUSB1, the camera server moved). Empty = as stored in the run's config.
struct SessionOverrides {
  std::string machine_uri;
  std::string camera_uri;
  // What the user has checked, answering the run's RunRecord::awaiting: "position" (the
  // controller's reported position is true, or with homing: the tool is clear, home it) or
  // "sensor" (go on although the resume check could not verify the sensor's position).
  std::string confirm;
};

class RunEngine {
 public:
  using ProgressCallback = std::function<void(const RunProgress&)>;

  // The database is opened (and created) per call with `options`; `database` must be writable.
  explicit RunEngine(std::filesystem::path database, RunDatabaseOptions options = {});
  // Stops a started run (RequestStop) and joins its thread.
  ~RunEngine();
  RunEngine(const RunEngine&) = delete;
  RunEngine& operator=(const RunEngine&) = delete;

  // A run's plan and what storing it needs of the rig, so that the rig's geometry (a mesh file
  // loaded, or a shape meshed) is built once per run created.
  struct PlannedRun {
    ProbePlan plan;
    std::string sensor_mesh_hash;  // hex Hash() of the rig's sensor mesh
  };
  // Validates the config and plans; with `limits`, every line of the plan is checked against them
  // (SafetyGuard::CheckPlan). No motion, nothing stored. Throws ConfigError (a limit broken,
  // naming the probe and the limit; or nothing reachable, with PlanAdvice's sentences) /
  // std::invalid_argument / MeshError.
  static PlannedRun PlanRun(const RunConfig& config, const SafetyLimits* limits = nullptr);
  // Stores run + plan (probe rows and the full plan as the "plan" artifact) for `config`, which
  // `planned` was planned from. Throws StorageError.
  std::int64_t StoreRun(const RunConfig& config, const PlannedRun& planned);
  // PlanRun (with the limits set by SetSafetyLimits, if any) then StoreRun. `plan_out` receives
  // the plan if given.
  std::int64_t CreateRun(const RunConfig& config, ProbePlan* plan_out = nullptr);

  // Limits every line sent from now on is checked against (default: none). Call before Start().
  void SetSafetyLimits(const SafetyLimits& limits);

  // Runs or resumes `run_id` until it ends, is paused / stopped / cancelled, or fails. Throws
  // only for set-up errors before anything moved (unknown run, terminal run, unreadable config,
  // camera or port that cannot be opened); the run is then left as it was, or `interrupted`.
  RunReport Execute(std::int64_t run_id, const SessionOverrides& overrides = {});

  // Execute() on the engine's own thread. Throws std::logic_error if one is already running.
  // Wait() joins it and returns its report, rethrowing what Execute() threw.
  void Start(std::int64_t run_id, const SessionOverrides& overrides = {});
  bool Running() const;
  RunReport Wait();

  void RequestStop();    // finish the current probe, retract, commit, return (resumable)
  void RequestPause();   // the same, state paused
  void RequestCancel();  // the same, state cancelled (terminal)
  // The same, then every probe not captured is skipped with `reason` (the run has converged),
  // the tool parked, and the run is done.
  void RequestFinish(const std::string& reason);

  void SetProgressCallback(ProgressCallback callback);
  RunProgress Progress() const;

  const std::filesystem::path& database() const { return database_; }

  // The stored plan of a run (the "plan" artifact).
  static ProbePlan LoadPlan(const RunDatabase& db, std::int64_t run_id);

 private:
  friend class RunSession;
  void Publish(const RunProgress& progress);

  std::filesystem::path database_;
  RunDatabaseOptions database_options_;
  std::optional<SafetyLimits> limits_;
  std::thread thread_;
  std::atomic<bool> running_{false};
  RunReport thread_report_;
  std::exception_ptr thread_error_;
  std::atomic<int> request_{0};  // 0 none, 1 stop, 2 pause, 3 cancel, 4 finish
  std::string FinishReason() const;
  mutable std::mutex progress_mutex_;  // also guards finish_reason_
  std::string finish_reason_;
  RunProgress progress_;
  ProgressCallback callback_;
};

}  // namespace gs360
