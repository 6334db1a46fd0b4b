// `gs360 bench converge` as a user runs it: a small plan on the virtual rig, calibrated round
// after round as gs360d's checkpoints are, then against the simulator's truth.

#include <catch2/catch.hpp>

#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "tests/cli/run_gs360.h"

using namespace gs360;
using test::Gs360;

TEST_CASE("bench converge calibrates every round and compares with the whole plan",
          "[cli][converge]") {
  const test::Gs360Result r =
      Gs360("--json bench converge --shapes cone --candidates 120 --round 30 --seed 2");
  INFO(r.out);
  REQUIRE(r.status == 0);
  // The JSON on stdout follows the progress on stderr.
  const std::size_t key = r.out.rfind("\"shapes\"");
  REQUIRE(key != std::string::npos);
  const nlohmann::json out = nlohmann::json::parse(r.out.substr(r.out.rfind('{', key)));
  REQUIRE(out["shapes"].size() == 1);
  const nlohmann::json& cone = out["shapes"][0];
  CHECK(cone["shape"] == "cone");
  const int probes = cone["plan_probes"].get<int>();
  REQUIRE(probes > 30);
  // Too few probes to meet the targets: a checkpoint at every round's end (but one within half
  // a round of the plan's end) and at the plan's.
  CHECK_FALSE(cone["converged"].get<bool>());
  std::vector<int> limits;
  for (int end = 30; end < probes; end += 30) {
    if (probes - end >= 15) limits.push_back(end);
  }
  limits.push_back(probes);
  const nlohmann::json& curve = cone["checkpoints"];
  REQUIRE(curve.size() == limits.size());
  for (std::size_t i = 0; i < curve.size(); ++i) {
    CHECK(curve[i]["plan_index_limit"] == limits[i]);
    CHECK(curve[i]["probes"].get<int>() <= limits[i]);
    CHECK(curve[i]["targets"].size() == 4);  // judged without truth, as gs360d does
    CHECK(curve[i]["seconds"].get<double>() > 0.0);
  }
  CHECK(cone["pressed"] == probes);
  CHECK(cone["pressed_machine_s"].get<double>() ==
        Approx(cone["plan_machine_s"].get<double>()).epsilon(0.02));
  // The fixed default validated against the physical truth: the pose is judged too.
  REQUIRE(cone["fixed_targets"].size() == 6);
  CHECK(cone["fixed_targets"][0]["value"].is_number());
  CHECK(cone["converged_targets"] == cone["fixed_targets"]);

  const test::Gs360Result bad = Gs360("bench converge --min-improvement 1.5");
  CHECK(bad.status != 0);
  CHECK_THAT(bad.out, Catch::Contains("min-improvement"));
}
