#pragma once
// Until converged (docs/running.md, "Until converged"): a run that calibrates itself at the end
// of each round of probes (plan.checkpoint_probes, in the farthest-point order that covers the
// surface at every prefix), in the background while the machine goes on, and ends once the
// held-out error meets every target and has stopped improving (ConvergeConfig).
//
// A checkpoint is one calibration of the probes below a round's end in plan order. The curve
// (every checkpoint and the last verdict) is stored in the run's database as an artifact after
// each checkpoint: a restarted daemon goes on from it, and the report draws it.

#include <cstdint>
#include <filesystem>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "run/run_config.h"
#include "run/run_engine.h"
#include "storage/run_database.h"

namespace gs360 {

class CalibrationJobs;
class EventHub;

// The artifact holding a run's curve: (run, kConvergenceStage, kConvergenceKey), JSON.
inline constexpr const char* kConvergenceStage = "convergence";
inline constexpr const char* kConvergenceKey = "curve";

struct Checkpoint {
  int plan_index_limit = 0;  // the probes below this plan index
  std::int64_t probes = 0;   // captured probes the calibration used
  std::string state;         // "done" or "failed"
  std::string error;         // why it failed
  // ValidationTargets() of its validation (calib/report.h): {"name", "value", "target", "pass",
  // ...} each; empty when it failed.
  nlohmann::json targets = nlohmann::json::array();
  double seconds = 0.0;      // the calibration's wall time
  double finished_at = 0.0;  // Unix seconds

  bool TargetsMet() const;
  // A target's value by name ("mean depth error", ...); nullopt when absent or unknown.
  std::optional<double> Value(const std::string& name) const;
  nlohmann::json ToJson() const;
  static Checkpoint FromJson(const nlohmann::json& json);
};

struct ConvergenceCurve {
  std::vector<Checkpoint> checkpoints;
  bool converged = false;
  std::string verdict;  // the last judgement, one sentence
  nlohmann::json ToJson() const;
  // Tolerant of a damaged artifact: what cannot be read is left out.
  static ConvergenceCurve FromJson(const nlohmann::json& json);
};

struct Verdict {
  bool converged = false;
  std::string reason;
};

// The stop rule: the last two checkpoints both done and meeting every target, and the last one
// improving on the one before by less than config.min_improvement in both the mean and the
// > 50 deg band error (relative; an error that grew counts as no improvement).
Verdict Judge(const std::vector<Checkpoint>& curve, const ConvergeConfig& config);

// A checkpoint from a finished calibration job's view (CalibrationJobs::View).
Checkpoint CheckpointFromCalibration(const nlohmann::json& view, int plan_index_limit);

// The run's stored curve (empty when it has none). Never throws for a damaged one.
ConvergenceCurve LoadConvergenceCurve(const RunDatabase& db, std::int64_t run_id);
void StoreConvergenceCurve(RunDatabase& db, std::int64_t run_id, const ConvergenceCurve& curve);

// The daemon's side: follows the run that moves, starts its checkpoint calibrations on the
// daemon's calibration thread when the machine has passed a round's end, records each one, and
// says when the run is to finish. Threads: every method may be called from any thread.
class ConvergenceWatch {
 public:
  ConvergenceWatch(std::filesystem::path database, std::filesystem::path checkerboards,
                   CalibrationJobs& jobs, EventHub& hub);

  // The event pump's tick (every 200 ms): `active_run` the run moving the machine (0: none) and
  // its progress. Returns the run to finish (RunEngine::RequestFinish) with the reason, or 0.
  struct Action {
    std::int64_t finish_run = 0;
    std::string reason;
  };
  Action Tick(std::int64_t active_run, const RunProgress& progress);
  // True while a checkpoint calibration of `run_id` runs (the run may then be resumed).
  bool Calibrating(std::int64_t run_id) const;
  // The run's convergence for its view: {"enabled", "checkpoint_probes", "min_improvement",
  // "state" (probing, calibrating, converged, not_converged), "verdict", "checkpoints"}; nullopt
  // for a run that does not converge.
  std::optional<nlohmann::json> View(const RunDatabase& db, std::int64_t run_id) const;

 private:
  void Track(std::int64_t run_id);
  void RecordPending(RunDatabase& db);
  void StartCheckpoint(RunDatabase& db, int plan_index_limit, const std::string& what);
  // The round end to calibrate at now (0: none): the latest one the machine has passed with a
  // probe to spare (the committer may still hold the probe before it).
  int DueRoundEnd(const RunProgress& progress) const;
  // A run that is done (its whole plan probed, or finished once converged) and has captured
  // probes its last checkpoint did not use: `captured` its captured probes.
  bool WholeRunDue(const RunRecord& run, std::int64_t captured) const;

  std::filesystem::path database_;
  std::filesystem::path checkerboards_;
  CalibrationJobs& jobs_;
  EventHub& hub_;
  mutable std::mutex mutex_;
  std::int64_t run_id_ = 0;   // the run followed (0: none)
  std::int64_t ignored_ = 0;  // the moving run, known not to converge
  ConvergeConfig config_;
  int round_ = 0;        // probes per round
  int plan_probes_ = 0;  // the plan's probes
  ConvergenceCurve curve_;
  int pending_ = 0;  // the plan index limit of the checkpoint calibrating (0: none)
  bool finish_requested_ = false;
};

}  // namespace gs360
