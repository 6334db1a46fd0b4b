#pragma once
// The daemon's calibrations: one at a time, on its own thread, through the stages of
// calib/pipeline.h. Each job's state lives in memory and in DATA/runs/ID/calibration.json (written
// at every stage change), so a restarted daemon still shows the last calibration of every run; a
// job that was running when the daemon died shows as `interrupted` (its finished stages are
// cached in the database: calibrating again resumes there).
//
// Stages report "stage" events and the job "calibration" events on the hub. Stop() makes the
// running job stop at its next step (the next stage or training epoch).

#include <atomic>
#include <cstdint>
#include <filesystem>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <thread>

#include <nlohmann/json.hpp>

#include "calib/pipeline.h"
#include "daemon/event_hub.h"

namespace gs360 {

class JsonReader;

// The options a calibration request may set (docs/api.md, `gs360 calibrate --help`), read into
// `options`: from, to, only, max_epochs, hidden, samples_per_probe, max_samples, edge_exclusion,
// integration, hf_min_view_angle, fourier, context_sigmas, smooth_sigma, max_validation_probes,
// model_name, model_version. Throws ConfigError naming the field.
void ReadCalibrationRequest(JsonReader& reader, CalibrationOptions& options);

class CalibrationJobs {
 public:
  // `runs_dir`: DATA/runs; `database`: the run database. `threads`: worker threads per job.
  CalibrationJobs(std::filesystem::path runs_dir, std::filesystem::path database, int threads,
                  EventHub& hub);
  ~CalibrationJobs();

  // Starts calibrating `run_id`. False (nothing started) when a job is running; `*busy_run` then
  // names its run.
  bool Start(std::int64_t run_id, const CalibrationInputs& inputs, CalibrationOptions options,
             std::int64_t* busy_run);
  // The running job's run, or 0.
  std::int64_t Running() const;
  // The run's last calibration (running, done, failed, stopped or interrupted); nullopt if it was
  // never calibrated by this data folder's daemon.
  std::optional<nlohmann::json> View(std::int64_t run_id) const;
  // View()'s state alone ("running", "done", ...), cheap enough for every status poll.
  std::optional<std::string> State(std::int64_t run_id) const;
  // Drops what is known of a deleted run.
  void Forget(std::int64_t run_id);
  void Stop();

 private:
  struct Job;
  void Execute(std::shared_ptr<Job> job, CalibrationInputs inputs, CalibrationOptions options);
  void OnStageMessage(Job& job, const std::string& stage, const std::string& message);
  void Save(const Job& job) const;
  nlohmann::json ViewOf(const Job& job) const;

  std::filesystem::path runs_dir_;
  std::filesystem::path database_;
  int threads_;
  EventHub& hub_;
  mutable std::mutex mutex_;
  std::map<std::int64_t, std::shared_ptr<Job>> jobs_;  // this daemon's jobs, by run
  std::shared_ptr<Job> running_;
  // Views read from the files of earlier daemons' jobs, by run (nullopt: no file).
  mutable std::map<std::int64_t, std::optional<nlohmann::json>> loaded_;
  std::thread thread_;
  std::atomic<bool> stop_{false};
};

}  // namespace gs360
