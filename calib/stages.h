#pragma once
// The calibration stages as data: each stage's name, the option fields it reads and the inputs it
// depends on, and its cache key computed from exactly that, mechanically.
//
// A stage's key hashes, in order: the calibration code's hash (every source file of the modules
// the stages run, hashed at build time: a build whose calibration code differs recomputes rather
// than serve what an older build stored), the stage's name, the JSON (base/fields.h) of every
// option field under its `options` pointers except the `ignored` ones, and the key of each of
// its `inputs`: an upstream stage's key or an external input's (the frames, the meshes...).
// A new option field is in the key of every stage that reads its struct without anyone listing
// it; tests/calib/stages_test.cc changes every field in turn and checks which keys change.

#include <cstdint>
#include <filesystem>
#include <map>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "calib/dataset.h"
#include "calib/impression_centroid.h"
#include "calib/intrinsics.h"
#include "calib/pose.h"
#include "calib/render.h"
#include "calib/train.h"
#include "calib/validate.h"
#include "recon/reconstructor.h"
#include "recon/surface_map.h"

namespace gs360 {

struct CalibrationOptions {
  IntrinsicsOptions intrinsics;
  SurfaceMapOptions surface_map;
  ImpressionCentroidOptions impression;
  PoseOptions pose;
  ProbeRenderOptions render;
  DatasetOptions dataset;
  TrainOptions train;
  ValidationOptions validation;
  ReconstructionOptions reconstruction;
  // Stage selection (names from CalibrationStages()); none of them changes a result.
  std::string from_stage;  // "": use every cached stage; else re-run it and every later one
  std::string to_stage;    // "": run to the end; else stop after this stage
  // "": every stage; else run (re-run) only this one, its inputs from the cache: a missing
  // input is a std::runtime_error naming it and the `--to` that computes it.
  std::string only_stage;
  std::string model_name;            // export: default "run-<id>"
  std::string model_version;         // export: default the train artifact's hash
  std::filesystem::path export_dir;  // where model files go; "" = next to the database
  // > 0: only the captured probes whose plan index is below it (a run's first rounds, as a run
  // that stops when it has converged calibrates them); 0: every captured probe. It enters the
  // cache keys through the frames input.
  int plan_index_limit = 0;
  int threads = 2;
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("intrinsics", self.intrinsics);
    visit("surface_map", self.surface_map);
    visit("impression", self.impression);
    visit("pose", self.pose);
    visit("render", self.render);
    visit("dataset", self.dataset);
    visit("train", self.train);
    visit("validation", self.validation);
    visit("reconstruction", self.reconstruction);
    visit("from_stage", self.from_stage);
    visit("to_stage", self.to_stage);
    visit("only_stage", self.only_stage);
    visit("model_name", self.model_name);
    visit("model_version", self.model_version);
    visit("export_dir", self.export_dir);
    visit("plan_index_limit", self.plan_index_limit);
    visit("threads", self.threads);
  }
  void Check() const;  // throws std::invalid_argument naming the field
};

struct StageSpec {
  std::string name;
  // JSON pointers into FieldsToJson(CalibrationOptions) ("/pose", "/reconstruction/difference").
  std::vector<std::string> options;
  // Pointers under `options` that cannot change the stage's output (thread counts the stage
  // overrides or that only change its speed).
  std::vector<std::string> ignored;
  // Upstream stage names and external inputs (CalibrationExternalInputs()).
  std::vector<std::string> inputs;
};

// The stages in running order; CalibrationStages() is their names.
const std::vector<StageSpec>& CalibrationStageSpecs();
const std::vector<std::string>& CalibrationStages();

// The inputs that are not stages, each computed by the pipeline from what it reads:
//   frames              every captured probe's frame and reference checksums and ball position
//   geometry            gel and fin meshes, ball radius
//   nominal_intrinsics  the rig's lens
//   checkerboards       the checkerboard images' bytes
//   nominal_pose        the rig's cam_from_sensor
//   samples_per_probe   the dataset's per-probe sample cap (from the budget and the renders)
//   truth               the validation truth's description ("no truth" in production)
//   export_dir          where the model files go
const std::vector<std::string>& CalibrationExternalInputs();

// The stage's key from the options' JSON and the keys of its inputs. Throws std::logic_error
// naming an input missing from `keys` or a pointer missing from `options_json`.
std::string StageKey(const StageSpec& stage, const nlohmann::json& options_json,
                     const std::map<std::string, std::string>& keys);

// Every stage's key, in order, from the options and the external inputs' keys (each of
// CalibrationExternalInputs() must be present). Used by the pipeline's tests and reports.
std::map<std::string, std::string> CalibrationStageKeys(
    const CalibrationOptions& options, const std::map<std::string, std::string>& external);

// The code hash in every key (see above): 64 hex digits.
const std::string& CalibrationCodeHash();

}  // namespace gs360
