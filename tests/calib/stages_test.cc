// calib/stages.h: every option field is in the cache key of each stage that reads it (and of
// every stage downstream), and in no other.

#include <catch2/catch.hpp>

#include <algorithm>
#include <set>

#include "base/fields.h"
#include "calib/stages.h"

using namespace gs360;

namespace {

std::map<std::string, std::string> External() {
  std::map<std::string, std::string> keys;
  for (const std::string& input : CalibrationExternalInputs()) keys[input] = "key-of-" + input;
  return keys;
}

// The stages that read `leaf` (dotted) directly, by their specs.
std::set<std::string> Readers(const std::string& leaf) {
  std::string pointer = "/" + leaf;
  std::replace(pointer.begin(), pointer.end(), '.', '/');
  auto under = [&](const std::string& prefix) {
    return pointer == prefix || pointer.rfind(prefix + "/", 0) == 0;
  };
  std::set<std::string> out;
  for (const StageSpec& s : CalibrationStageSpecs()) {
    const bool reads = std::any_of(s.options.begin(), s.options.end(), under);
    const bool ignores = std::any_of(s.ignored.begin(), s.ignored.end(), under);
    if (reads && !ignores) out.insert(s.name);
  }
  return out;
}

// Whether some stage declares `leaf` (dotted) as not changing its output.
bool Ignored(const std::string& leaf) {
  std::string pointer = "/" + leaf;
  std::replace(pointer.begin(), pointer.end(), '.', '/');
  for (const StageSpec& s : CalibrationStageSpecs()) {
    if (std::count(s.ignored.begin(), s.ignored.end(), pointer)) return true;
  }
  return false;
}

// `stages` and every stage downstream of them.
std::set<std::string> Downstream(std::set<std::string> stages) {
  for (const StageSpec& s : CalibrationStageSpecs()) {
    for (const std::string& input : s.inputs) {
      if (stages.count(input)) stages.insert(s.name);
    }
  }
  return stages;
}

}  // namespace

TEST_CASE("calibration stages: every member of every options struct is described",
          "[calib][stages]") {
  const auto missing = FieldsNotNamed<CalibrationOptions>("CalibrationOptions");
  INFO((missing.empty() ? std::string() : missing.front()));
  CHECK(missing.empty());
}

TEST_CASE("calibration stages: changing any option changes exactly its readers' keys",
          "[calib][stages]") {
  const CalibrationOptions base;
  const auto base_keys = CalibrationStageKeys(base, External());
  // Fields no stage's result depends on: the stage selection, where the files go (an input
  // of export by its resolved directory, external key export_dir), and the probe selection (an
  // input of every stage through the frames key).
  const std::set<std::string> no_result = {"from_stage", "to_stage", "only_stage", "export_dir",
                                           "plan_index_limit"};
  int fields = 0;
  for (const auto& [leaf, options] : EachFieldChanged(base)) {
    ++fields;
    const auto keys = CalibrationStageKeys(options, External());
    std::set<std::string> changed;
    for (const auto& [stage, key] : keys) {
      if (key != base_keys.at(stage)) changed.insert(stage);
    }
    INFO("option " << leaf);
    CHECK(changed == Downstream(Readers(leaf)));
    // A field that is in no key must say why: a selection field, or ignored by its stage.
    if (!no_result.count(leaf) && !Ignored(leaf)) CHECK_FALSE(changed.empty());
  }
  CHECK(fields > 90);
}

TEST_CASE("calibration stages: every input changes its stage's key and the ones downstream",
          "[calib][stages]") {
  const CalibrationOptions options;
  const auto base_keys = CalibrationStageKeys(options, External());
  for (const std::string& input : CalibrationExternalInputs()) {
    auto external = External();
    external[input] += "-changed";
    const auto keys = CalibrationStageKeys(options, external);
    std::set<std::string> direct, changed;
    for (const StageSpec& s : CalibrationStageSpecs()) {
      if (std::count(s.inputs.begin(), s.inputs.end(), input)) direct.insert(s.name);
      if (keys.at(s.name) != base_keys.at(s.name)) changed.insert(s.name);
    }
    INFO("input " << input);
    CHECK_FALSE(direct.empty());
    CHECK(changed == Downstream(direct));
  }
  auto missing = External();
  missing.erase("frames");
  CHECK_THROWS_WITH(CalibrationStageKeys(options, missing), Catch::Contains("frames"));
}

TEST_CASE("calibration stages: keys include the build's calibration code hash", "[calib][stages]") {
  CHECK(CalibrationCodeHash().size() == 64);
  // Stage names are unique and each input is an earlier stage or an external input.
  std::set<std::string> known(CalibrationExternalInputs().begin(),
                              CalibrationExternalInputs().end());
  for (const StageSpec& s : CalibrationStageSpecs()) {
    for (const std::string& input : s.inputs) {
      INFO(s.name << " reads " << input);
      CHECK(known.count(input));
    }
    CHECK(known.insert(s.name).second);
  }
}
