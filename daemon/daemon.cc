#include "daemon/daemon.h"

#include <unistd.h>

#include <chrono>
#include <cmath>
#include <fstream>
#include <sstream>
#include <thread>

#include <spdlog/spdlog.h>

#include "base/atomic_file.h"
#include "base/hash.h"
#include "base/json_reader.h"
#include "base/version.h"
#include "daemon/calibration_jobs.h"
#include "daemon/convergence.h"
#include "daemon/daemon_util.h"
#include "geometry/mesh.h"
#include "run/calibration_inputs.h"

namespace gs360 {
namespace {

using Json = nlohmann::json;
using daemon_util::IsMeshFormat;
using daemon_util::UnixNow;
using daemon_util::Vec;

Json Optional(const std::optional<double>& v) {
  return v ? Json(*v) : Json(nullptr);
}

std::string Duration(double s) {
  const long total = std::lround(std::max(0.0, s));
  std::ostringstream os;
  if (total >= 3600) {
    os << total / 3600 << "h " << (total % 3600) / 60 << "m";
  } else if (total >= 60) {
    os << total / 60 << "m " << total % 60 << "s";
  } else {
    os << total << "s";
  }
  return os.str();
}

// A machine URI naming a device file that is not there (unplugged; a pty whose other end
// closed). Such a device's lock is let go at once: the kernel reuses tty names, and a new device
// under the old name belongs to whoever opens it next.
bool DeviceVanished(const std::string& uri) {
  std::error_code ec;
  return !uri.empty() && uri[0] == '/' && !std::filesystem::exists(uri, ec);
}

// The port lock, waiting up to a second for a daemon whose device vanished to let go of it (its
// event pump notices within 200 ms).
InstanceLock AcquirePortLock(const std::string& uri, const std::string& holder) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(1);
  for (;;) {
    try {
      return InstanceLock::Acquire(MachineLockPath(uri), "the machine port " + uri, holder);
    } catch (const LockHeldError&) {
      if (std::chrono::steady_clock::now() > deadline) throw;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
  }
}

}  // namespace

Daemon::Daemon(DaemonConfig config) : config_(std::move(config)) {
  config_.Check();
  std::filesystem::create_directories(config_.data_dir);
  config_.data_dir = std::filesystem::canonical(config_.data_dir);
  const std::string holder = "gs360d pid " + std::to_string(::getpid()) + " (data folder " +
                             config_.data_dir.string() + ")";
  data_lock_ = InstanceLock::Acquire(config_.data_dir / "gs360d.lock",
                                     "the data folder " + config_.data_dir.string(), holder);
  holder_ = holder;
  if (!config_.run.machine.uri.empty() && !DeviceVanished(config_.run.machine.uri)) {
    port_lock_ = AcquirePortLock(config_.run.machine.uri, holder);
  }
  started_at_ = UnixNow();
  std::filesystem::create_directories(config_.data_dir / "runs");
  std::filesystem::create_directories(config_.data_dir / "meshes");
  try {
    RunDatabase create(config_.DatabasePath());  // creates or migrates the file
  } catch (const StorageError& e) {
    if (e.code() != StorageErrc::kReadOnly) throw;
    throw std::runtime_error(std::string(e.what()) +
                             ". gs360d records every probe in it: make the file and its folder "
                             "writable for the user gs360d runs as, then start gs360d again "
                             "(nothing in it was changed)");
  }
  MarkDeadRunsInterrupted();
  engine_ = std::make_unique<RunEngine>(config_.DatabasePath());
  engine_->SetSafetyLimits(config_.limits);
  engine_->SetProgressCallback([this](const RunProgress& p) { OnProgress(p); });
  calibration_ = std::make_unique<CalibrationJobs>(
      config_.data_dir / "runs", config_.DatabasePath(), config_.calibration.threads, hub_);
  convergence_ = std::make_unique<ConvergenceWatch>(
      config_.DatabasePath(), config_.calibration.checkerboards, *calibration_, hub_);
  StartNotifications();
  pump_ = std::thread([this] { PumpEvents(); });
}

Daemon::~Daemon() {
  Shutdown();
}

void Daemon::MarkDeadRunsInterrupted() {
  RunDatabase db(config_.DatabasePath());
  for (const RunRecord& run : db.ListRuns()) {
    if (run.state != RunState::kRunning) continue;
    // This daemon holds the data folder: whoever was running it is gone.
    db.SetRunState(run.id, RunState::kInterrupted);
    db.AppendEvent(run.id, EventLevel::kWarning,
                   "the daemon stopped while this run was running; the machine was not moved "
                   "since. Resume it when the rig is ready.");
    spdlog::warn("run {} was running when the daemon stopped: now interrupted", run.id);
    unclean_runs_.push_back(run.id);
  }
}

void Daemon::Shutdown() {
  if (stopping_.exchange(true)) return;
  {
    std::lock_guard lock(mutex_);
    if (active_run_ != 0) engine_->RequestStop();
  }
  if (watcher_.joinable()) watcher_.join();
  // The pump first: its convergence tick may start a calibration.
  pump_wake_.notify_all();
  if (pump_.joinable()) pump_.join();
  calibration_->Stop();
  // The last run's end reaches the notifiers before the hub closes, and goes out if it can.
  if (notify_feed_) notify_feed_->Drain(std::chrono::seconds(2));
  hub_.Close();
  notify_feed_.reset();
  if (notifier_) notifier_->WaitIdle(std::chrono::seconds(5));
}

void Daemon::StartNotifications() {
  notifier_ = std::make_unique<Notifier>(config_.notify);
  if (notifier_->size() > 0) {
    spdlog::info("notifications: {} notifier{}", notifier_->size(),
                 notifier_->size() == 1 ? "" : "s");
  }
  NotifyFeed::Sources sources;
  sources.run = [this](std::int64_t id) { return GetRun(id); };
  sources.calibration = [this](std::int64_t id) { return calibration_->View(id); };
  sources.dashboard_url = [this] {
    std::lock_guard lock(mutex_);
    return url_.empty() ? std::string() : url_ + "/";
  };
  sources.latest_frame = [this](std::int64_t id) { return LatestFramePng(id); };
  notify_feed_ = std::make_unique<NotifyFeed>(hub_, *notifier_, std::move(sources), unclean_runs_);
}

Json Daemon::NotifyView() const {
  return notifier_->View();
}

std::optional<Json> Daemon::NotifyTest(std::int64_t run) {
  if (run != 0 && !Reader().GetRun(run)) return std::nullopt;
  notify_feed_->Send(NotifyEvent::kTest, run, "a test notification from gs360d");
  return Json{{"sent_to", notifier_->size()}};
}

void Daemon::FollowPortLock() {
  if (config_.run.machine.uri.empty()) return;
  const std::string& uri = config_.run.machine.uri;
  std::lock_guard lock(port_lock_mutex_);
  if (DeviceVanished(uri)) {
    if (port_lock_.Held()) {
      spdlog::info("gs360d: {} is gone: its lock {} is released until it is back", uri,
                   port_lock_.path().string());
      port_lock_.Release();
    }
    return;
  }
  const std::filesystem::path now = MachineLockPath(uri);
  if (port_lock_.Held() && now == port_lock_.path()) return;
  try {
    InstanceLock moved = InstanceLock::Acquire(now, "the machine port " + uri, holder_);
    if (port_lock_.path() != now) {
      spdlog::info("gs360d: {} now names another device: its lock moved from {} to {}", uri,
                   port_lock_.path().string(), now.string());
    }
    port_lock_ = std::move(moved);
  } catch (const std::exception& e) {
    // Held by another daemon: keep ours; say so once per new name.
    if (now != port_lock_warned_) spdlog::warn("gs360d: {}", e.what());
    port_lock_warned_ = now;
  }
}

void Daemon::SetUrl(const std::string& url) {
  {
    std::lock_guard lock(mutex_);
    url_ = url;
  }
  data_lock_.SetHolder("gs360d pid " + std::to_string(::getpid()) + " at " + url +
                       " (data folder " + config_.data_dir.string() + ")");
  std::lock_guard port_lock(port_lock_mutex_);
  holder_ = "gs360d pid " + std::to_string(::getpid()) + " at " + url;
  if (port_lock_.Held()) port_lock_.SetHolder(holder_);
  WriteFileAtomically(
      config_.data_dir / "daemon.json",
      Json{{"pid", ::getpid()}, {"url", url}, {"started_at", started_at_}}.dump() + "\n");
}

RunDatabase& Daemon::Reader() const {
  // One read-only connection per thread and daemon (SQLite connections are per thread; WAL
  // readers never block the run's writer).
  thread_local std::map<const Daemon*, std::unique_ptr<RunDatabase>> readers;
  auto& db = readers[this];
  if (!db) {
    RunDatabaseOptions options;
    options.read_only = true;
    db = std::make_unique<RunDatabase>(config_.DatabasePath(), options);
  }
  return *db;
}

std::string Daemon::StatusLine() const {
  std::lock_guard lock(mutex_);
  std::string line;
  if (active_run_ != 0) {
    const ProbeCounts& c = progress_.counts;
    line = "run " + std::to_string(active_run_) + ": " + std::to_string(c.captured) + "/" +
           std::to_string(c.total - c.skipped) + " probes";
    if (progress_.eta_s >= 0) line += ", ETA " + Duration(progress_.eta_s);
    if (!progress_.phase.empty() && progress_.phase != "probing")
      line += " (" + progress_.phase + ")";
  }
  if (const std::int64_t cal = calibration_->Running(); cal != 0) {
    line += (line.empty() ? "" : "; ") + std::string("calibrating run ") + std::to_string(cal);
  }
  return line.empty() ? "idle" : line;
}

// ---- reads ----------------------------------------------------------------------------------

Json Daemon::RunView(const RunRecord& run, const ProbeCounts& counts) const {
  const std::int64_t to_press = counts.total - counts.skipped;
  Json view{{"id", run.id},
            {"name", run.name},
            {"state", std::string(ToString(run.state))},
            {"probes_total", to_press},
            {"probes_done", counts.captured},
            {"probes_failed", counts.failed},
            {"probes_skipped", counts.skipped},
            {"probes_pending", counts.planned + counts.failed},
            {"elapsed_s", run.active_s},
            {"eta_s", nullptr},
            {"rate_per_h", nullptr},
            {"phase", nullptr},
            {"machine_state", nullptr},
            {"machine_position", nullptr},
            {"last_error", run.last_error.empty() ? Json(nullptr) : Json(run.last_error)},
            {"awaiting", run.awaiting.empty() ? Json(nullptr) : Json(run.awaiting)},
            {"created_at", run.created_at},
            {"started_at", Optional(run.started_at)},
            {"updated_at", run.updated_at},
            {"finished_at", Optional(run.finished_at)}};
  if (run.running_since) view["elapsed_s"] = run.active_s + (UnixNow() - *run.running_since);
  std::lock_guard lock(mutex_);
  if (active_run_ == run.id) {
    if (run.state != RunState::kRunning) view["state"] = "starting";
    if (progress_.eta_s >= 0) view["eta_s"] = progress_.eta_s;
    if (progress_.probes_per_hour > 0) view["rate_per_h"] = progress_.probes_per_hour;
    view["phase"] = progress_.phase;
    if (!progress_.machine_state.empty()) view["machine_state"] = progress_.machine_state;
    if (progress_.machine_position) view["machine_position"] = Vec(*progress_.machine_position);
  }
  return view;
}

Json Daemon::Info() const {
  Json machine{{"uri", config_.run.machine.uri},
               {"configured", !config_.run.machine.uri.empty()},
               {"connected", false},
               {"state", nullptr},
               {"position", nullptr}};
  Json active = nullptr;
  {
    std::lock_guard lock(mutex_);
    if (active_run_ != 0) {
      active = active_run_;
      machine["connected"] = progress_.machine_connected;
      if (!progress_.machine_state.empty()) machine["state"] = progress_.machine_state;
      if (progress_.machine_position) machine["position"] = Vec(*progress_.machine_position);
    }
  }
  const RigConfig& rig = config_.run.rig;
  return {{"name", "gs360d"},
          {"version", std::string(Version())},
          {"commit", std::string(Commit())},
          {"api", "v1"},
          {"started_at", started_at_},
          {"uptime_s", UnixNow() - started_at_},
          {"rig",
           {{"shape", std::string(SensorShapeName(rig.shape.shape))},
            {"mesh", !rig.mesh_path.empty()},
            {"ball_radius", rig.ball_radius},
            {"gel_thickness", rig.gel_thickness},
            {"camera_z", rig.camera_z},
            {"base_in_machine", Vec(rig.base_in_machine)}}},
          {"limits",
           {{"envelope_min", Vec(config_.limits.envelope_min)},
            {"envelope_max", Vec(config_.limits.envelope_max)},
            {"max_press_depth", config_.limits.max_press_depth},
            {"max_feed_mm_per_min", config_.limits.max_feed_mm_per_min}}},
          {"machine", machine},
          {"camera",
           {{"uri", config_.run.camera.uri}, {"configured", !config_.run.camera.uri.empty()}}},
          {"active_run", active},
          {"calibrating_run",
           calibration_->Running() != 0 ? Json(calibration_->Running()) : Json(nullptr)},
          {"status", StatusLine()}};
}

Json Daemon::ListRuns() const {
  Json runs = Json::array();
  for (const RunRecord& run : Reader().ListRuns()) {
    if (auto view = GetRun(run.id)) runs.push_back(std::move(*view));
  }
  return {{"runs", runs}};
}

Json Daemon::RunStatic(RunDatabase& db, std::int64_t run_id) const {
  {
    std::lock_guard lock(mutex_);
    const auto it = run_static_.find(run_id);
    if (it != run_static_.end()) return it->second;
  }
  Json facts = Json::object();
  try {
    const RunConfig config = StoredRunConfig(db, run_id);
    facts["shape"] = config.rig.mesh_path.empty()
                         ? Json(std::string(SensorShapeName(config.rig.shape.shape)))
                         : Json("mesh");
    facts["until_converged"] = config.converge.enabled;
    const ProbePlan plan = RunEngine::LoadPlan(db, run_id);
    facts["candidates"] = plan.candidates;
    facts["estimate_s"] = plan.estimate.Total();
  } catch (const std::exception&) {
    // A run created by another tool: its counts still hold.
  }
  std::lock_guard lock(mutex_);
  run_static_[run_id] = facts;
  return facts;
}

std::optional<Json> Daemon::GetRun(std::int64_t run_id) const {
  RunDatabase& db = Reader();
  const auto run = db.GetRun(run_id);
  if (!run) return std::nullopt;
  Json view = RunView(*run, db.CountProbes(run_id));
  view.update(RunStatic(db, run_id));
  if (!view["eta_s"].is_number() && view.contains("estimate_s") && !IsTerminal(run->state)) {
    const double total = static_cast<double>(std::max<std::int64_t>(1, view["probes_total"]));
    view["eta_s"] = view["estimate_s"].get<double>() *
                    static_cast<double>(view["probes_pending"].get<std::int64_t>()) / total;
  }
  const auto calibration = calibration_->State(run_id);
  view["calibration"] = calibration ? Json(*calibration) : Json(nullptr);
  // Read only for the runs that converge: the stored config is parsed for it.
  const auto convergence =
      view.value("until_converged", false) ? convergence_->View(db, run_id) : std::optional<Json>();
  view["convergence"] = convergence ? *convergence : Json(nullptr);
  return view;
}

std::optional<Json> Daemon::ListProbes(std::int64_t run_id) const {
  RunDatabase& db = Reader();
  if (!db.GetRun(run_id)) return std::nullopt;
  Json probes = Json::array();
  for (const ProbeRecord& p : db.ListProbes(run_id)) {
    Json e{{"index", p.plan_index},
           {"point", Vec(p.plan.point_sensor)},
           {"normal", Vec(p.plan.normal_sensor)},
           {"state", std::string(ToString(p.state))},
           {"attempts", p.attempts}};
    if (!p.last_error.empty()) e["last_error"] = p.last_error;
    if (!p.skip_reason.empty()) e["skip_reason"] = p.skip_reason;
    if (p.state == ProbeState::kFailed && !p.retry) e["retry"] = false;
    probes.push_back(std::move(e));
  }
  return Json{{"run", run_id}, {"frame", "sensor"}, {"unit", "mm"}, {"probes", probes}};
}

std::optional<Json> Daemon::RunLog(std::int64_t run_id, std::int64_t after, int limit) const {
  RunDatabase& db = Reader();
  if (!db.GetRun(run_id)) return std::nullopt;
  Json events = Json::array();
  for (const EventRecord& e : db.ListEvents(run_id, after, limit)) {
    events.push_back({{"id", e.id},
                      {"time", e.timestamp},
                      {"level", std::string(ToString(e.level))},
                      {"message", e.message}});
  }
  return Json{{"run", run_id}, {"events", events}};
}

std::optional<std::vector<std::uint8_t>> Daemon::LatestFramePng(std::int64_t run_id) const {
  RunDatabase& db = Reader();
  if (!db.GetRun(run_id)) return std::nullopt;
  const auto frame = db.LatestFrame(run_id);
  if (!frame) return std::nullopt;
  return db.LoadFramePng(frame->id);
}

std::optional<std::vector<std::uint8_t>> Daemon::ProbeFramePng(std::int64_t run_id,
                                                               int plan_index) const {
  RunDatabase& db = Reader();
  const auto probe = db.GetProbeByIndex(run_id, plan_index);
  if (!probe || probe->state != ProbeState::kCaptured) return std::nullopt;
  for (const CapturedProbe& c : db.ListCapturedProbes(run_id)) {
    if (c.probe.plan_index == plan_index) return db.LoadFramePng(c.frame_id);
  }
  return std::nullopt;
}

std::optional<Json> Daemon::Calibration(std::int64_t run_id) const {
  if (!Reader().GetRun(run_id)) return std::nullopt;
  if (auto view = calibration_->View(run_id)) {
    (*view).erase("files");  // paths stay inside the daemon
    return view;
  }
  return Json{{"run", run_id}, {"state", "none"}, {"stages", Json::array()}};
}

std::optional<std::filesystem::path> Daemon::FileOf(std::int64_t run_id, RunFile file) const {
  const auto view = calibration_->View(run_id);
  if (!view || view->value("state", "") != "done" || !view->contains("files")) return std::nullopt;
  static constexpr const char* kKeys[] = {"model", "onnx", "report", "validation"};
  const std::string key = kKeys[static_cast<int>(file)];
  const Json& files = (*view)["files"];
  if (!files.contains(key) || !files[key].is_string()) return std::nullopt;
  // Only files this daemon wrote into its own data folder are served.
  std::error_code ec;
  const auto path = std::filesystem::weakly_canonical(files[key].get<std::string>(), ec);
  const auto runs = RunDir(run_id);
  if (ec || path.string().rfind(runs.string() + "/", 0) != 0 ||
      !std::filesystem::is_regular_file(path)) {
    return std::nullopt;
  }
  return path;
}

std::filesystem::path Daemon::RunDir(std::int64_t run_id) const {
  return config_.data_dir / "runs" / std::to_string(run_id);
}

Json Daemon::ListMeshes() const {
  Json meshes = Json::array();
  for (const auto& entry : std::filesystem::directory_iterator(config_.data_dir / "meshes")) {
    const std::string ext = entry.path().extension().string();
    if (ext.size() < 2 || !IsMeshFormat(ext.substr(1))) continue;
    meshes.push_back({{"id", entry.path().stem().string()},
                      {"format", ext.substr(1)},
                      {"bytes", std::filesystem::file_size(entry.path())}});
  }
  return {{"meshes", meshes}};
}

std::optional<std::filesystem::path> Daemon::MeshPath(const std::string& id) const {
  if (id.size() != 16 || id.find_first_not_of("0123456789abcdef") != std::string::npos) {
    return std::nullopt;
  }
  for (const char* ext : {"stl", "obj", "ply"}) {
    const auto path = config_.data_dir / "meshes" / (id + "." + ext);
    if (std::filesystem::is_regular_file(path)) return path;
  }
  return std::nullopt;
}

}  // namespace gs360
