#include "daemon/calibration_jobs.h"

#include <chrono>
#include <cmath>
#include <fstream>
#include <sstream>
#include <string_view>
#include <utility>

#include <spdlog/spdlog.h>

#include "base/atomic_file.h"
#include "base/json_reader.h"
#include "calib/report.h"
#include "recon/reconstructor.h"

namespace gs360 {
namespace {

using Clock = std::chrono::steady_clock;

double UnixNow() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

// Thrown from the pipeline's log callback to stop a job between two steps.
struct Stopped {};

}  // namespace

struct CalibrationJobs::Job {
  struct Stage {
    std::string name;
    std::string state = "pending";  // pending, running, done, cached, failed, skipped
    double seconds = 0.0;
    std::string message;     // the stage's latest log line
    nlohmann::json metrics;  // what the stage measured (null until the job ends)
  };
  std::int64_t run_id = 0;
  std::string state = "running";  // running, done, failed, stopped, interrupted
  double started_at = 0.0;
  double finished_at = 0.0;
  std::string error;
  std::vector<Stage> stages;
  int current = -1;
  Clock::time_point stage_start{};
  nlohmann::json validation;                 // validation.json, when done
  std::map<std::string, std::string> files;  // model, onnx, report, validation -> path
};

namespace {

// A CalibrationOptions::Check() message names the field by its C++ type
// ("TrainOptions.max_epochs"); the request knows it by its key ("max_epochs").
ConfigError CalibrationRequestError(const std::string& where, const std::string& message) {
  static constexpr std::pair<std::string_view, std::string_view> kKeys[] = {
      {"TrainOptions.max_epochs", "max_epochs"},
      {"TrainOptions.hidden", "hidden"},
      {"DatasetOptions.max_contact_samples_per_probe", "samples_per_probe"},
      {"DatasetOptions.max_samples", "max_samples"},
      {"DatasetOptions.small_probe_repeat", "small_probe_repeat"},
      {"DatasetOptions.edge_exclusion_mm", "edge_exclusion"},
      {"HeightFieldOptions.min_view_angle_deg", "hf_min_view_angle"},
      {"DifferenceOptions.context_sigmas_px", "context_sigmas"},
      {"DifferenceOptions.smooth_sigma_px", "smooth_sigma"},
      {"ValidationOptions.max_probes", "max_validation_probes"},
      {"CalibrationOptions.only_stage", "only"},
      {"CalibrationOptions.from_stage", "from"},
      {"CalibrationOptions.to_stage", "to"},
  };
  for (const auto& [type, key] : kKeys) {
    if (message.rfind(type, 0) == 0) {
      return ConfigError(where + ": " + std::string(key) + message.substr(type.size()),
                         std::string(key));
    }
  }
  return ConfigError(where + ": " + message);
}

}  // namespace

void ReadCalibrationRequest(JsonReader& r, CalibrationOptions& o) {
  // Stage selection: names checked here so that the error names the request's field.
  for (const auto& [field, value] : {std::pair{"from", &o.from_stage}, std::pair{"to", &o.to_stage},
                                     std::pair{"only", &o.only_stage}}) {
    r.Get(field, *value);
    const auto& stages = CalibrationStages();
    if (!value->empty() && std::find(stages.begin(), stages.end(), *value) == stages.end()) {
      std::string names;
      for (const auto& s : stages) names += (names.empty() ? "" : ", ") + s;
      r.Fail(field, "unknown stage \"" + *value + "\" (stages: " + names + ")");
    }
  }
  // The checkerboard the lens was photographed with: inner corners and square side.
  // Counts checked as they are read, their ranges named; the options' Check() below holds the
  // rest, its messages renamed to the request's keys (CalibrationRequestError).
  r.Get("board_cols", o.intrinsics.board_cols, IntRange{2, 1000});
  r.Get("board_rows", o.intrinsics.board_rows, IntRange{2, 1000});
  r.Get("square_mm", o.intrinsics.square_mm, NumberRange{0.0, 1000.0, true, "mm"});
  r.Get("max_epochs", o.train.max_epochs, IntRange{1, 100000});
  r.Get("hidden", o.train.hidden);
  r.Get("samples_per_probe", o.dataset.max_contact_samples_per_probe, IntRange{1, 1000000});
  r.Get("max_samples", o.dataset.max_samples);
  r.Get("small_probe_repeat", o.dataset.small_probe_repeat, IntRange{1, 16});
  r.Get("edge_exclusion", o.dataset.edge_exclusion_mm);
  std::string integration;
  r.Get("integration", integration);
  if (!integration.empty()) {
    try {
      o.reconstruction.integration.method = ParseIntegrationMethod(integration);
    } catch (const std::exception& e) {
      r.Fail("integration", e.what());
    }
  }
  r.Get("hf_min_view_angle", o.reconstruction.integration.height_field.min_view_angle_deg);
  int frequencies = -1;
  r.Get("fourier", frequencies, IntRange{0, 16});  // FourierFeatures' limit (recon/mlp.cc)
  if (frequencies == 0) o.train.fourier = {};
  if (frequencies > 0) o.train.fourier.frequencies = frequencies;
  if (r.Raw("context_sigmas") != nullptr) {
    std::vector<double> sigmas;
    r.Get("context_sigmas", sigmas);
    o.reconstruction.difference.context_sigmas_px.clear();
    for (double s : sigmas) {
      if (s > 0.0) o.reconstruction.difference.context_sigmas_px.push_back(s);
    }
  }
  r.Get("smooth_sigma", o.reconstruction.difference.smooth_sigma_px);
  r.Get("max_validation_probes", o.validation.max_probes, IntRange{1, 1000000});
  r.Get("model_name", o.model_name);
  r.Get("model_version", o.model_version);
  try {
    o.Check();
  } catch (const std::invalid_argument& e) {
    throw CalibrationRequestError(r.where(), e.what());
  }
}

CalibrationJobs::CalibrationJobs(std::filesystem::path runs_dir, std::filesystem::path database,
                                 int threads, EventHub& hub)
    : runs_dir_(std::move(runs_dir)),
      database_(std::move(database)),
      threads_(threads),
      hub_(hub) {}

CalibrationJobs::~CalibrationJobs() {
  Stop();
}

void CalibrationJobs::Stop() {
  stop_ = true;
  if (thread_.joinable()) thread_.join();
}

std::int64_t CalibrationJobs::Running() const {
  std::lock_guard lock(mutex_);
  return running_ ? running_->run_id : 0;
}

bool CalibrationJobs::Start(std::int64_t run_id, const CalibrationInputs& inputs,
                            CalibrationOptions options, std::int64_t* busy_run) {
  std::lock_guard lock(mutex_);
  if (running_) {
    if (busy_run) *busy_run = running_->run_id;
    return false;
  }
  if (thread_.joinable()) thread_.join();
  auto job = std::make_shared<Job>();
  job->run_id = run_id;
  job->started_at = UnixNow();
  for (const std::string& name : CalibrationStages()) job->stages.push_back({name});
  jobs_[run_id] = job;
  running_ = job;
  options.threads = threads_;
  options.train.threads = threads_;
  options.validation.threads = threads_;
  options.surface_map.threads = threads_;
  options.export_dir = runs_dir_ / std::to_string(run_id) / "model";
  stop_ = false;
  Save(*job);
  hub_.Publish("calibration", {{"run", run_id}, {"state", "running"}});
  thread_ = std::thread([this, job, inputs, options] { Execute(job, inputs, options); });
  return true;
}

// A stage's progress message from the pipeline: "running" or "cached ..." starts the stage
// (the one before is done), anything else is the current stage's message. Throws Stopped once
// the daemon stops.
void CalibrationJobs::OnStageMessage(Job& job, const std::string& stage,
                                     const std::string& message) {
  if (stop_) throw Stopped{};
  std::lock_guard lock(mutex_);
  const bool starts = message == "running" || message.rfind("cached", 0) == 0;
  if (starts) {
    if (job.current >= 0 && job.stages[job.current].state == "running") {
      job.stages[job.current].state = "done";
      job.stages[job.current].seconds =
          std::chrono::duration<double>(Clock::now() - job.stage_start).count();
    }
    for (std::size_t i = 0; i < job.stages.size(); ++i) {
      if (job.stages[i].name == stage) job.current = static_cast<int>(i);
    }
    job.stage_start = Clock::now();
    if (job.current >= 0) {
      job.stages[job.current].state = message == "running" ? "running" : "cached";
    }
    hub_.Publish("stage", {{"run", job.run_id},
                           {"stage", stage},
                           {"state", message == "running" ? "running" : "cached"}});
    Save(job);
  }
  if (job.current >= 0 && !starts) job.stages[job.current].message = message;
}

void CalibrationJobs::Execute(std::shared_ptr<Job> job, CalibrationInputs inputs,
                              CalibrationOptions options) {
  const auto log = [&](const std::string& stage, const std::string& message) {
    OnStageMessage(*job, stage, message);
  };
  std::string state = "done";
  std::string error;
  CalibrationResult result;
  try {
    RunDatabase db(database_);
    result = RunCalibration(db, job->run_id, inputs, options, nullptr, log);
  } catch (const Stopped&) {
    state = "stopped";
    error = "stopped when the daemon shut down; calibrate again to continue from the last stage";
  } catch (const std::exception& e) {
    state = "failed";
    error = e.what();
  }
  {
    std::lock_guard lock(mutex_);
    job->state = state;
    job->error = error;
    job->finished_at = UnixNow();
    for (auto& s : job->stages) {
      if (s.state == "running") s.state = state == "done" ? "done" : "failed";
    }
    for (const StageReport& r : result.stages) {
      for (auto& s : job->stages) {
        if (s.name == r.stage) {
          s.state = r.cached ? "cached" : "done";
          s.seconds = r.seconds;
          s.metrics = r.metrics;
        }
      }
    }
    if (state == "done") {
      // Stages after `to` (or around `only`) did not run.
      for (auto& s : job->stages) {
        if (s.state == "pending") s.state = "skipped";
      }
    }
    if (state == "done" && !result.model_path.empty()) {
      job->validation = result.validation;
      job->files = {{"model", result.model_path.string()},
                    {"onnx", result.onnx_path.string()},
                    {"report", result.report_path.string()},
                    {"validation", result.validation_path.string()}};
    }
    running_.reset();
  }
  try {
    Save(*job);
  } catch (const std::exception& e) {
    spdlog::error("calibration of run {}: {}", job->run_id, e.what());
  }
  if (state == "done") {
    spdlog::info("calibration of run {} done", job->run_id);
  } else {
    spdlog::error("calibration of run {} {}: {}", job->run_id, state, error);
  }
  hub_.Publish("calibration", {{"run", job->run_id}, {"state", state}, {"error", error}});
}

nlohmann::json CalibrationJobs::ViewOf(const Job& job) const {
  nlohmann::json stages = nlohmann::json::array();
  for (const auto& s : job.stages) {
    double seconds = s.seconds;
    if (s.state == "running") {
      seconds = std::chrono::duration<double>(Clock::now() - job.stage_start).count();
    }
    stages.push_back({{"name", s.name},
                      {"state", s.state},
                      {"seconds", seconds},
                      {"message", s.message},
                      {"metrics", s.metrics}});
  }
  nlohmann::json files = nlohmann::json::object();
  for (const auto& [kind, path] : job.files) files[kind] = path;
  return {{"run", job.run_id},
          {"state", job.state},
          {"started_at", job.started_at},
          {"finished_at", job.finished_at > 0 ? nlohmann::json(job.finished_at) : nullptr},
          {"stage", job.current >= 0 ? nlohmann::json(job.stages[job.current].name) : nullptr},
          {"stages", stages},
          {"error", job.error},
          {"validation", job.validation},
          {"targets",
           job.validation.is_null() ? nlohmann::json::array() : ValidationTargets(job.validation)},
          {"warnings", job.validation.is_object() && job.validation.contains("warnings")
                           ? job.validation["warnings"]
                           : nlohmann::json::array()},
          {"files", files}};
}

void CalibrationJobs::Save(const Job& job) const {
  const std::filesystem::path dir = runs_dir_ / std::to_string(job.run_id);
  std::filesystem::create_directories(dir);
  WriteFileAtomically(dir / "calibration.json", ViewOf(job).dump(1));
}

std::optional<std::string> CalibrationJobs::State(std::int64_t run_id) const {
  {
    std::lock_guard lock(mutex_);
    const auto it = jobs_.find(run_id);
    if (it != jobs_.end()) return it->second->state;
  }
  const auto view = View(run_id);
  if (!view) return std::nullopt;
  return view->value("state", "");
}

void CalibrationJobs::Forget(std::int64_t run_id) {
  std::lock_guard lock(mutex_);
  if (running_ && running_->run_id == run_id) return;
  jobs_.erase(run_id);
  loaded_.erase(run_id);
}

std::optional<nlohmann::json> CalibrationJobs::View(std::int64_t run_id) const {
  std::lock_guard lock(mutex_);
  const auto it = jobs_.find(run_id);
  if (it != jobs_.end()) return ViewOf(*it->second);
  const auto cached = loaded_.find(run_id);
  if (cached != loaded_.end()) return cached->second;
  // A job of an earlier daemon: its file.
  const std::filesystem::path path = runs_dir_ / std::to_string(run_id) / "calibration.json";
  std::ifstream in(path, std::ios::binary);
  if (!in) return loaded_[run_id] = std::nullopt;
  std::stringstream ss;
  ss << in.rdbuf();
  nlohmann::json view = nlohmann::json::parse(ss.str(), nullptr, false);
  if (view.is_discarded() || !view.is_object()) return loaded_[run_id] = std::nullopt;
  if (view.value("state", "") == "running") {
    view["state"] = "interrupted";
    view["error"] = "the daemon stopped during this calibration; calibrate again to continue";
  }
  return loaded_[run_id] = view;
}

}  // namespace gs360
