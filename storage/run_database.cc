#include "storage/run_database.h"

#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <locale>
#include <sstream>
#include <stdexcept>
#include <system_error>
#include <unordered_map>
#include <utility>

#include <nlohmann/json.hpp>

#include "storage/schema.h"
#include "storage/sqlite_connection.h"

namespace gs360 {
namespace {

namespace fs = std::filesystem;
using storage_internal::Connection;
using storage_internal::Stmt;
using storage_internal::Transaction;

void RequireJson(std::string_view json, std::string_view field) {
  if (!nlohmann::json::accept(json.begin(), json.end())) {
    std::string head(json.substr(0, 60));
    throw std::invalid_argument(std::string(field) + " is not valid JSON: '" + head +
                                (json.size() > 60 ? "...'" : "'"));
  }
}

void RequireFinite(const Eigen::Vector3d& v, const std::string& what) {
  if (!v.allFinite()) {
    throw std::invalid_argument(what + " has a non-finite coordinate (" + std::to_string(v.x()) +
                                ", " + std::to_string(v.y()) + ", " + std::to_string(v.z()) + ")");
  }
}

void RequireFinite(double v, const std::string& what) {
  if (!std::isfinite(v)) throw std::invalid_argument(what + " is not finite: " + std::to_string(v));
}

void RequireValidFrame(const EncodedFrame& f) {
  if (f.png.empty()) throw std::invalid_argument("EncodedFrame.png is empty");
  if (f.width <= 0 || f.height <= 0) {
    throw std::invalid_argument("EncodedFrame size must be positive, got " +
                                std::to_string(f.width) + "x" + std::to_string(f.height));
  }
  if (f.channels != 1 && f.channels != 3) {
    throw std::invalid_argument("EncodedFrame.channels must be 1 or 3, got " +
                                std::to_string(f.channels));
  }
  if (f.bit_depth != 8 && f.bit_depth != 16) {
    throw std::invalid_argument("EncodedFrame.bit_depth must be 8 or 16, got " +
                                std::to_string(f.bit_depth));
  }
}

// ---------------------------------------------------------------------------------------------
// Row readers. Column lists are macros so that the SQL stays a literal (the cache key).

#define GS360_RUN_COLUMNS                                                                      \
  "id, name, config_json, mesh_hash, state, created_at, started_at, updated_at, finished_at, " \
  "active_s, running_since, last_error, awaiting, commanded_path, homing_sent"

RunRecord ReadRun(const Stmt& s) {
  RunRecord r;
  r.id = s.GetInt(0);
  r.name = s.GetText(1);
  r.config_json = s.GetText(2);
  r.mesh_hash = s.GetText(3);
  r.state = ParseRunState(s.GetText(4)).value_or(RunState::kFailed);
  r.created_at = s.GetReal(5);
  r.started_at = s.GetOptReal(6);
  r.updated_at = s.GetReal(7);
  r.finished_at = s.GetOptReal(8);
  r.active_s = s.GetReal(9);
  r.running_since = s.GetOptReal(10);
  r.last_error = s.GetText(11);
  r.awaiting = s.GetText(12);
  // "x y z;x y z;...": written by SetCommandedPath only.
  std::istringstream path(s.GetText(13));
  for (std::string point; std::getline(path, point, ';');) {
    Eigen::Vector3d p;
    std::istringstream xyz(point);
    xyz.imbue(std::locale::classic());
    if (xyz >> p.x() >> p.y() >> p.z()) r.commanded_path.push_back(p);
  }
  r.homing_sent = s.GetInt(14) != 0;
  return r;
}

#define GS360_PROBE_COLUMNS                                                                    \
  "p.id, p.run_id, p.plan_index, p.point_x, p.point_y, p.point_z, p.normal_x, p.normal_y, "    \
  "p.normal_z, p.approach_x, p.approach_y, p.approach_z, p.press_x, p.press_y, p.press_z, "    \
  "p.retract_x, p.retract_y, p.retract_z, p.state, p.attempts, p.mpos_x, p.mpos_y, p.mpos_z, " \
  "p.sync_time, p.captured_at, p.last_error, p.skip_reason, p.retry"
constexpr int kProbeColumnCount = 28;

ProbeRecord ReadProbe(const Stmt& s) {
  ProbeRecord p;
  p.id = s.GetInt(0);
  p.run_id = s.GetInt(1);
  p.plan_index = static_cast<int>(s.GetInt(2));
  p.plan.point_sensor = s.GetVec(3);
  p.plan.normal_sensor = s.GetVec(6);
  p.plan.approach_machine = s.GetVec(9);
  p.plan.press_machine = s.GetVec(12);
  p.plan.retract_machine = s.GetVec(15);
  p.state = ParseProbeState(s.GetText(18)).value_or(ProbeState::kPlanned);
  p.attempts = static_cast<int>(s.GetInt(19));
  if (!s.IsNull(20)) p.machine_position = s.GetVec(20);
  p.sync_time = s.GetOptReal(23);
  p.captured_at = s.GetOptReal(24);
  p.last_error = s.GetText(25);
  p.skip_reason = s.GetText(26);
  p.retry = s.GetInt(27) != 0;
  return p;
}

#define GS360_FRAME_COLUMNS \
  "id, run_id, probe_id, kind, timestamp, width, height, channels, bit_depth, size, checksum"

FrameInfo ReadFrameInfo(const Stmt& s) {
  FrameInfo f;
  f.id = s.GetInt(0);
  f.run_id = s.GetInt(1);
  f.probe_id = s.GetOptInt(2);
  f.kind = s.GetText(3) == "reference" ? FrameKind::kReference : FrameKind::kPress;
  f.timestamp = s.GetReal(4);
  f.width = static_cast<int>(s.GetInt(5));
  f.height = static_cast<int>(s.GetInt(6));
  f.channels = static_cast<int>(s.GetInt(7));
  f.bit_depth = static_cast<int>(s.GetInt(8));
  f.png_bytes = s.GetInt(9);
  f.checksum = s.GetText(10);
  return f;
}

#define GS360_EVENT_COLUMNS "id, run_id, timestamp, level, message, data_json"

EventRecord ReadEvent(const Stmt& s) {
  EventRecord e;
  e.id = s.GetInt(0);
  e.run_id = s.GetOptInt(1);
  e.timestamp = s.GetReal(2);
  e.level = ParseEventLevel(s.GetText(3)).value_or(EventLevel::kInfo);
  e.message = s.GetText(4);
  e.data_json = s.GetText(5);
  return e;
}

bool TransitionAllowed(RunState from, RunState to) {
  using S = RunState;
  switch (from) {
    case S::kCreated:
      return to == S::kRunning || to == S::kCancelled || to == S::kFailed;
    case S::kRunning:
      return to == S::kPaused || to == S::kInterrupted || to == S::kDone || to == S::kFailed ||
             to == S::kCancelled;
    case S::kPaused:
      return to == S::kRunning || to == S::kInterrupted || to == S::kFailed || to == S::kCancelled;
    case S::kInterrupted:
      return to == S::kRunning || to == S::kFailed || to == S::kCancelled;
    case S::kDone:
    case S::kFailed:
    case S::kCancelled:
      return false;
  }
  return false;
}

}  // namespace

// ---------------------------------------------------------------------------------------------

void RunDatabaseOptions::Check() const {
  if (busy_timeout_ms < 0) {
    throw std::invalid_argument("RunDatabaseOptions.busy_timeout_ms must be >= 0, got " +
                                std::to_string(busy_timeout_ms));
  }
  if (synchronous != SyncMode::kNormal && synchronous != SyncMode::kFull) {
    throw std::invalid_argument("RunDatabaseOptions.synchronous: unknown value " +
                                std::to_string(static_cast<int>(synchronous)));
  }
  if (max_page_count < 0) {
    throw std::invalid_argument("RunDatabaseOptions.max_page_count must be >= 0, got " +
                                std::to_string(max_page_count));
  }
  png.Check();
}

std::string_view ToString(RunState s) {
  switch (s) {
    case RunState::kCreated:
      return "created";
    case RunState::kRunning:
      return "running";
    case RunState::kPaused:
      return "paused";
    case RunState::kInterrupted:
      return "interrupted";
    case RunState::kDone:
      return "done";
    case RunState::kFailed:
      return "failed";
    case RunState::kCancelled:
      return "cancelled";
  }
  return "unknown";
}

std::string_view ToString(ProbeState s) {
  switch (s) {
    case ProbeState::kPlanned:
      return "planned";
    case ProbeState::kCaptured:
      return "captured";
    case ProbeState::kFailed:
      return "failed";
    case ProbeState::kSkipped:
      return "skipped";
  }
  return "unknown";
}

std::string_view ToString(FrameKind k) {
  return k == FrameKind::kPress ? "press" : "reference";
}

std::string_view ToString(EventLevel l) {
  switch (l) {
    case EventLevel::kDebug:
      return "debug";
    case EventLevel::kInfo:
      return "info";
    case EventLevel::kWarning:
      return "warning";
    case EventLevel::kError:
      return "error";
  }
  return "unknown";
}

std::optional<RunState> ParseRunState(std::string_view s) {
  for (RunState v :
       {RunState::kCreated, RunState::kRunning, RunState::kPaused, RunState::kInterrupted,
        RunState::kDone, RunState::kFailed, RunState::kCancelled}) {
    if (ToString(v) == s) return v;
  }
  return std::nullopt;
}

std::optional<ProbeState> ParseProbeState(std::string_view s) {
  for (ProbeState v :
       {ProbeState::kPlanned, ProbeState::kCaptured, ProbeState::kFailed, ProbeState::kSkipped}) {
    if (ToString(v) == s) return v;
  }
  return std::nullopt;
}

std::optional<EventLevel> ParseEventLevel(std::string_view s) {
  for (EventLevel v :
       {EventLevel::kDebug, EventLevel::kInfo, EventLevel::kWarning, EventLevel::kError}) {
    if (ToString(v) == s) return v;
  }
  return std::nullopt;
}

bool IsTerminal(RunState s) {
  return s == RunState::kDone || s == RunState::kFailed || s == RunState::kCancelled;
}

void CreateDatabaseAtVersion(const std::filesystem::path& path, int version) {
  if (version < 1 || version > kSchemaVersion) {
    throw std::invalid_argument("CreateDatabaseAtVersion: version must be in 1.." +
                                std::to_string(kSchemaVersion) + ", got " +
                                std::to_string(version));
  }
  Connection conn(path, RunDatabaseOptions{});
  conn.Open(version);
}

struct RunDatabase::Impl : Connection {
  using Connection::Connection;

  // Loads a probe's run id and state inside the caller's transaction; throws kNotFound.
  std::pair<std::int64_t, ProbeState> ProbeRunAndState(std::int64_t probe_id) const {
    Stmt s = Prepare("SELECT run_id, state FROM probes WHERE id = ?");
    s.Int(1, probe_id);
    if (!s.Step()) Throw(StorageErrc::kNotFound, "no probe with id " + std::to_string(probe_id));
    return {s.GetInt(0), ParseProbeState(s.GetText(1)).value_or(ProbeState::kPlanned)};
  }

  void RequireRun(std::int64_t run_id) const {
    Stmt s = Prepare("SELECT 1 FROM runs WHERE id = ? AND deleted_at IS NULL");
    s.Int(1, run_id);
    if (!s.Step()) Throw(StorageErrc::kNotFound, "no run with id " + std::to_string(run_id));
  }

  void RequireProbeOpen(std::int64_t probe_id, ProbeState state, std::string_view action) const {
    if (state == ProbeState::kPlanned || state == ProbeState::kFailed) return;
    Throw(StorageErrc::kInvalidState, "cannot " + std::string(action) + " probe " +
                                          std::to_string(probe_id) + ": it is already " +
                                          std::string(ToString(state)));
  }

  void TouchRun(std::int64_t run_id, double now) const {
    Stmt s = Prepare("UPDATE runs SET updated_at = ? WHERE id = ?");
    s.Real(1, now).Int(2, run_id).Run();
  }

  std::int64_t InsertFrame(std::int64_t run_id, std::optional<std::int64_t> probe_id,
                           FrameKind kind, double timestamp, const EncodedFrame& f,
                           const std::string& checksum) const {
    Stmt s = Prepare(
        "INSERT INTO frames (run_id, probe_id, kind, timestamp, width, height, channels, "
        "bit_depth, size, checksum, png) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)");
    s.Int(1, run_id)
        .OptInt(2, probe_id)
        .Text(3, ToString(kind))
        .Real(4, timestamp)
        .Int(5, f.width)
        .Int(6, f.height)
        .Int(7, f.channels)
        .Int(8, f.bit_depth)
        .Int(9, static_cast<std::int64_t>(f.png.size()))
        .Text(10, checksum)
        .Blob(11, f.png)
        .Run();
    return LastInsertId();
  }

  std::optional<FrameInfo> FrameInfoById(std::int64_t frame_id) const {
    Stmt s = Prepare("SELECT " GS360_FRAME_COLUMNS " FROM frames WHERE id = ?");
    s.Int(1, frame_id);
    if (!s.Step()) return std::nullopt;
    return ReadFrameInfo(s);
  }

  // The frame's PNG bytes, checksum verified, with its metadata.
  std::pair<FrameInfo, std::vector<std::uint8_t>> LoadVerified(std::int64_t frame_id) const {
    Transaction tx(*this, Transaction::kRead);
    Stmt s = Prepare("SELECT " GS360_FRAME_COLUMNS ", png FROM frames WHERE id = ?");
    s.Int(1, frame_id);
    if (!s.Step()) Throw(StorageErrc::kNotFound, "no frame with id " + std::to_string(frame_id));
    FrameInfo info = ReadFrameInfo(s);
    std::vector<std::uint8_t> png = s.GetBlob(11);
    const std::string actual = BlobChecksum(png);
    if (actual != info.checksum || static_cast<std::int64_t>(png.size()) != info.png_bytes) {
      Throw(StorageErrc::kCorruptBlob, Describe(info) + ": checksum mismatch (stored " +
                                           info.checksum + ", " + std::to_string(info.png_bytes) +
                                           " bytes; read " + actual + ", " +
                                           std::to_string(png.size()) + " bytes)");
    }
    return {std::move(info), std::move(png)};
  }

  std::string Describe(const FrameInfo& info) const {
    std::string d = std::string(ToString(info.kind)) + " frame " + std::to_string(info.id) +
                    " of run " + std::to_string(info.run_id);
    if (info.probe_id) {
      d += ", probe " + std::to_string(*info.probe_id);
      Stmt s = Prepare("SELECT plan_index FROM probes WHERE id = ?");
      s.Int(1, *info.probe_id);
      if (s.Step()) d += " (plan index " + std::to_string(s.GetInt(0)) + ")";
    }
    return d;
  }

  ProbeCounts Counts(std::int64_t run_id) const {
    ProbeCounts c;
    Stmt s = Prepare("SELECT state, count(*) FROM probes WHERE run_id = ? GROUP BY state");
    s.Int(1, run_id);
    while (s.Step()) {
      const std::int64_t n = s.GetInt(1);
      c.total += n;
      switch (ParseProbeState(s.GetText(0)).value_or(ProbeState::kPlanned)) {
        case ProbeState::kPlanned:
          c.planned += n;
          break;
        case ProbeState::kCaptured:
          c.captured += n;
          break;
        case ProbeState::kFailed:
          c.failed += n;
          break;
        case ProbeState::kSkipped:
          c.skipped += n;
          break;
      }
    }
    return c;
  }

  std::optional<RunRecord> Run(std::int64_t run_id) const {
    Stmt s = Prepare("SELECT " GS360_RUN_COLUMNS " FROM runs WHERE id = ? AND deleted_at IS NULL");
    s.Int(1, run_id);
    if (!s.Step()) return std::nullopt;
    return ReadRun(s);
  }

  std::int64_t AddEvent(std::optional<std::int64_t> run_id, EventLevel level,
                        std::string_view message, std::string_view data_json) const {
    Stmt s = Prepare(
        "INSERT INTO events (run_id, timestamp, level, message, data_json) "
        "VALUES (?, ?, ?, ?, ?)");
    s.OptInt(1, run_id)
        .Real(2, Now())
        .Text(3, ToString(level))
        .Text(4, message)
        .OptText(5, data_json)
        .Run();
    return LastInsertId();
  }
};

RunDatabase::RunDatabase(const std::filesystem::path& path, RunDatabaseOptions options) {
  options.Check();
  impl_ = std::make_unique<Impl>(path, std::move(options));
  impl_->Open(kSchemaVersion);
}

RunDatabase::~RunDatabase() = default;
RunDatabase::RunDatabase(RunDatabase&&) noexcept = default;
RunDatabase& RunDatabase::operator=(RunDatabase&&) noexcept = default;

const std::filesystem::path& RunDatabase::path() const {
  return impl_->path();
}
const RunDatabaseOptions& RunDatabase::options() const {
  return impl_->options();
}
int RunDatabase::schema_version() const {
  return impl_->schema_version();
}

// ---- runs ----

std::int64_t RunDatabase::CreateRun(std::string_view config_json, std::string_view mesh_hash,
                                    std::string_view name) {
  RequireJson(config_json, "CreateRun config_json");
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  const double now = c.Now();
  Stmt s = c.Prepare(
      "INSERT INTO runs (name, config_json, mesh_hash, state, created_at, updated_at) "
      "VALUES (?, ?, ?, 'created', ?, ?)");
  s.Text(1, name).Text(2, config_json).Text(3, mesh_hash).Real(4, now).Real(5, now).Run();
  const std::int64_t id = c.LastInsertId();
  c.AddEvent(id, EventLevel::kInfo, "run created", "");
  tx.Commit();
  return id;
}

std::optional<RunRecord> RunDatabase::GetRun(std::int64_t run_id) const {
  return impl_->Run(run_id);
}

std::vector<RunRecord> RunDatabase::ListRuns() const {
  std::vector<RunRecord> out;
  Stmt s =
      impl_->Prepare("SELECT " GS360_RUN_COLUMNS " FROM runs WHERE deleted_at IS NULL ORDER BY id");
  while (s.Step()) out.push_back(ReadRun(s));
  return out;
}

void RunDatabase::SetRunState(std::int64_t run_id, RunState state) {
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  const std::optional<RunRecord> run = c.Run(run_id);
  if (!run) c.Throw(StorageErrc::kNotFound, "no run with id " + std::to_string(run_id));
  if (run->state == state) return;
  if (!TransitionAllowed(run->state, state)) {
    c.Throw(StorageErrc::kInvalidState, "run " + std::to_string(run_id) + " cannot go from " +
                                            std::string(ToString(run->state)) + " to " +
                                            std::string(ToString(state)));
  }
  const double now = c.Now();
  double active_s = run->active_s;
  std::optional<double> running_since = run->running_since;
  std::optional<double> started_at = run->started_at;
  std::optional<double> finished_at = run->finished_at;
  if (run->state == RunState::kRunning && running_since) {
    const double end = state == RunState::kInterrupted ? run->updated_at : now;
    active_s += std::max(0.0, end - *running_since);
    running_since.reset();
  }
  if (state == RunState::kRunning) {
    running_since = now;
    if (!started_at) started_at = now;
  }
  if (IsTerminal(state)) finished_at = now;
  Stmt s = c.Prepare(
      "UPDATE runs SET state = ?, active_s = ?, running_since = ?, started_at = ?, "
      "finished_at = ?, updated_at = ? WHERE id = ?");
  s.Text(1, ToString(state))
      .Real(2, active_s)
      .OptReal(3, running_since)
      .OptReal(4, started_at)
      .OptReal(5, finished_at)
      .Real(6, now)
      .Int(7, run_id)
      .Run();
  if (state == RunState::kRunning) {
    Stmt clear = c.Prepare("UPDATE runs SET last_error = '', awaiting = '' WHERE id = ?");
    clear.Int(1, run_id).Run();
  }
  c.AddEvent(
      run_id, EventLevel::kInfo,
      "run state " + std::string(ToString(run->state)) + " -> " + std::string(ToString(state)),
      "{\"from\":\"" + std::string(ToString(run->state)) + "\",\"state\":\"" +
          std::string(ToString(state)) + "\"}");
  tx.Commit();
}

void RunDatabase::SetRunError(std::int64_t run_id, std::string_view message) {
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  c.RequireRun(run_id);
  Stmt s = c.Prepare("UPDATE runs SET last_error = ?, updated_at = ? WHERE id = ?");
  s.Text(1, message).Real(2, c.Now()).Int(3, run_id).Run();
  c.AddEvent(run_id, EventLevel::kError, message, "");
  tx.Commit();
}

void RunDatabase::SetRunAwaiting(std::int64_t run_id, std::string_view what,
                                 std::string_view message) {
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  c.RequireRun(run_id);
  Stmt s = c.Prepare("UPDATE runs SET last_error = ?, awaiting = ?, updated_at = ? WHERE id = ?");
  s.Text(1, message).Text(2, what).Real(3, c.Now()).Int(4, run_id).Run();
  c.AddEvent(run_id, EventLevel::kError, message, "");
  tx.Commit();
}

void RunDatabase::SetCommandedPath(std::int64_t run_id, std::span<const Eigen::Vector3d> path) {
  std::ostringstream text;
  text.imbue(std::locale::classic());
  text.precision(17);
  for (const Eigen::Vector3d& p : path) {
    RequireFinite(p, "SetCommandedPath: a point");
    text << p.x() << ' ' << p.y() << ' ' << p.z() << ';';
  }
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  c.RequireRun(run_id);
  Stmt s = c.Prepare("UPDATE runs SET commanded_path = ?, homing_sent = 0 WHERE id = ?");
  s.Text(1, text.str()).Int(2, run_id).Run();
  tx.Commit();
}

void RunDatabase::MarkHomingSent(std::int64_t run_id) {
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  c.RequireRun(run_id);
  c.Prepare("UPDATE runs SET homing_sent = 1 WHERE id = ?").Int(1, run_id).Run();
  tx.Commit();
}

void RunDatabase::DeleteRun(std::int64_t run_id) {
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  const std::optional<RunRecord> run = c.Run(run_id);
  if (!run) c.Throw(StorageErrc::kNotFound, "no run with id " + std::to_string(run_id));
  if (run->state == RunState::kRunning) {
    c.Throw(StorageErrc::kInvalidState,
            "run " + std::to_string(run_id) + " is running; pause or cancel it first");
  }
  // The row stays as a tombstone (SQLite would give its id to the next run otherwise).
  for (const char* sql :
       {"DELETE FROM frames WHERE run_id = ?", "DELETE FROM probes WHERE run_id = ?",
        "DELETE FROM events WHERE run_id = ?", "DELETE FROM artifacts WHERE run_id = ?",
        "UPDATE models SET run_id = NULL WHERE run_id = ?"}) {
    Stmt s = c.Prepare(sql);
    s.Int(1, run_id).Run();
  }
  Stmt s = c.Prepare(
      "UPDATE runs SET deleted_at = ?, name = '', config_json = '{}', last_error = '' WHERE id = "
      "?");
  s.Real(1, c.Now()).Int(2, run_id).Run();
  tx.Commit();
}

// ---- plan and probes ----

std::vector<std::int64_t> RunDatabase::InsertPlan(std::int64_t run_id,
                                                  std::span<const ProbePlanEntry> plan) {
  for (std::size_t i = 0; i < plan.size(); ++i) {
    const std::string where = "InsertPlan: plan index " + std::to_string(i) + " ";
    RequireFinite(plan[i].point_sensor, where + "point_sensor");
    RequireFinite(plan[i].normal_sensor, where + "normal_sensor");
    RequireFinite(plan[i].approach_machine, where + "approach_machine");
    RequireFinite(plan[i].press_machine, where + "press_machine");
    RequireFinite(plan[i].retract_machine, where + "retract_machine");
  }
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  c.RequireRun(run_id);
  {
    Stmt s = c.Prepare("SELECT count(*) FROM probes WHERE run_id = ?");
    s.Int(1, run_id);
    if (s.Step() && s.GetInt(0) > 0) {
      c.Throw(StorageErrc::kInvalidState, "run " + std::to_string(run_id) + " already has " +
                                              std::to_string(s.GetInt(0)) + " planned probes");
    }
  }
  std::vector<std::int64_t> ids;
  ids.reserve(plan.size());
  for (std::size_t i = 0; i < plan.size(); ++i) {
    const ProbePlanEntry& e = plan[i];
    Stmt s = c.Prepare(
        "INSERT INTO probes (run_id, plan_index, point_x, point_y, point_z, normal_x, normal_y, "
        "normal_z, approach_x, approach_y, approach_z, press_x, press_y, press_z, retract_x, "
        "retract_y, retract_z) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)");
    s.Int(1, run_id)
        .Int(2, static_cast<std::int64_t>(i))
        .Vec(3, e.point_sensor)
        .Vec(6, e.normal_sensor)
        .Vec(9, e.approach_machine)
        .Vec(12, e.press_machine)
        .Vec(15, e.retract_machine)
        .Run();
    ids.push_back(c.LastInsertId());
  }
  c.AddEvent(run_id, EventLevel::kInfo, "plan inserted: " + std::to_string(plan.size()) + " probes",
             "");
  c.TouchRun(run_id, c.Now());
  tx.Commit();
  return ids;
}

std::optional<ProbeRecord> RunDatabase::GetProbe(std::int64_t probe_id) const {
  Stmt s = impl_->Prepare("SELECT " GS360_PROBE_COLUMNS " FROM probes p WHERE p.id = ?");
  s.Int(1, probe_id);
  if (!s.Step()) return std::nullopt;
  return ReadProbe(s);
}

std::optional<ProbeRecord> RunDatabase::GetProbeByIndex(std::int64_t run_id, int plan_index) const {
  Stmt s = impl_->Prepare("SELECT " GS360_PROBE_COLUMNS
                          " FROM probes p WHERE p.run_id = ? AND p.plan_index = ?");
  s.Int(1, run_id).Int(2, plan_index);
  if (!s.Step()) return std::nullopt;
  return ReadProbe(s);
}

std::vector<ProbeRecord> RunDatabase::ListProbes(std::int64_t run_id,
                                                 std::optional<ProbeState> state) const {
  std::vector<ProbeRecord> out;
  if (state) {
    Stmt s = impl_->Prepare("SELECT " GS360_PROBE_COLUMNS
                            " FROM probes p WHERE p.run_id = ? AND p.state = ? "
                            "ORDER BY p.plan_index");
    s.Int(1, run_id).Text(2, ToString(*state));
    while (s.Step()) out.push_back(ReadProbe(s));
  } else {
    Stmt s = impl_->Prepare("SELECT " GS360_PROBE_COLUMNS
                            " FROM probes p WHERE p.run_id = ? ORDER BY p.plan_index");
    s.Int(1, run_id);
    while (s.Step()) out.push_back(ReadProbe(s));
  }
  return out;
}

std::optional<ProbeRecord> RunDatabase::NextPendingProbe(std::int64_t run_id, int max_attempts,
                                                         std::optional<std::int64_t> except) const {
  // Two index lookups (probes_by_state) instead of a scan past every captured probe.
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kRead);
  std::optional<ProbeRecord> best;
  {
    Stmt s = c.Prepare("SELECT " GS360_PROBE_COLUMNS
                       " FROM probes p WHERE p.run_id = ? AND p.state = 'planned' "
                       "AND p.id != ? ORDER BY p.plan_index LIMIT 1");
    s.Int(1, run_id).Int(2, except.value_or(-1));
    if (s.Step()) best = ReadProbe(s);
  }
  {
    Stmt s = c.Prepare("SELECT " GS360_PROBE_COLUMNS
                       " FROM probes p WHERE p.run_id = ? AND p.state = 'failed' "
                       "AND p.retry != 0 AND p.attempts < ? AND p.id != ? "
                       "ORDER BY p.plan_index LIMIT 1");
    s.Int(1, run_id).Int(2, max_attempts).Int(3, except.value_or(-1));
    if (s.Step()) {
      ProbeRecord failed = ReadProbe(s);
      if (!best || failed.plan_index < best->plan_index) best = std::move(failed);
    }
  }
  tx.Commit();
  return best;
}

ProbeCounts RunDatabase::CountProbes(std::int64_t run_id) const {
  return impl_->Counts(run_id);
}

std::int64_t RunDatabase::CommitCapture(std::int64_t probe_id, const EncodedFrame& frame,
                                        const CaptureReport& report) {
  RequireValidFrame(frame);
  RequireFinite(report.machine_position, "CaptureReport.machine_position");
  RequireFinite(report.sync_time, "CaptureReport.sync_time");
  RequireFinite(report.frame_time, "CaptureReport.frame_time");
  if (report.frame_time < report.sync_time) {
    throw std::invalid_argument("CaptureReport.frame_time (" + std::to_string(report.frame_time) +
                                ") is before sync_time (" + std::to_string(report.sync_time) +
                                "): a press frame must be taken after the sync ok");
  }
  const std::string checksum = BlobChecksum(frame.png);
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  const auto [run_id, state] = c.ProbeRunAndState(probe_id);
  c.RequireProbeOpen(probe_id, state, "capture");
  const double now = c.Now();
  const std::int64_t frame_id =
      c.InsertFrame(run_id, probe_id, FrameKind::kPress, report.frame_time, frame, checksum);
  Stmt s = c.Prepare(
      "UPDATE probes SET state = 'captured', attempts = attempts + 1, mpos_x = ?, mpos_y = ?, "
      "mpos_z = ?, sync_time = ?, captured_at = ? WHERE id = ?");
  s.Vec(1, report.machine_position).Real(4, report.sync_time).Real(5, now).Int(6, probe_id).Run();
  c.TouchRun(run_id, now);
  tx.Commit();
  return frame_id;
}

std::int64_t RunDatabase::CommitCapture(std::int64_t probe_id, const cv::Mat& image,
                                        const CaptureReport& report) {
  return CommitCapture(probe_id, EncodeFrame(image, impl_->options().png), report);
}

void RunDatabase::MarkProbeFailed(std::int64_t probe_id, std::string_view error, bool retry) {
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  const auto [run_id, state] = c.ProbeRunAndState(probe_id);
  c.RequireProbeOpen(probe_id, state, "fail");
  Stmt s = c.Prepare(
      "UPDATE probes SET state = 'failed', attempts = attempts + 1, last_error = ?, retry = ? "
      "WHERE id = ?");
  s.Text(1, error).Int(2, retry ? 1 : 0).Int(3, probe_id).Run();
  c.TouchRun(run_id, c.Now());
  tx.Commit();
}

void RunDatabase::MarkProbeSkipped(std::int64_t probe_id, std::string_view reason) {
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  const auto [run_id, state] = c.ProbeRunAndState(probe_id);
  c.RequireProbeOpen(probe_id, state, "skip");
  Stmt s = c.Prepare("UPDATE probes SET state = 'skipped', skip_reason = ? WHERE id = ?");
  s.Text(1, reason).Int(2, probe_id).Run();
  c.TouchRun(run_id, c.Now());
  tx.Commit();
}

std::int64_t RunDatabase::SkipOpenProbes(std::int64_t run_id, std::string_view reason) {
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  c.RequireRun(run_id);
  Stmt s = c.Prepare(
      "UPDATE probes SET state = 'skipped', skip_reason = ? WHERE run_id = ? AND state IN "
      "('planned', 'failed')");
  s.Text(1, reason).Int(2, run_id).Run();
  const std::int64_t changed = c.Changes();
  c.TouchRun(run_id, c.Now());
  tx.Commit();
  return changed;
}

// ---- frames ----

std::int64_t RunDatabase::AddReferenceFrame(std::int64_t run_id, const EncodedFrame& frame,
                                            double timestamp) {
  RequireValidFrame(frame);
  RequireFinite(timestamp, "AddReferenceFrame timestamp");
  const std::string checksum = BlobChecksum(frame.png);
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  c.RequireRun(run_id);
  const std::int64_t id =
      c.InsertFrame(run_id, std::nullopt, FrameKind::kReference, timestamp, frame, checksum);
  c.TouchRun(run_id, c.Now());
  tx.Commit();
  return id;
}

std::int64_t RunDatabase::AddReferenceFrame(std::int64_t run_id, const cv::Mat& image,
                                            double timestamp) {
  return AddReferenceFrame(run_id, EncodeFrame(image, impl_->options().png), timestamp);
}

std::optional<FrameInfo> RunDatabase::GetFrameInfo(std::int64_t frame_id) const {
  return impl_->FrameInfoById(frame_id);
}

cv::Mat RunDatabase::LoadFrame(std::int64_t frame_id) const {
  const Impl& c = *impl_;
  auto [info, png] = c.LoadVerified(frame_id);
  cv::Mat image = DecodeFrame(png);
  if (image.empty()) {
    c.Throw(StorageErrc::kCorruptBlob,
            c.Describe(info) +
                ": the PNG blob does not decode (checksum matched: it was stored "
                "corrupt)");
  }
  const int expected_type = CV_MAKETYPE(info.bit_depth == 16 ? CV_16U : CV_8U, info.channels);
  if (image.cols != info.width || image.rows != info.height || image.type() != expected_type) {
    c.Throw(StorageErrc::kCorruptBlob,
            c.Describe(info) + ": decoded " + std::to_string(image.cols) + "x" +
                std::to_string(image.rows) + " " + cv::typeToString(image.type()) + ", stored as " +
                std::to_string(info.width) + "x" + std::to_string(info.height) + " " +
                cv::typeToString(expected_type));
  }
  return image;
}

std::vector<std::uint8_t> RunDatabase::LoadFramePng(std::int64_t frame_id) const {
  return impl_->LoadVerified(frame_id).second;
}

std::optional<FrameInfo> RunDatabase::LatestFrame(std::int64_t run_id,
                                                  std::optional<FrameKind> kind) const {
  if (kind) {
    Stmt s = impl_->Prepare("SELECT " GS360_FRAME_COLUMNS
                            " FROM frames WHERE run_id = ? AND kind = ? ORDER BY id DESC LIMIT 1");
    s.Int(1, run_id).Text(2, ToString(*kind));
    if (!s.Step()) return std::nullopt;
    return ReadFrameInfo(s);
  }
  Stmt s = impl_->Prepare("SELECT " GS360_FRAME_COLUMNS
                          " FROM frames WHERE run_id = ? ORDER BY id DESC LIMIT 1");
  s.Int(1, run_id);
  if (!s.Step()) return std::nullopt;
  return ReadFrameInfo(s);
}

std::vector<FrameInfo> RunDatabase::ListFrames(std::int64_t run_id, FrameKind kind) const {
  std::vector<FrameInfo> out;
  Stmt s = impl_->Prepare("SELECT " GS360_FRAME_COLUMNS
                          " FROM frames WHERE run_id = ? AND kind = ? ORDER BY timestamp, id");
  s.Int(1, run_id).Text(2, ToString(kind));
  while (s.Step()) out.push_back(ReadFrameInfo(s));
  return out;
}

std::optional<FrameInfo> RunDatabase::NearestReferenceFrame(std::int64_t run_id,
                                                            double timestamp) const {
  RequireFinite(timestamp, "NearestReferenceFrame timestamp");
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kRead);
  std::optional<FrameInfo> before, after;
  {
    Stmt s = c.Prepare("SELECT " GS360_FRAME_COLUMNS
                       " FROM frames WHERE run_id = ? AND kind = 'reference' AND timestamp <= ? "
                       "ORDER BY timestamp DESC, id DESC LIMIT 1");
    s.Int(1, run_id).Real(2, timestamp);
    if (s.Step()) before = ReadFrameInfo(s);
  }
  {
    Stmt s = c.Prepare("SELECT " GS360_FRAME_COLUMNS
                       " FROM frames WHERE run_id = ? AND kind = 'reference' AND timestamp > ? "
                       "ORDER BY timestamp, id LIMIT 1");
    s.Int(1, run_id).Real(2, timestamp);
    if (s.Step()) after = ReadFrameInfo(s);
  }
  tx.Commit();
  if (before && after) {
    return (timestamp - before->timestamp) <= (after->timestamp - timestamp) ? before : after;
  }
  return before ? before : after;
}

std::vector<CapturedProbe> RunDatabase::ListCapturedProbes(std::int64_t run_id) const {
  std::vector<CapturedProbe> out;
  Stmt s = impl_->Prepare("SELECT " GS360_PROBE_COLUMNS
                          ", f.id, f.timestamp FROM probes p JOIN frames f ON f.probe_id = p.id "
                          "WHERE p.run_id = ? AND p.state = 'captured' ORDER BY p.plan_index");
  s.Int(1, run_id);
  while (s.Step()) {
    CapturedProbe cp;
    cp.probe = ReadProbe(s);
    cp.frame_id = s.GetInt(kProbeColumnCount);
    cp.frame_time = s.GetReal(kProbeColumnCount + 1);
    out.push_back(std::move(cp));
  }
  return out;
}

// ---- status ----

RunStatus RunDatabase::GetRunStatus(std::int64_t run_id) const {
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kRead);
  RunStatus st;
  std::optional<RunRecord> run = c.Run(run_id);
  if (!run) c.Throw(StorageErrc::kNotFound, "no run with id " + std::to_string(run_id));
  st.run = std::move(*run);
  st.probes = c.Counts(run_id);
  {
    Stmt s = c.Prepare("SELECT count(*) FROM frames WHERE run_id = ? AND kind = 'reference'");
    s.Int(1, run_id);
    if (s.Step()) st.reference_frames = s.GetInt(0);
  }
  st.latest_frame = LatestFrame(run_id);
  st.elapsed_s = st.run.active_s;
  if (st.run.state == RunState::kRunning && st.run.running_since) {
    st.elapsed_s += std::max(0.0, c.Now() - *st.run.running_since);
  }
  tx.Commit();
  return st;
}

// ---- events ----

std::int64_t RunDatabase::AppendEvent(std::optional<std::int64_t> run_id, EventLevel level,
                                      std::string_view message, std::string_view data_json) {
  if (!data_json.empty()) RequireJson(data_json, "AppendEvent data_json");
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  if (run_id) c.RequireRun(*run_id);
  const std::int64_t id = c.AddEvent(run_id, level, message, data_json);
  tx.Commit();
  return id;
}

std::vector<EventRecord> RunDatabase::ListEvents(std::optional<std::int64_t> run_id,
                                                 std::int64_t after_id, int limit) const {
  std::vector<EventRecord> out;
  if (run_id) {
    Stmt s = impl_->Prepare("SELECT " GS360_EVENT_COLUMNS
                            " FROM events WHERE run_id = ? AND id > ? ORDER BY id LIMIT ?");
    s.Int(1, *run_id).Int(2, after_id).Int(3, limit);
    while (s.Step()) out.push_back(ReadEvent(s));
  } else {
    Stmt s = impl_->Prepare("SELECT " GS360_EVENT_COLUMNS
                            " FROM events WHERE id > ? ORDER BY id LIMIT ?");
    s.Int(1, after_id).Int(2, limit);
    while (s.Step()) out.push_back(ReadEvent(s));
  }
  return out;
}

// ---- artifacts ----

std::int64_t RunDatabase::PutArtifact(std::int64_t run_id, std::string_view stage,
                                      std::string_view input_hash,
                                      std::span<const std::uint8_t> blob,
                                      std::string_view metrics_json) {
  if (stage.empty()) throw std::invalid_argument("PutArtifact: stage is empty");
  if (input_hash.empty()) throw std::invalid_argument("PutArtifact: input_hash is empty");
  RequireJson(metrics_json, "PutArtifact metrics_json");
  const std::string checksum = BlobChecksum(blob);
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  c.RequireRun(run_id);
  Stmt s = c.Prepare(
      "INSERT INTO artifacts (run_id, stage, input_hash, created_at, metrics_json, size, "
      "checksum, blob) VALUES (?, ?, ?, ?, ?, ?, ?, ?) "
      "ON CONFLICT (run_id, stage, input_hash) DO UPDATE SET created_at = excluded.created_at, "
      "metrics_json = excluded.metrics_json, size = excluded.size, checksum = excluded.checksum, "
      "blob = excluded.blob RETURNING id");
  s.Int(1, run_id)
      .Text(2, stage)
      .Text(3, input_hash)
      .Real(4, c.Now())
      .Text(5, metrics_json)
      .Int(6, static_cast<std::int64_t>(blob.size()))
      .Text(7, checksum)
      .Blob(8, blob);
  if (!s.Step()) c.Throw(StorageErrc::kIo, "PutArtifact returned no id");
  const std::int64_t id = s.GetInt(0);
  s.Run();
  tx.Commit();
  return id;
}

std::optional<ArtifactRecord> RunDatabase::GetArtifact(std::int64_t run_id, std::string_view stage,
                                                       std::string_view input_hash) const {
  const Impl& c = *impl_;
  Stmt s = c.Prepare(
      "SELECT id, run_id, stage, input_hash, created_at, metrics_json, checksum, size, blob "
      "FROM artifacts WHERE run_id = ? AND stage = ? AND input_hash = ?");
  s.Int(1, run_id).Text(2, stage).Text(3, input_hash);
  if (!s.Step()) return std::nullopt;
  ArtifactRecord a;
  a.id = s.GetInt(0);
  a.run_id = s.GetInt(1);
  a.stage = s.GetText(2);
  a.input_hash = s.GetText(3);
  a.created_at = s.GetReal(4);
  a.metrics_json = s.GetText(5);
  a.checksum = s.GetText(6);
  a.size = s.GetInt(7);
  a.blob = s.GetBlob(8);
  const std::string actual = BlobChecksum(a.blob);
  if (actual != a.checksum || static_cast<std::int64_t>(a.blob.size()) != a.size) {
    c.Throw(StorageErrc::kCorruptBlob,
            "artifact " + std::to_string(a.id) + " (run " + std::to_string(run_id) + ", stage " +
                a.stage + ", input " + a.input_hash + "): checksum mismatch (stored " + a.checksum +
                ", read " + actual + ")");
  }
  return a;
}

std::vector<ArtifactRecord> RunDatabase::ListArtifacts(std::int64_t run_id) const {
  std::vector<ArtifactRecord> out;
  Stmt s = impl_->Prepare(
      "SELECT id, run_id, stage, input_hash, created_at, metrics_json, checksum, size "
      "FROM artifacts WHERE run_id = ? ORDER BY id");
  s.Int(1, run_id);
  while (s.Step()) {
    ArtifactRecord a;
    a.id = s.GetInt(0);
    a.run_id = s.GetInt(1);
    a.stage = s.GetText(2);
    a.input_hash = s.GetText(3);
    a.created_at = s.GetReal(4);
    a.metrics_json = s.GetText(5);
    a.checksum = s.GetText(6);
    a.size = s.GetInt(7);
    out.push_back(std::move(a));
  }
  return out;
}

// ---- models ----

std::int64_t RunDatabase::PutModel(std::string_view name, std::string_view version,
                                   std::span<const std::uint8_t> blob,
                                   std::string_view metadata_json,
                                   std::optional<std::int64_t> run_id) {
  if (name.empty()) throw std::invalid_argument("PutModel: name is empty");
  if (version.empty()) throw std::invalid_argument("PutModel: version is empty");
  RequireJson(metadata_json, "PutModel metadata_json");
  const std::string checksum = BlobChecksum(blob);
  const Impl& c = *impl_;
  Transaction tx(c, Transaction::kWrite);
  if (run_id) c.RequireRun(*run_id);
  {
    Stmt s = c.Prepare("SELECT id FROM models WHERE name = ? AND version = ?");
    s.Text(1, name).Text(2, version);
    if (s.Step()) {
      c.Throw(StorageErrc::kConflict, "model " + std::string(name) + " version " +
                                          std::string(version) + " already exists (id " +
                                          std::to_string(s.GetInt(0)) + ")");
    }
  }
  Stmt s = c.Prepare(
      "INSERT INTO models (run_id, name, version, created_at, metadata_json, size, checksum, "
      "blob) VALUES (?, ?, ?, ?, ?, ?, ?, ?)");
  s.OptInt(1, run_id)
      .Text(2, name)
      .Text(3, version)
      .Real(4, c.Now())
      .Text(5, metadata_json)
      .Int(6, static_cast<std::int64_t>(blob.size()))
      .Text(7, checksum)
      .Blob(8, blob)
      .Run();
  const std::int64_t id = c.LastInsertId();
  tx.Commit();
  return id;
}

std::optional<ModelRecord> RunDatabase::GetModel(std::string_view name,
                                                 std::string_view version) const {
  const Impl& c = *impl_;
  Stmt s = c.Prepare(
      "SELECT id, run_id, name, version, created_at, metadata_json, checksum, size, blob "
      "FROM models WHERE name = ? AND version = ?");
  s.Text(1, name).Text(2, version);
  if (!s.Step()) return std::nullopt;
  ModelRecord m;
  m.id = s.GetInt(0);
  m.run_id = s.GetOptInt(1);
  m.name = s.GetText(2);
  m.version = s.GetText(3);
  m.created_at = s.GetReal(4);
  m.metadata_json = s.GetText(5);
  m.checksum = s.GetText(6);
  m.size = s.GetInt(7);
  m.blob = s.GetBlob(8);
  const std::string actual = BlobChecksum(m.blob);
  if (actual != m.checksum || static_cast<std::int64_t>(m.blob.size()) != m.size) {
    c.Throw(StorageErrc::kCorruptBlob, "model " + m.name + " version " + m.version + " (id " +
                                           std::to_string(m.id) + "): checksum mismatch (stored " +
                                           m.checksum + ", read " + actual + ")");
  }
  return m;
}

std::vector<ModelRecord> RunDatabase::ListModels() const {
  std::vector<ModelRecord> out;
  Stmt s = impl_->Prepare(
      "SELECT id, run_id, name, version, created_at, metadata_json, checksum, size "
      "FROM models ORDER BY id");
  while (s.Step()) {
    ModelRecord m;
    m.id = s.GetInt(0);
    m.run_id = s.GetOptInt(1);
    m.name = s.GetText(2);
    m.version = s.GetText(3);
    m.created_at = s.GetReal(4);
    m.metadata_json = s.GetText(5);
    m.checksum = s.GetText(6);
    m.size = s.GetInt(7);
    out.push_back(std::move(m));
  }
  return out;
}

// ---- maintenance ----

std::vector<std::string> RunDatabase::IntegrityCheck() const {
  std::vector<std::string> rows;
  Stmt s = impl_->Prepare("PRAGMA integrity_check");
  while (s.Step()) rows.push_back(s.GetText(0));
  if (rows.size() == 1 && rows[0] == "ok") rows.clear();
  return rows;
}

}  // namespace gs360
