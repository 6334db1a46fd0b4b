#pragma once
// The numerical stress suite: every numerical stage driven to its edges (pose from few, clustered
// or collinear impressions; lens guesses far off; saturated, black and noisy frames; grazing view
// angles; huge, NaN and discontinuous gradients; broken meshes and splines; the MLP in float
// against double). Each case states what it expects -- a result within a tolerance, or a clear
// error -- and reports what it observed. A case never lets an exception escape: an unexpected one
// is a failed case whose observation is the message.
//
// Run by `gs360 bench stress` (a table, or --json) and by CTest's label `stress`. The cases use
// the virtual rig's truth (sim/): test and benchmark code, never production.

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>

namespace gs360 {

struct ModelBundle;

struct StressOutcome {
  std::string stage;     // "pose", "intrinsics", "frames", "integration", "geometry", "mlp"
  std::string name;      // the case, unique within the suite
  std::string expected;  // the stated tolerance, or the error expected
  std::string observed;  // the figures measured, or the error's message
  bool passed = false;
  // A measured limit, not a requirement: `passed` then says only that the stage stayed finite and
  // did not crash, and `observed` says where it stops holding. Reported as "limit".
  bool limit = false;
  double seconds = 0.0;
};

struct StressContext {
  std::uint64_t seed = 1;
  // A model calibrated on the default virtual rig (cli/sim_model.h), for the cases of the
  // frames, integration and mlp stages; without one those cases fail, saying so.
  std::shared_ptr<const ModelBundle> model;
  int threads = 2;
  void Check() const;  // throws std::invalid_argument naming the field
};

struct StressCase {
  std::string stage;
  std::string name;
  std::string expected;
  // Returns the observation and whether it meets `expected`; may throw (caught by RunStressCase).
  std::function<bool(const StressContext&, std::string* observed)> run;
  bool limit = false;  // see StressOutcome::limit
};

// Every case, grouped by stage in the order above.
std::vector<StressCase> StressCases();

// Runs one case: times it, catches anything it throws (a failed outcome naming the exception).
StressOutcome RunStressCase(const StressCase& c, const StressContext& context);

// The cases whose stage or name equals one of `only` (all when empty), run in order;
// `progress` (optional) is called after each.
std::vector<StressOutcome> RunStress(
    const StressContext& context, const std::vector<std::string>& only = {},
    const std::function<void(const StressOutcome&)>& progress = {});

nlohmann::json StressOutcomesToJson(const std::vector<StressOutcome>& outcomes);
// A Markdown table (stage, case, expected, observed, result) for docs/stress.md.
std::string StressOutcomesToMarkdown(const std::vector<StressOutcome>& outcomes);

}  // namespace gs360
