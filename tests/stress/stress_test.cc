// The stress suite in CTest: each stage's cases must pass (a measured limit must stay finite).
// The model the frame cases need is calibrated once per run of this executable, in a temporary
// folder.

#include "stress/stress.h"

#include <unistd.h>

#include <catch2/catch.hpp>
#include <filesystem>
#include <memory>
#include <string>

#include "cli/sim_model.h"
#include "recon/model_bundle.h"

namespace gs360 {
namespace {

namespace fs = std::filesystem;

struct Fixture {
  fs::path dir;
  StressContext context;
  Fixture() {
    dir = fs::temp_directory_path() / ("gs360-stress-test-" + std::to_string(::getpid()));
    fs::remove_all(dir);
    context.model =
        std::make_shared<const ModelBundle>(ReadModelBundle(cli::MakeSimModel(dir, {})));
  }
  ~Fixture() {
    std::error_code ec;
    fs::remove_all(dir, ec);
  }
};

Fixture& Shared() {
  static Fixture f;
  return f;
}

void RunStage(const std::string& stage) {
  const auto outcomes = RunStress(Shared().context, {stage});
  REQUIRE(!outcomes.empty());
  for (const StressOutcome& o : outcomes) {
    INFO(o.name << "\n  expected: " << o.expected << "\n  observed: " << o.observed);
    CHECK(o.passed);
  }
}

}  // namespace

TEST_CASE("pose from few clustered collinear outlying and grazing impressions", "[stress]") {
  RunStage("pose");
}

TEST_CASE("intrinsics from nominal lenses 20 percent off and the corner window", "[stress]") {
  RunStage("intrinsics");
}

TEST_CASE("saturated black noisy and wrong-sized frames", "[stress]") {
  RunStage("frames");
}

TEST_CASE("integration of zero huge NaN and discontinuous slopes and extreme weights", "[stress]") {
  RunStage("integration");
}

TEST_CASE("degenerate meshes and meshes in metres and self-intersecting splines", "[stress]") {
  RunStage("geometry");
}

TEST_CASE("the MLP in float against double and training that diverges", "[stress]") {
  RunStage("mlp");
}

TEST_CASE("every case belongs to a stage and has a unique name", "[stress]") {
  const auto cases = StressCases();
  REQUIRE(cases.size() >= 30);
  for (std::size_t i = 0; i < cases.size(); ++i) {
    INFO(cases[i].name);
    CHECK(!cases[i].expected.empty());
    for (std::size_t j = 0; j < i; ++j) CHECK(cases[i].name != cases[j].name);
  }
}

}  // namespace gs360
