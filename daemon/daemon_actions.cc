// Daemon: the actions (create, start, pause, resume, cancel, delete, calibrate, upload) and the
// threads behind them (the run's watcher, the event pump).

#include <unistd.h>

#include <fstream>

#include <spdlog/spdlog.h>

#include "base/hash.h"
#include "base/json_reader.h"
#include "daemon/calibration_jobs.h"
#include "daemon/convergence.h"
#include "daemon/daemon.h"
#include "daemon/daemon_util.h"
#include "geometry/mesh.h"
#include "run/calibration_inputs.h"

namespace gs360 {
namespace {

using Json = nlohmann::json;
using daemon_util::IsMeshFormat;
using daemon_util::UnixNow;

ActionResult Conflict(std::string message, RunState state) {
  return {ActionStatus::kConflict, std::move(message), std::string(ToString(state))};
}

ActionResult NotFound(std::int64_t run_id) {
  return {ActionStatus::kNotFound, "no run " + std::to_string(run_id), ""};
}

// The run-creation request's keys, read on top of the daemon's defaults.
void ReadRunRequest(JsonReader& r, RunConfig& config, std::string* mesh_id, bool* plan_only) {
  r.Get("name", config.name);
  if (const std::string problem = CheckRunName(config.name); !problem.empty()) {
    r.Fail("name", problem);
  }
  r.Object("shape", [&](JsonReader& o) { ReadSensorShape(o, config.rig.shape); });
  r.Get("mesh", *mesh_id);
  ReadProbeCount(r, "probes", config.plan);
  r.Object("plan", [&](JsonReader& o) { ReadPlanOptions(o, config.plan); });
  r.Get("until_converged", config.converge.enabled);
  r.Object("converge", [&](JsonReader& o) { ReadConvergeConfig(o, config.converge); });
  r.Get("plan_only", *plan_only);
  r.RejectUnknown();
  // A run that converges is probed in rounds, each covering the surface.
  if (config.converge.enabled && config.plan.checkpoint_probes == 0) {
    config.plan.checkpoint_probes = kDefaultConvergeRound;
  }
}

// A run request the configuration's Check() or the planner refused: a 400 naming the field by
// its path in the request ("shape.cylinder.radius", "probes"), not in the configuration
// ("rig.shape.cylinder.radius") nor by a C++ type ("CylinderCapOptions.radius"). A problem of
// the daemon's own settings that the request's shape or mesh brings out (fins too large for a
// small shape) names "shape" or "mesh" and then the setting.
ConfigError RequestError(const std::string& what, const Json& request) {
  std::string message = WithRunConfigPath(what);
  const std::string field = RunConfigField(message);
  const Json* plan = request.contains("plan") ? &request["plan"] : nullptr;
  std::string to;
  if (field == "plan.probe_count" && request.contains("probes") &&
      !(plan != nullptr && plan->is_object() && plan->contains("probe_count"))) {
    to = "probes";
  } else if (field.rfind("rig.shape.", 0) == 0) {
    to = field.substr(4);
  } else if (field.rfind("plan.", 0) == 0 || field.rfind("converge.", 0) == 0) {
    to = field;
  }
  if (!to.empty()) return ConfigError("request: " + to + message.substr(field.size()), to);
  to = request.contains("mesh") ? "mesh" : request.contains("shape") ? "shape" : field;
  return ConfigError("request: " + (to.empty() || to == field ? "" : to + ": ") + message, to);
}

Json PlanSummary(const ProbePlan& plan) {
  Json dropped = Json::object();
  for (int i = 0; i < kNumDropReasons; ++i) {
    const auto reason = static_cast<DropReason>(i);
    dropped[std::string(DropReasonName(reason))] = plan.dropped[reason];
  }
  return {{"probes_total", plan.probes.size()},
          {"candidates", plan.candidates},
          {"dropped", dropped},
          {"advice", PlanAdvice(plan)},
          {"coverage_gaps", CoverageGapsJson(plan.coverage_gaps)},
          {"estimate_s", plan.estimate.Total()},
          {"tour_gain", plan.TourGain()},
          {"checkpoint_probes", plan.checkpoint_probes}};
}

Json PlanSummary(const ProbePlan& plan, const RunConfig& config) {
  Json summary = PlanSummary(plan);
  summary["until_converged"] = config.converge.enabled;
  return summary;
}

}  // namespace

Json Daemon::CreateRun(const Json& request, bool* created) {
  RunConfig config = config_.run;
  config.name.clear();
  std::string mesh_id;
  bool plan_only = false;
  {
    JsonReader reader(request, "request");
    ReadRunRequest(reader, config, &mesh_id, &plan_only);
  }
  if (!mesh_id.empty()) {
    const auto path = MeshPath(mesh_id);
    if (!path) throw ConfigError("request: mesh: no uploaded mesh \"" + mesh_id + "\"", "mesh");
    config.rig.mesh_path = path->string();
  }
  if (config.name.empty()) config.name = "run";
  // A daemon without a machine can still plan; the URIs are checked when the run starts.
  RunConfig checked = config;
  if (checked.machine.uri.empty()) checked.machine.uri = "unset";
  if (checked.camera.uri.empty()) checked.camera.uri = "unset";
  RunEngine::PlannedRun planned;
  try {
    planned = RunEngine::PlanRun(checked, &config_.limits);  // checks `checked` first
  } catch (const ConfigError&) {
    throw;
  } catch (const MeshError&) {
    throw;
  } catch (const std::invalid_argument& e) {
    throw RequestError(e.what(), request);
  } catch (const std::runtime_error& e) {
    // What the planner found impossible for these values (no area, beyond the travel): the
    // request's, not the daemon's failure.
    throw RequestError(e.what(), request);
  }
  const ProbePlan& plan = planned.plan;
  *created = !plan_only;
  if (plan_only) return PlanSummary(plan, config);
  std::int64_t run_id = 0;
  {
    std::lock_guard lock(mutex_);
    run_id = engine_->StoreRun(config, planned);
  }
  spdlog::info("created run {} ({}, {} probes)", run_id, config.name, plan.probes.size());
  hub_.Publish("state", {{"run", run_id}, {"state", "created"}});
  Json view = *GetRun(run_id);
  view["plan"] = PlanSummary(plan, config);
  return view;
}

ActionResult Daemon::Start(std::int64_t run_id, const std::string& confirm) {
  return Launch(run_id, false, confirm);
}

ActionResult Daemon::Resume(std::int64_t run_id, const std::string& confirm) {
  return Launch(run_id, true, confirm);
}

ActionResult Daemon::Launch(std::int64_t run_id, bool resume, const std::string& confirm) {
  if (!confirm.empty() && confirm != "position" && confirm != "sensor") {
    throw ConfigError(
        "request: confirm: expected \"position\" or \"sensor\", got \"" + confirm + "\"",
        "confirm");
  }
  std::lock_guard lock(mutex_);
  if (stopping_) return {ActionStatus::kConflict, "the daemon is shutting down", ""};
  RunDatabase db(config_.DatabasePath());
  const auto run = db.GetRun(run_id);
  if (!run) return NotFound(run_id);
  if (active_run_ == run_id) return Conflict("run is already running", run->state);
  if (active_run_ != 0) {
    return Conflict("run " + std::to_string(active_run_) + " is using the machine", run->state);
  }
  // A created run that asked at its start (awaiting) is resumed like any other.
  const bool startable =
      resume ? (run->state == RunState::kPaused || run->state == RunState::kInterrupted ||
                (run->state == RunState::kCreated && !run->awaiting.empty()))
             : run->state == RunState::kCreated;
  if (!startable) {
    return Conflict(std::string(resume ? "only a paused or interrupted run can be resumed"
                                       : "only a created run can be started (resume a paused or "
                                         "interrupted one)"),
                    run->state);
  }
  // A checkpoint calibration (daemon/convergence.h) reads only the probes already captured.
  if (calibration_->Running() == run_id && !convergence_->Calibrating(run_id)) {
    return Conflict("run is being calibrated", run->state);
  }
  // A confirmation answers the question the run asked, and only that one: unasked, it would
  // skip a check nobody saw (a jogged tool taken as where it was sent, a ball in the gel homed).
  if (!confirm.empty() && run->awaiting.empty()) {
    return Conflict("no confirmation was asked for: run " + std::to_string(run_id) +
                        " is not waiting for its " + confirm + " to be confirmed. " +
                        (resume ? "Resume" : "Start") + " it without --confirm (`gs360 run " +
                        (resume ? "resume " : "start ") + std::to_string(run_id) +
                        "`): it checks the machine and asks if it needs you to",
                    run->state);
  }
  if (!confirm.empty() && confirm != run->awaiting) {
    return Conflict("the run waits for its " + run->awaiting + " to be confirmed, not its " +
                        confirm + ": " + run->last_error,
                    run->state);
  }
  if (config_.run.machine.uri.empty() || config_.run.camera.uri.empty()) {
    return Conflict("gs360d.toml names no machine.uri or camera.uri: nothing to run on",
                    run->state);
  }
  // The machine and camera are the daemon's, whatever the run was created with.
  SessionOverrides overrides;
  overrides.machine_uri = config_.run.machine.uri;
  overrides.camera_uri = config_.run.camera.uri;
  overrides.confirm = confirm;
  if (watcher_.joinable()) watcher_.join();
  engine_->Start(run_id, overrides);
  active_run_ = run_id;
  progress_ = RunProgress{};
  progress_.run_id = run_id;
  progress_.phase = "connecting";
  watcher_ = std::thread([this, run_id] { WatchSession(run_id); });
  spdlog::info("run {}: {}{}", run_id, resume ? "resuming" : "starting",
               confirm.empty() ? "" : " (the user confirms the " + confirm + ")");
  return {ActionStatus::kAccepted, resume ? "resuming" : "starting", "starting"};
}

void Daemon::WatchSession(std::int64_t run_id) {
  std::string error;
  RunReport report;
  try {
    report = engine_->Wait();
  } catch (const std::exception& e) {
    error = e.what();
  }
  try {
    RunDatabase db(config_.DatabasePath());
    if (!error.empty()) db.SetRunError(run_id, error);
    const auto run = db.GetRun(run_id);
    const std::string state = run ? std::string(ToString(run->state)) : "unknown";
    hub_.Publish("run_end", {{"run", run_id},
                             {"state", state},
                             {"outcome", error.empty() ? std::string(ToString(report.outcome))
                                                       : std::string("failed")},
                             {"message", error.empty() ? report.message : error}});
    spdlog::info("run {} is {}{}", run_id, state, error.empty() ? "" : ": " + error);
  } catch (const std::exception& e) {
    spdlog::error("run {}: after the session: {}", run_id, e.what());
  }
  std::lock_guard lock(mutex_);
  active_run_ = 0;
  progress_.machine_connected = false;
}

ActionResult Daemon::Pause(std::int64_t run_id) {
  std::lock_guard lock(mutex_);
  const auto run = Reader().GetRun(run_id);
  if (!run) return NotFound(run_id);
  if (active_run_ != run_id) return Conflict("only a running run can be paused", run->state);
  engine_->RequestPause();
  return {ActionStatus::kAccepted, "pausing after the current probe", "running"};
}

ActionResult Daemon::Cancel(std::int64_t run_id) {
  std::lock_guard lock(mutex_);
  RunDatabase db(config_.DatabasePath());
  const auto run = db.GetRun(run_id);
  if (!run) return NotFound(run_id);
  if (active_run_ == run_id) {
    engine_->RequestCancel();
    return {ActionStatus::kAccepted, "cancelling after the current probe, then parking", "running"};
  }
  if (IsTerminal(run->state)) return Conflict("run has already ended", run->state);
  db.SetRunState(run_id, RunState::kCancelled);
  hub_.Publish("state", {{"run", run_id}, {"state", "cancelled"}});
  return {ActionStatus::kAccepted, "cancelled; the captured probes are kept", "cancelled"};
}

ActionResult Daemon::Delete(std::int64_t run_id) {
  std::lock_guard lock(mutex_);
  RunDatabase db(config_.DatabasePath());
  const auto run = db.GetRun(run_id);
  if (!run) return NotFound(run_id);
  if (active_run_ == run_id || run->state == RunState::kRunning) {
    return Conflict("run is running; pause or cancel it first", run->state);
  }
  if (calibration_->Running() == run_id) return Conflict("run is being calibrated", run->state);
  db.DeleteRun(run_id);
  run_static_.erase(run_id);
  calibration_->Forget(run_id);
  std::error_code ec;
  std::filesystem::remove_all(RunDir(run_id), ec);
  spdlog::info("deleted run {}", run_id);
  hub_.Publish("state", {{"run", run_id}, {"state", "deleted"}});
  return {ActionStatus::kAccepted, "deleted", "deleted"};
}

ActionResult Daemon::Calibrate(std::int64_t run_id, const Json& request) {
  CalibrationOptions options;
  {
    JsonReader reader(request, "request");
    ReadCalibrationRequest(reader, options);
    reader.RejectUnknown();
  }
  std::lock_guard lock(mutex_);
  RunDatabase db(config_.DatabasePath());
  const auto run = db.GetRun(run_id);
  if (!run) return NotFound(run_id);
  if (active_run_ == run_id) return Conflict("run is still probing", run->state);
  if (db.CountProbes(run_id).captured == 0) {
    return Conflict("run has no captured probes to calibrate from", run->state);
  }
  const CalibrationInputs inputs =
      CalibrationInputsFor(db, run_id, config_.calibration.checkerboards);
  std::int64_t busy = 0;
  if (!calibration_->Start(run_id, inputs, options, &busy)) {
    return Conflict("run " + std::to_string(busy) + " is being calibrated", run->state);
  }
  spdlog::info("run {}: calibrating", run_id);
  return {ActionStatus::kAccepted, "calibrating", std::string(ToString(run->state))};
}

Json Daemon::UploadMesh(const std::string& bytes, const std::string& format) {
  if (!IsMeshFormat(format)) {
    throw ConfigError("format: expected stl, obj or ply, got \"" + format + "\"", "format");
  }
  const std::string id = HashHex(bytes.data(), bytes.size());
  const std::filesystem::path dir = config_.data_dir / "meshes";
  const std::filesystem::path tmp = dir / ("upload-" + std::to_string(::getpid()) + "-" +
                                           std::to_string(hub_.LastId()) + "-" + id + "." + format);
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
    if (!out.flush()) throw std::runtime_error("cannot write " + tmp.string());
  }
  TriangleMesh mesh;
  MeshReport report;
  try {
    mesh = LoadMesh(tmp, MeshLoadOptions{}, &report);
  } catch (const std::exception& e) {
    std::filesystem::remove(tmp);
    // The loader names our temporary file (assimp's messages may name it twice); the client
    // knows its upload by its bytes.
    std::string why = e.what();
    const std::string name = "the uploaded mesh";
    for (std::size_t at = 0; (at = why.find(tmp.string(), at)) != std::string::npos;) {
      why.replace(at, tmp.string().size(), name);
      at += name.size();
    }
    throw MeshError("mesh: " + why);
  }
  std::filesystem::rename(tmp, dir / (id + "." + format));
  const auto bounds = mesh.Bounds();
  return {{"id", id},
          {"format", format},
          {"triangles", mesh.NumTriangles()},
          {"bounds_min", {bounds.min().x(), bounds.min().y(), bounds.min().z()}},
          {"bounds_max", {bounds.max().x(), bounds.max().y(), bounds.max().z()}}};
}

// ---- live progress and the event pump ---------------------------------------------------------

void Daemon::OnProgress(const RunProgress& p) {
  const double now = UnixNow();
  bool publish = false;
  {
    std::lock_guard lock(mutex_);
    const bool phase_changed = p.phase != progress_.phase;
    progress_ = p;
    // At most four progress events a second, but every phase change.
    if (phase_changed || now - last_progress_event_ >= 0.25) {
      last_progress_event_ = now;
      publish = true;
    }
  }
  if (!publish) return;
  Json data{{"run", p.run_id},
            {"probes_done", p.counts.captured},
            {"probes_total", p.counts.total - p.counts.skipped},
            {"probes_failed", p.counts.failed},
            {"probes_skipped", p.counts.skipped},
            {"elapsed_s", p.elapsed_s},
            {"eta_s", p.eta_s >= 0 ? Json(p.eta_s) : Json(nullptr)},
            {"rate_per_h", p.probes_per_hour > 0 ? Json(p.probes_per_hour) : Json(nullptr)},
            {"phase", p.phase},
            {"plan_index", p.plan_index},
            {"machine_state", p.machine_state.empty() ? Json(nullptr) : Json(p.machine_state)}};
  if (p.machine_position) {
    data["machine_position"] = {p.machine_position->x(), p.machine_position->y(),
                                p.machine_position->z()};
  }
  hub_.Publish("progress", std::move(data));
}

void Daemon::ConvergenceTick() {
  std::int64_t active = 0;
  RunProgress progress;
  {
    std::lock_guard lock(mutex_);
    active = active_run_;
    progress = progress_;
  }
  const auto action = convergence_->Tick(active, progress);
  if (action.finish_run == 0) return;
  std::lock_guard lock(mutex_);
  if (active_run_ == action.finish_run) {
    spdlog::info("run {}: {}; ending the run", action.finish_run, action.reason);
    engine_->RequestFinish("converged");
  }
}

void Daemon::PumpEvents() {
  // The run log in the database is the record; the hub forwards its new entries live. Start at
  // the current end: older entries are history (GET /runs/ID/log).
  std::int64_t after = 0;
  try {
    RunDatabase db(config_.DatabasePath(), RunDatabaseOptions{.read_only = true});
    for (;;) {
      const auto batch = db.ListEvents(std::nullopt, after, 1000);
      if (batch.empty()) break;
      after = batch.back().id;
    }
  } catch (const std::exception& e) {
    spdlog::error("event pump: {}", e.what());
  }
  while (!stopping_) {
    try {
      RunDatabase& db = Reader();
      for (const EventRecord& e : db.ListEvents(std::nullopt, after, 200)) {
        after = e.id;
        Json data{{"run", e.run_id ? Json(*e.run_id) : Json(nullptr)},
                  {"time", e.timestamp},
                  {"level", std::string(ToString(e.level))},
                  {"message", e.message}};
        std::string type = "log";
        if (e.level == EventLevel::kWarning) type = "warning";
        // Not "error": EventSource gives that name to a lost connection.
        if (e.level == EventLevel::kError) type = "failure";
        if (e.message.find("ALARM") != std::string::npos) type = "alarm";
        // A state change carries {"from", "state"} (RunDatabase::SetRunState).
        const Json extra = e.data_json.empty() ? Json() : Json::parse(e.data_json, nullptr, false);
        if (extra.is_object() && extra.contains("state")) {
          type = "state";
          data["state"] = extra["state"];
          if (extra.contains("from")) data["from"] = extra["from"];
        }
        hub_.Publish(type, std::move(data));
      }
    } catch (const std::exception& e) {
      spdlog::warn("event pump: {}", e.what());
    }
    FollowPortLock();
    try {
      ConvergenceTick();
    } catch (const std::exception& e) {
      spdlog::warn("convergence: {}", e.what());
    }
    std::unique_lock lock(pump_mutex_);
    pump_wake_.wait_for(lock, std::chrono::milliseconds(200), [&] { return stopping_.load(); });
  }
}

}  // namespace gs360
