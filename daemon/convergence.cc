#include "daemon/convergence.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <memory>

#include <spdlog/spdlog.h>

#include "base/format.h"
#include "calib/report.h"
#include "daemon/calibration_jobs.h"
#include "daemon/event_hub.h"
#include "run/calibration_inputs.h"

namespace gs360 {
namespace {

using Json = nlohmann::json;

double UnixNow() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

constexpr const char* kMean = "mean depth error";
constexpr const char* kBand = "depth error seen > 50 deg";

std::string Percent(double fraction) {
  return FormatFixed(100.0 * fraction, 1) + " %";
}

// (before - after) / before; an error that grew, or an unknown one, is no improvement.
double Improvement(std::optional<double> before, std::optional<double> after) {
  if (!before || !after || !(*before > 0.0)) return 0.0;
  return std::max(0.0, (*before - *after) / *before);
}

std::string Missed(const Checkpoint& c) {
  std::string out;
  for (const Json& t : c.targets) {
    if (t.value("pass", false)) continue;
    const Json& v = t["value"];
    out += (out.empty() ? "" : ", ") + t.value("name", std::string("?")) + " " +
           (v.is_number() ? FormatFixed(v.get<double>(), 4) : std::string("unknown")) + " > " +
           FormatFixed(t.value("target", 0.0), 3) + " " + t.value("unit", std::string());
  }
  return out;
}

}  // namespace

bool Checkpoint::TargetsMet() const {
  if (state != "done" || !targets.is_array() || targets.empty()) return false;
  return std::all_of(targets.begin(), targets.end(),
                     [](const Json& t) { return t.value("pass", false); });
}

std::optional<double> Checkpoint::Value(const std::string& name) const {
  if (!targets.is_array()) return std::nullopt;
  for (const Json& t : targets) {
    if (t.value("name", std::string()) == name && t.contains("value") && t["value"].is_number()) {
      return t["value"].get<double>();
    }
  }
  return std::nullopt;
}

Json Checkpoint::ToJson() const {
  return {{"plan_index_limit", plan_index_limit},
          {"probes", probes},
          {"state", state},
          {"error", error},
          {"targets", targets},
          {"targets_met", TargetsMet()},
          {"seconds", seconds},
          {"finished_at", finished_at}};
}

Checkpoint Checkpoint::FromJson(const Json& j) {
  Checkpoint c;
  if (!j.is_object()) return c;
  c.plan_index_limit = j.value("plan_index_limit", 0);
  c.probes = j.value("probes", std::int64_t{0});
  c.state = j.value("state", std::string());
  c.error = j.value("error", std::string());
  if (j.contains("targets") && j["targets"].is_array()) c.targets = j["targets"];
  c.seconds = j.value("seconds", 0.0);
  c.finished_at = j.value("finished_at", 0.0);
  return c;
}

Json ConvergenceCurve::ToJson() const {
  Json list = Json::array();
  for (const Checkpoint& c : checkpoints) list.push_back(c.ToJson());
  return {{"checkpoints", list}, {"converged", converged}, {"verdict", verdict}};
}

ConvergenceCurve ConvergenceCurve::FromJson(const Json& j) {
  ConvergenceCurve curve;
  if (!j.is_object()) return curve;
  if (j.contains("checkpoints") && j["checkpoints"].is_array()) {
    for (const Json& c : j["checkpoints"]) {
      if (c.is_object()) curve.checkpoints.push_back(Checkpoint::FromJson(c));
    }
  }
  curve.converged = j.value("converged", false);
  curve.verdict = j.value("verdict", std::string());
  return curve;
}

Verdict Judge(const std::vector<Checkpoint>& curve, const ConvergeConfig& config) {
  if (curve.empty()) return {false, "no checkpoint yet"};
  const Checkpoint& last = curve.back();
  const std::string at = std::to_string(last.probes) + " probes";
  if (last.state != "done") return {false, "the checkpoint at " + at + " failed: " + last.error};
  if (!last.TargetsMet()) return {false, "at " + at + " the model misses: " + Missed(last)};
  if (curve.size() < 2 || !curve[curve.size() - 2].TargetsMet()) {
    return {false, "every target met at " + at +
                       " for the first time; one more round shows whether the error still falls"};
  }
  const Checkpoint& prev = curve[curve.size() - 2];
  const double gain = std::max(Improvement(prev.Value(kMean), last.Value(kMean)),
                               Improvement(prev.Value(kBand), last.Value(kBand)));
  if (gain >= config.min_improvement) {
    return {false, "every target met at " + at + ", still improving (" + Percent(gain) + " since " +
                       std::to_string(prev.probes) + " probes)"};
  }
  return {true, "converged at " + at + ": every target met at " + std::to_string(prev.probes) +
                    " and " + at + ", and the error improved by " + Percent(gain) + " (less than " +
                    Percent(config.min_improvement) + ")"};
}

Checkpoint CheckpointFromCalibration(const Json& view, int plan_index_limit) {
  Checkpoint c;
  c.plan_index_limit = plan_index_limit;
  c.state = view.value("state", std::string()) == "done" ? "done" : "failed";
  c.error = view.value("error", std::string());
  if (c.state != "done" && c.error.empty()) c.error = "the calibration ended without a model";
  const Json& validation = view.contains("validation") ? view["validation"] : Json();
  if (c.state == "done" && validation.is_object()) {
    c.targets = ValidationTargets(validation);
    c.probes = validation.value("probes_captured", std::int64_t{0});
  }
  const double started = view.value("started_at", 0.0);
  const Json& finished = view.contains("finished_at") ? view["finished_at"] : Json();
  c.finished_at = finished.is_number() ? finished.get<double>() : UnixNow();
  c.seconds = started > 0.0 ? std::max(0.0, c.finished_at - started) : 0.0;
  return c;
}

ConvergenceCurve LoadConvergenceCurve(const RunDatabase& db, std::int64_t run_id) {
  try {
    const auto artifact = db.GetArtifact(run_id, kConvergenceStage, kConvergenceKey);
    if (!artifact) return {};
    const std::string text(artifact->blob.begin(), artifact->blob.end());
    return ConvergenceCurve::FromJson(Json::parse(text, nullptr, false));
  } catch (const std::exception& e) {
    spdlog::warn("run {}: convergence curve unreadable: {}", run_id, e.what());
    return {};
  }
}

void StoreConvergenceCurve(RunDatabase& db, std::int64_t run_id, const ConvergenceCurve& curve) {
  const std::string text = curve.ToJson().dump();
  db.PutArtifact(run_id, kConvergenceStage, kConvergenceKey,
                 std::span(reinterpret_cast<const std::uint8_t*>(text.data()), text.size()));
}

ConvergenceWatch::ConvergenceWatch(std::filesystem::path database,
                                   std::filesystem::path checkerboards, CalibrationJobs& jobs,
                                   EventHub& hub)
    : database_(std::move(database)),
      checkerboards_(std::move(checkerboards)),
      jobs_(jobs),
      hub_(hub) {}

void ConvergenceWatch::Track(std::int64_t run_id) {
  run_id_ = 0;
  pending_ = 0;
  finish_requested_ = false;
  curve_ = {};
  RunDatabase db(database_, RunDatabaseOptions{.read_only = true});
  RunConfig config;
  try {
    config = StoredRunConfig(db, run_id);
  } catch (const std::exception& e) {
    // Said once: the run is then left alone (it cannot have been created to converge).
    spdlog::warn("run {}: stored configuration unreadable, not followed: {}", run_id, e.what());
    return;
  }
  if (!config.converge.enabled) return;
  run_id_ = run_id;
  config_ = config.converge;
  round_ =
      config.plan.checkpoint_probes > 0 ? config.plan.checkpoint_probes : kDefaultConvergeRound;
  plan_probes_ = static_cast<int>(db.CountProbes(run_id).total);
  curve_ = LoadConvergenceCurve(db, run_id);
}

int ConvergenceWatch::DueRoundEnd(const RunProgress& progress) const {
  if (progress.plan_index < 2) return 0;
  const int end = (progress.plan_index - 1) / round_ * round_;
  const int last = curve_.checkpoints.empty() ? 0 : curve_.checkpoints.back().plan_index_limit;
  // A round's end within half a round of the plan's: the whole-run checkpoint comes soon.
  if (plan_probes_ - end < round_ / 2) return 0;
  return end > last ? end : 0;
}

void ConvergenceWatch::StartCheckpoint(RunDatabase& db, int limit, const std::string& what) {
  CalibrationOptions options;
  options.plan_index_limit = limit;
  std::int64_t busy = 0;
  try {
    CalibrationInputs inputs = CalibrationInputsFor(db, run_id_, checkerboards_);
    for (const Checkpoint& c : curve_.checkpoints) {
      if (c.state != "done") continue;
      const auto mean = c.Value(kMean), band = c.Value(kBand);
      inputs.convergence.push_back({{"probes", c.probes},
                                    {"mean_mm", mean ? Json(*mean) : Json(nullptr)},
                                    {"band50_mm", band ? Json(*band) : Json(nullptr)},
                                    {"targets_met", c.TargetsMet()}});
    }
    if (!jobs_.Start(run_id_, inputs, options, &busy)) return;  // another job: next tick
  } catch (const std::exception& e) {
    Checkpoint failed;
    failed.plan_index_limit = limit;
    failed.state = "failed";
    failed.error = e.what();
    failed.finished_at = UnixNow();
    curve_.checkpoints.push_back(failed);
    curve_.verdict = Judge(curve_.checkpoints, config_).reason;
    StoreConvergenceCurve(db, run_id_, curve_);
    db.AppendEvent(run_id_, EventLevel::kWarning, "checkpoint calibration failed: " + failed.error);
    return;
  }
  pending_ = limit;
  db.AppendEvent(run_id_, EventLevel::kInfo,
                 "checkpoint: calibrating " + what + " in the background (plan index < " +
                     std::to_string(limit) + ")");
}

void ConvergenceWatch::RecordPending(RunDatabase& db) {
  const auto view = jobs_.View(run_id_);
  Checkpoint c = CheckpointFromCalibration(view ? *view : Json::object(), pending_);
  pending_ = 0;
  curve_.checkpoints.push_back(c);
  // Converged stays converged: a checkpoint on the whole run after the verdict only adds probes.
  const bool was_converged = curve_.converged;
  const Verdict verdict = Judge(curve_.checkpoints, config_);
  if (!was_converged) {
    curve_.converged = verdict.converged;
    curve_.verdict = verdict.reason;
  }
  StoreConvergenceCurve(db, run_id_, curve_);
  std::string figures;
  if (c.state == "done") {
    figures = "mean " + FormatFixed(c.Value(kMean).value_or(NAN), 4) + " mm, > 50 deg " +
              FormatFixed(c.Value(kBand).value_or(NAN), 4) + " mm; ";
  }
  db.AppendEvent(
      run_id_, c.state == "done" ? EventLevel::kInfo : EventLevel::kWarning,
      "checkpoint at " + std::to_string(c.probes) + " probes (" + FormatDuration(c.seconds) +
          "): " + figures +
          (was_converged ? "the model now takes in every probe of the run" : verdict.reason));
  hub_.Publish("convergence", {{"run", run_id_},
                               {"checkpoint", c.ToJson()},
                               {"converged", curve_.converged},
                               {"verdict", curve_.verdict}});
}

ConvergenceWatch::Action ConvergenceWatch::Tick(std::int64_t active_run,
                                                const RunProgress& progress) {
  std::lock_guard lock(mutex_);
  // Opened only when there is something to read or write: most ticks have nothing to do.
  std::unique_ptr<RunDatabase> open;
  const auto db = [&]() -> RunDatabase& {
    if (!open) open = std::make_unique<RunDatabase>(database_);
    return *open;
  };
  // A checkpoint is recorded before anything else, even when another run has started since.
  if (pending_ != 0) {
    if (jobs_.Running() == run_id_) return {};
    RecordPending(db());
  }
  if (active_run != 0 && active_run != run_id_ && active_run != ignored_) {
    Track(active_run);
    ignored_ = run_id_ == 0 ? active_run : 0;
  }
  if (run_id_ == 0) return {};
  const bool moving = active_run == run_id_;
  if (moving && curve_.converged) {
    if (finish_requested_) return {};
    finish_requested_ = true;
    return {run_id_, curve_.verdict};
  }
  if (jobs_.Running() != 0) return {};
  if (moving) {
    if (const int end = DueRoundEnd(progress); end > 0) {
      StartCheckpoint(db(), end, "the first " + std::to_string(end / round_) + " rounds");
    }
    return {};
  }
  // The run stopped. One that probed its whole plan (it did not converge, or its verdict came
  // after its last probe) gets a last checkpoint on all of it: the model then uses every probe.
  const auto run = db().GetRun(run_id_);
  if (run && WholeRunDue(*run, db().CountProbes(run_id_).captured)) {
    StartCheckpoint(db(), plan_probes_, "the whole run");
  } else {
    run_id_ = 0;  // nothing more to do until it moves again
  }
  return {};
}

bool ConvergenceWatch::WholeRunDue(const RunRecord& run, std::int64_t captured) const {
  if (run.state != RunState::kDone) return false;
  if (curve_.checkpoints.empty()) return captured > 0;
  const Checkpoint& last = curve_.checkpoints.back();
  // A converged run goes on probing while its last checkpoint calibrates: those probes count.
  return last.plan_index_limit < plan_probes_ && captured > last.probes;
}

bool ConvergenceWatch::Calibrating(std::int64_t run_id) const {
  std::lock_guard lock(mutex_);
  return run_id_ == run_id && pending_ != 0;
}

std::optional<Json> ConvergenceWatch::View(const RunDatabase& db, std::int64_t run_id) const {
  RunConfig config;
  try {
    config = StoredRunConfig(db, run_id);
  } catch (const std::exception&) {
    return std::nullopt;
  }
  if (!config.converge.enabled) return std::nullopt;
  ConvergenceCurve curve;
  bool calibrating = false;
  const auto run = db.GetRun(run_id);
  {
    std::lock_guard lock(mutex_);
    if (run_id_ == run_id) {
      curve = curve_;
      // A run just done waits for the tick that starts its last checkpoint, on the whole run.
      calibrating = pending_ != 0 || (run && WholeRunDue(*run, db.CountProbes(run_id).captured));
    }
  }
  if (curve.checkpoints.empty()) curve = LoadConvergenceCurve(db, run_id);
  std::string state = "probing";
  // The model of a converged run is the calibration on all its probes: "calibrating" until then.
  if (calibrating) {
    state = "calibrating";
  } else if (curve.converged) {
    state = "converged";
  } else if (run && IsTerminal(run->state)) {
    state = "not_converged";
  }
  Json view = curve.ToJson();
  view["enabled"] = true;
  view["state"] = state;
  view["checkpoint_probes"] =
      config.plan.checkpoint_probes > 0 ? config.plan.checkpoint_probes : kDefaultConvergeRound;
  view["min_improvement"] = config.converge.min_improvement;
  return view;
}

}  // namespace gs360
