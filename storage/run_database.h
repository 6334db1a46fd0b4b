#pragma once
// The run database: one SQLite file per daemon holding runs, their probe plans, captured frames,
// calibration artifacts, exported models and a run log.
//
// Durability: WAL journal, foreign keys on, a busy timeout, schema version in user_version with
// forward migrations on open (storage/schema.h), 16 KiB pages for new files (frames are large
// blobs). Every mutating call is one transaction: it either happens completely or not at all,
// also when the process is killed or the disk fills up.
// In particular CommitCapture() writes the frame, the reported machine position and the probe's
// new state together, so a probe marked captured always has its frame.
//
// Threads and processes: one RunDatabase object is one SQLite connection and must be used from
// one thread at a time (it is movable, not copyable). For concurrent access open the same file
// from several objects, e.g. the run engine's writer plus a status reader per API thread; in WAL
// mode readers see the last committed state and never block the writer, and writers from several
// objects or processes serialise on the write lock (waiting up to busy_timeout_ms).
//
// Units and frames: positions in mm. A probe's point and normal are in the sensor frame; its
// approach / press / retract positions and the reported position (GRBL MPos) are in the machine
// frame. Times are seconds; stored timestamps (created_at, captured_at, events) come from
// RunDatabaseOptions::clock (Unix time by default). Frame and sync times are the caller's and
// must come from one clock (Unix time recommended) so that they compare with each other.
//
// Errors: StorageError (storage/storage_error.h) with a StorageErrc code for every I/O, SQLite
// and data problem, its message naming the database file; std::invalid_argument for bad
// arguments (non-finite numbers, malformed JSON, bad options). Expected outcomes (no pending
// probe, no such artifact) are std::optional.

#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core/mat.hpp>

#include "storage/frame_codec.h"
#include "storage/storage_error.h"

namespace gs360 {

// What a power cut may cost (a process crash or SIGKILL loses nothing committed in either mode):
// - kNormal: WAL + synchronous=NORMAL never corrupts the file but can lose the last few commits
//   (those not yet checkpointed or synced), so some captured probes would be probed again.
// - kFull (default): every commit is synced to the WAL before it returns; nothing committed is
//   lost. It costs one fsync per commit, small against a press (docs/benchmarks.md has both),
//   and the overnight run's promise is "resume losing nothing".
enum class SyncMode { kNormal, kFull };

struct RunDatabaseOptions {
  // How long a write waits for another connection's write lock before StorageErrc::kBusy.
  int busy_timeout_ms = 5000;
  SyncMode synchronous = SyncMode::kFull;
  // Used by the cv::Mat overloads of CommitCapture / AddReferenceFrame.
  PngOptions png;
  // Open without write access (status readers on another thread or process). The file must
  // already be a gs360 database at the current schema version.
  bool read_only = false;
  // Create the file if it does not exist (ignored when read_only).
  bool create = true;
  // Cap on the database size in pages (PRAGMA max_page_count, this connection only); 0 keeps
  // SQLite's default. For tests of the disk-full path.
  std::int64_t max_page_count = 0;
  // Wall clock for stored timestamps, Unix seconds; empty means std::chrono::system_clock.
  std::function<double()> clock;

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

enum class RunState { kCreated, kRunning, kPaused, kInterrupted, kDone, kFailed, kCancelled };
enum class ProbeState { kPlanned, kCaptured, kFailed, kSkipped };
enum class FrameKind { kPress, kReference };
enum class EventLevel { kDebug, kInfo, kWarning, kError };

std::string_view ToString(RunState s);
std::string_view ToString(ProbeState s);
std::string_view ToString(FrameKind k);
std::string_view ToString(EventLevel l);
// Parse the strings above; std::nullopt for anything else.
std::optional<RunState> ParseRunState(std::string_view s);
std::optional<ProbeState> ParseProbeState(std::string_view s);
std::optional<EventLevel> ParseEventLevel(std::string_view s);
// done, failed and cancelled are terminal: a run in them never changes state again.
bool IsTerminal(RunState s);

struct RunRecord {
  std::int64_t id = 0;
  std::string name;
  std::string config_json;
  std::string mesh_hash;
  RunState state = RunState::kCreated;
  double created_at = 0;
  std::optional<double> started_at;   // first time the run entered kRunning
  double updated_at = 0;              // last state change or probe commit
  std::optional<double> finished_at;  // when it entered a terminal state
  // Seconds spent in kRunning, up to the last time it left that state.
  double active_s = 0;
  std::optional<double> running_since;  // set while the state is kRunning
  // Why the run last stopped short (an alarm, a set-up that failed); cleared when it next enters
  // kRunning. Empty if none.
  std::string last_error;
  // What the run waits for the user to confirm before it goes on ("position", "sensor"), with
  // the reason in last_error; cleared when it next enters kRunning. Empty if nothing.
  std::string awaiting;
  // The last motion it sent: where it started, then each target (machine frame, MPos, mm);
  // empty before the first.
  std::vector<Eigen::Vector3d> commanded_path;
  // A homing cycle ($H) was sent after that motion, and no motion since: the tool may stand
  // anywhere between the path's end and the machine's home.
  bool homing_sent = false;
};

// One planned probe, as the planner emits it.
struct ProbePlanEntry {
  Eigen::Vector3d point_sensor = Eigen::Vector3d::Zero();    // surface point, sensor frame
  Eigen::Vector3d normal_sensor = Eigen::Vector3d::UnitZ();  // outward unit normal, sensor frame
  Eigen::Vector3d approach_machine = Eigen::Vector3d::Zero();
  Eigen::Vector3d press_machine = Eigen::Vector3d::Zero();
  Eigen::Vector3d retract_machine = Eigen::Vector3d::Zero();
};

struct ProbeRecord {
  std::int64_t id = 0;
  std::int64_t run_id = 0;
  int plan_index = 0;
  ProbePlanEntry plan;
  ProbeState state = ProbeState::kPlanned;
  int attempts = 0;
  std::optional<Eigen::Vector3d> machine_position;  // reported MPos at the press (captured)
  std::optional<double> sync_time;                  // when the G4 `ok` arrived (captured)
  std::optional<double> captured_at;                // commit time (captured)
  std::string last_error;                           // of the last failed attempt, else empty
  std::string skip_reason;                          // for kSkipped
  bool retry = true;  // false: failed for a reason a second press cannot change
};

// What the run engine reports with a press frame.
struct CaptureReport {
  Eigen::Vector3d machine_position = Eigen::Vector3d::Zero();  // GRBL MPos, machine frame, mm
  double sync_time = 0;                                        // time the sync `ok` (G4) arrived
  double frame_time = 0;  // capture time of the (averaged) frame; must be >= sync_time
};

struct FrameInfo {
  std::int64_t id = 0;
  std::int64_t run_id = 0;
  std::optional<std::int64_t> probe_id;  // press frames only
  FrameKind kind = FrameKind::kPress;
  double timestamp = 0;
  int width = 0;
  int height = 0;
  int channels = 0;
  int bit_depth = 0;
  std::int64_t png_bytes = 0;
  std::string checksum;
};

struct CapturedProbe {
  ProbeRecord probe;
  std::int64_t frame_id = 0;
  double frame_time = 0;
};

struct ProbeCounts {
  std::int64_t total = 0;
  std::int64_t planned = 0;
  std::int64_t captured = 0;
  std::int64_t failed = 0;
  std::int64_t skipped = 0;
};

struct RunStatus {
  RunRecord run;
  ProbeCounts probes;
  std::int64_t reference_frames = 0;
  // Time spent running: active_s plus, while running, the time since running_since.
  double elapsed_s = 0;
  std::optional<FrameInfo> latest_frame;  // of any kind
};

struct EventRecord {
  std::int64_t id = 0;
  std::optional<std::int64_t> run_id;
  double timestamp = 0;
  EventLevel level = EventLevel::kInfo;
  std::string message;
  std::string data_json;  // empty if none
};

struct ArtifactRecord {
  std::int64_t id = 0;
  std::int64_t run_id = 0;
  std::string stage;
  std::string input_hash;
  double created_at = 0;
  std::string metrics_json;
  std::string checksum;
  std::int64_t size = 0;
  std::vector<std::uint8_t> blob;  // empty in listings
};

struct ModelRecord {
  std::int64_t id = 0;
  std::optional<std::int64_t> run_id;
  std::string name;
  std::string version;
  double created_at = 0;
  std::string metadata_json;
  std::string checksum;
  std::int64_t size = 0;
  std::vector<std::uint8_t> blob;  // empty in listings
};

class RunDatabase {
 public:
  // Opens (creating if allowed) and migrates the database. Throws StorageError: kCannotOpen,
  // kNotADatabase, kForeignDatabase, kNewerSchema, kReadOnly (read-only file or directory, or a
  // read-only open of a database that needs migrating), kBusy, kIo; std::invalid_argument for
  // bad options. A file that is refused is left untouched.
  explicit RunDatabase(const std::filesystem::path& path, RunDatabaseOptions options = {});
  ~RunDatabase();
  RunDatabase(RunDatabase&&) noexcept;
  RunDatabase& operator=(RunDatabase&&) noexcept;
  RunDatabase(const RunDatabase&) = delete;
  RunDatabase& operator=(const RunDatabase&) = delete;

  const std::filesystem::path& path() const;
  const RunDatabaseOptions& options() const;
  int schema_version() const;

  // ---- runs ----
  // config_json must be valid JSON (std::invalid_argument otherwise). State kCreated.
  std::int64_t CreateRun(std::string_view config_json, std::string_view mesh_hash,
                         std::string_view name = "");
  std::optional<RunRecord> GetRun(std::int64_t run_id) const;
  std::vector<RunRecord> ListRuns() const;  // by id
  // Changes the run's state and appends an event saying so, in one transaction. Allowed:
  // created -> running/cancelled/failed; running -> paused/interrupted/done/failed/cancelled;
  // paused -> running/interrupted/failed/cancelled; interrupted -> running/failed/cancelled.
  // Setting the current state again is a no-op. Leaving kRunning adds the time since
  // running_since to active_s; for kInterrupted (a daemon that died) the run's last activity,
  // updated_at, is taken as the end. Throws kNotFound, kInvalidState.
  void SetRunState(std::int64_t run_id, RunState state);
  // Records why the run stopped short (RunRecord::last_error) with an error event, in one
  // transaction. Throws kNotFound.
  void SetRunError(std::int64_t run_id, std::string_view message);
  // As SetRunError, and the run waits for the user to confirm `what` (RunRecord::awaiting).
  void SetRunAwaiting(std::int64_t run_id, std::string_view what, std::string_view message);
  // The last motion the run sent (RunRecord::commanded_path). Throws std::invalid_argument for a
  // non-finite position, kNotFound.
  // Also clears RunRecord::homing_sent: the path is the newest motion.
  void SetCommandedPath(std::int64_t run_id, std::span<const Eigen::Vector3d> path);
  // Records a homing cycle about to be sent (RunRecord::homing_sent). Throws kNotFound.
  void MarkHomingSent(std::int64_t run_id);
  // Removes the run and everything of it (probes, frames, events, artifacts; its models stay,
  // detached). Its id is never given to another run. Throws kNotFound, kInvalidState while it is
  // kRunning.
  void DeleteRun(std::int64_t run_id);

  // ---- plan and probes ----
  // Inserts the whole plan in one transaction, plan_index = position in `plan`; returns the probe
  // ids in plan order. Throws kInvalidState if the run already has probes, kNotFound,
  // std::invalid_argument for a non-finite coordinate (naming the plan index).
  std::vector<std::int64_t> InsertPlan(std::int64_t run_id, std::span<const ProbePlanEntry> plan);
  std::optional<ProbeRecord> GetProbe(std::int64_t probe_id) const;
  std::optional<ProbeRecord> GetProbeByIndex(std::int64_t run_id, int plan_index) const;
  // All probes of a run in plan order, optionally only those in `state`.
  std::vector<ProbeRecord> ListProbes(std::int64_t run_id,
                                      std::optional<ProbeState> state = std::nullopt) const;
  // For resume: the first probe in plan order that is kPlanned, or kFailed with fewer than
  // `max_attempts` attempts and not failed with retry false, other than probe id `except` (a probe
  // whose capture is being committed on another connection); std::nullopt when none is left.
  std::optional<ProbeRecord> NextPendingProbe(std::int64_t run_id, int max_attempts = 1,
                                              std::optional<std::int64_t> except = {}) const;
  ProbeCounts CountProbes(std::int64_t run_id) const;

  // Commits one press in one transaction: the frame (kind press), the reported position and sync
  // time, state captured, attempts + 1. The probe must be kPlanned or kFailed (kInvalidState
  // otherwise: a captured probe is never captured again). Returns the frame id. Throws kNotFound,
  // kInvalidState, kDiskFull (nothing written), std::invalid_argument (non-finite position,
  // frame_time < sync_time, empty frame).
  std::int64_t CommitCapture(std::int64_t probe_id, const EncodedFrame& frame,
                             const CaptureReport& report);
  // Same, encoding `image` (see EncodeFrame) with options().png before the transaction starts.
  std::int64_t CommitCapture(std::int64_t probe_id, const cv::Mat& image,
                             const CaptureReport& report);
  // A failed attempt: state failed, attempts + 1, last_error. Probe must not be captured.
  // `retry` false: NextPendingProbe never returns it again (the reason would not change).
  void MarkProbeFailed(std::int64_t probe_id, std::string_view error, bool retry = true);
  // Deliberately not probed: state skipped with the reason. Probe must not be captured.
  void MarkProbeSkipped(std::int64_t probe_id, std::string_view reason);
  // Every probe of the run not captured (planned or failed) skipped with `reason`, in one
  // transaction; returns how many. For a run that ends before its plan (it has converged).
  std::int64_t SkipOpenProbes(std::int64_t run_id, std::string_view reason);

  // ---- frames ----
  // A no-contact reference frame (kind reference, no probe). Returns the frame id.
  std::int64_t AddReferenceFrame(std::int64_t run_id, const EncodedFrame& frame, double timestamp);
  std::int64_t AddReferenceFrame(std::int64_t run_id, const cv::Mat& image, double timestamp);
  std::optional<FrameInfo> GetFrameInfo(std::int64_t frame_id) const;
  // Decoded frame, checksum verified. Throws kNotFound, kCorruptBlob (checksum mismatch, PNG
  // that does not decode or does not match its stored size/type; the message names the file,
  // the frame id and the probe).
  cv::Mat LoadFrame(std::int64_t frame_id) const;
  // The stored PNG bytes, checksum verified (e.g. to serve to a browser). Throws as LoadFrame.
  std::vector<std::uint8_t> LoadFramePng(std::int64_t frame_id) const;
  // Latest frame (highest id) of the run, optionally of one kind.
  std::optional<FrameInfo> LatestFrame(std::int64_t run_id,
                                       std::optional<FrameKind> kind = std::nullopt) const;
  std::vector<FrameInfo> ListFrames(std::int64_t run_id, FrameKind kind) const;  // by timestamp
  // The reference frame whose timestamp is nearest to `timestamp` (the earlier one on a tie).
  std::optional<FrameInfo> NearestReferenceFrame(std::int64_t run_id, double timestamp) const;
  // Captured probes in plan order, with their press frame ids.
  std::vector<CapturedProbe> ListCapturedProbes(std::int64_t run_id) const;

  // ---- status ----
  // One consistent snapshot (read transaction). Throws kNotFound.
  RunStatus GetRunStatus(std::int64_t run_id) const;

  // ---- events (run log) ----
  // data_json is empty or valid JSON. run_id may be empty for daemon-wide events.
  std::int64_t AppendEvent(std::optional<std::int64_t> run_id, EventLevel level,
                           std::string_view message, std::string_view data_json = "");
  // Events with id > after_id, oldest first, at most `limit`; of one run, or all if empty.
  std::vector<EventRecord> ListEvents(std::optional<std::int64_t> run_id, std::int64_t after_id = 0,
                                      int limit = 1000) const;

  // ---- calibration artifacts, keyed (run, stage, input_hash) ----
  // Inserts or replaces the artifact for the key. metrics_json: valid JSON. Returns its id.
  std::int64_t PutArtifact(std::int64_t run_id, std::string_view stage, std::string_view input_hash,
                           std::span<const std::uint8_t> blob,
                           std::string_view metrics_json = "{}");
  // With the blob, checksum verified (kCorruptBlob otherwise); std::nullopt if the key is absent.
  std::optional<ArtifactRecord> GetArtifact(std::int64_t run_id, std::string_view stage,
                                            std::string_view input_hash) const;
  std::vector<ArtifactRecord> ListArtifacts(std::int64_t run_id) const;  // without blobs

  // ---- exported models ----
  // Stores a model bundle; (name, version) is unique (kConflict if it exists). Returns its id.
  std::int64_t PutModel(std::string_view name, std::string_view version,
                        std::span<const std::uint8_t> blob, std::string_view metadata_json = "{}",
                        std::optional<std::int64_t> run_id = std::nullopt);
  // With the blob, checksum verified; std::nullopt if absent.
  std::optional<ModelRecord> GetModel(std::string_view name, std::string_view version) const;
  std::vector<ModelRecord> ListModels() const;  // without blobs, by id

  // ---- maintenance ----
  // PRAGMA integrity_check: empty if the file is sound, else SQLite's findings.
  std::vector<std::string> IntegrityCheck() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace gs360
