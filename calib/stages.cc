#include "calib/stages.h"

#include <algorithm>
#include <stdexcept>

#include "base/fields.h"
#include "base/hash.h"
#include "calib/code_hash.h"  // generated (calib/CMakeLists.txt)

namespace gs360 {
namespace {

std::string Names(const std::vector<std::string>& names) {
  std::string out;
  for (const auto& s : names) out += (out.empty() ? "" : ", ") + s;
  return out;
}

void CheckStageName(const std::string& field, const std::string& value) {
  if (value.empty()) return;
  const auto& s = CalibrationStages();
  if (std::find(s.begin(), s.end(), value) == s.end()) {
    throw std::invalid_argument("CalibrationOptions." + field + ": unknown stage \"" + value +
                                "\" (stages: " + Names(s) + ")");
  }
}

bool Under(const std::string& pointer, const std::string& prefix) {
  return pointer == prefix || pointer.rfind(prefix + "/", 0) == 0;
}

}  // namespace

const std::vector<StageSpec>& CalibrationStageSpecs() {
  // What each stage reads. A stage's options are whole structs where it uses the struct; the
  // thread counts the pipeline overrides with CalibrationOptions.threads are ignored where the
  // output does not depend on them (training's does: "/threads" is in its key).
  static const std::vector<StageSpec> kSpecs = {
      {"intrinsics", {"/intrinsics"}, {}, {"nominal_intrinsics", "checkerboards"}},
      {"impressions", {"/impression"}, {}, {"frames"}},
      {"pose",
       {"/pose"},
       {"/pose/threads", "/pose/ball_radius_mm"},  // geometry's ball radius replaces it
       {"impressions", "intrinsics", "geometry", "nominal_pose"}},
      {"surface_map",
       {"/surface_map"},
       {"/surface_map/threads"},
       {"pose", "intrinsics", "geometry"}},
      {"render", {"/render"}, {}, {"surface_map", "frames", "geometry"}},
      {"dataset",
       {"/dataset", "/reconstruction/difference"},
       // Replaced by samples_per_probe, the cap the budget gives for this run's renders.
       {"/dataset/max_contact_samples_per_probe", "/dataset/max_samples"},
       {"render", "frames", "samples_per_probe"}},
      {"train", {"/train", "/threads"}, {"/train/threads"}, {"dataset"}},
      {"validate",
       {"/validation", "/reconstruction"},
       {"/validation/threads"},
       {"train", "pose", "surface_map", "dataset", "truth"}},
      {"export",
       {"/model_name", "/model_version", "/surface_map", "/reconstruction"},
       {"/surface_map/threads"},
       {"validate", "train", "export_dir"}},
  };
  return kSpecs;
}

const std::vector<std::string>& CalibrationStages() {
  static const std::vector<std::string> kNames = [] {
    std::vector<std::string> names;
    for (const StageSpec& s : CalibrationStageSpecs()) names.push_back(s.name);
    return names;
  }();
  return kNames;
}

const std::vector<std::string>& CalibrationExternalInputs() {
  static const std::vector<std::string> kInputs = {
      "frames",        "geometry",     "nominal_intrinsics",
      "checkerboards", "nominal_pose", "samples_per_probe",
      "truth",         "export_dir"};
  return kInputs;
}

const std::string& CalibrationCodeHash() {
  static const std::string kHash = GS360_CALIB_CODE_HASH;
  return kHash;
}

void CalibrationOptions::Check() const {
  intrinsics.Check();
  surface_map.Check();
  impression.Check();
  pose.Check();
  render.Check();
  dataset.Check();
  train.Check();
  validation.Check();
  reconstruction.Check();
  if (threads < 1 || threads > 64) {
    throw std::invalid_argument("CalibrationOptions.threads must be in [1, 64], got " +
                                std::to_string(threads));
  }
  if (plan_index_limit < 0) {
    throw std::invalid_argument("CalibrationOptions.plan_index_limit must be >= 0, got " +
                                std::to_string(plan_index_limit));
  }
  CheckStageName("from_stage", from_stage);
  CheckStageName("to_stage", to_stage);
  CheckStageName("only_stage", only_stage);
  if (!only_stage.empty() && (!from_stage.empty() || !to_stage.empty())) {
    throw std::invalid_argument(
        "CalibrationOptions.only_stage (\"" + only_stage +
        "\") runs one stage: it cannot be combined with from_stage or to_stage");
  }
  if (!from_stage.empty() && !to_stage.empty()) {
    const auto& s = CalibrationStages();
    if (std::find(s.begin(), s.end(), to_stage) < std::find(s.begin(), s.end(), from_stage)) {
      throw std::invalid_argument("CalibrationOptions.to_stage (\"" + to_stage +
                                  "\") comes before from_stage (\"" + from_stage + "\")");
    }
  }
}

std::string StageKey(const StageSpec& stage, const nlohmann::json& options_json,
                     const std::map<std::string, std::string>& keys) {
  Hasher h;
  h.Add(CalibrationCodeHash()).Add(stage.name);
  for (const std::string& pointer : stage.options) {
    const nlohmann::json::json_pointer ptr(pointer);
    if (!options_json.contains(ptr)) {
      throw std::logic_error("stage " + stage.name + ": no option " + pointer);
    }
    nlohmann::json selected = options_json.at(ptr);
    for (const std::string& ignored : stage.ignored) {
      if (!Under(ignored, pointer) || ignored == pointer) continue;
      const nlohmann::json::json_pointer rel(ignored.substr(pointer.size()));
      if (!selected.contains(rel)) {
        throw std::logic_error("stage " + stage.name + ": no option " + ignored + " to ignore");
      }
      selected.at(rel.parent_pointer()).erase(rel.back());
    }
    h.Add(pointer).Add(selected.dump());
  }
  for (const std::string& input : stage.inputs) {
    const auto it = keys.find(input);
    if (it == keys.end()) {
      throw std::logic_error("stage " + stage.name + ": no key for its input " + input);
    }
    h.Add(input).Add(it->second);
  }
  return h.Hex();
}

std::map<std::string, std::string> CalibrationStageKeys(
    const CalibrationOptions& options, const std::map<std::string, std::string>& external) {
  const nlohmann::json json = FieldsToJson(options);
  std::map<std::string, std::string> keys = external;
  std::map<std::string, std::string> out;
  for (const StageSpec& stage : CalibrationStageSpecs()) {
    const std::string key = StageKey(stage, json, keys);
    keys[stage.name] = key;
    out[stage.name] = key;
  }
  return out;
}

}  // namespace gs360
