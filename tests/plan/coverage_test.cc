// Where a plan leaves the sensor unprobed (plan/coverage.h): gaps found, joined and named.

#include <algorithm>
#include <catch2/catch.hpp>
#include <cmath>
#include <numbers>

#include <nlohmann/json.hpp>

#include "plan/coverage.h"
#include "plan/plan.h"
#include "rig/rig_config.h"
#include "tests/angles.h"

using namespace gs360;
using Catch::Matchers::Contains;

namespace {

using gs360::test::kDeg;

Eigen::Vector3d Ring(double azimuth_deg, double z) {
  return {10.0 * std::cos(azimuth_deg * kDeg), 10.0 * std::sin(azimuth_deg * kDeg), z};
}

}  // namespace

TEST_CASE("CoverageTally joins unprobed cells into gaps and names their reason", "[plan]") {
  CoverageOptions o;
  o.band_mm = 1.0;
  o.sectors = 12;  // 30 deg each, the first from -180
  CoverageTally tally(30.0, o);
  // Candidates every 5 deg and 0.25 mm: kept, except
  // - above z = 26 (the tip): all dropped, mostly for view_angle;
  // - at azimuth 60-90 deg, z 5-8: dropped for fin;
  // - across +-180 deg (150 to -150), z 12-13: dropped for reach.
  for (double z = 0.125; z < 30.0; z += 0.25) {
    for (double az = -177.5; az < 180.0; az += 5.0) {
      std::optional<DropReason> reason;
      if (z > 26.0) {
        reason = az < -170.0 ? DropReason::kFov : DropReason::kViewAngle;
      } else if (az > 60.0 && az < 90.0 && z > 5.0 && z < 8.0) {
        reason = DropReason::kFin;
      } else if ((az > 150.0 || az < -150.0) && z > 12.0 && z < 13.0) {
        reason = DropReason::kReach;
      }
      tally.Add(Ring(az, z), reason);
    }
  }
  const std::vector<CoverageGap> gaps = tally.Gaps();
  REQUIRE(gaps.size() == 3);
  // Largest first: the tip, all around, four bands.
  CHECK(gaps[0].all_around);
  CHECK(gaps[0].z_min_mm == 26.0);
  CHECK(gaps[0].z_max_mm == 30.0);
  CHECK(gaps[0].reason == DropReason::kViewAngle);
  CHECK(gaps[0].candidates == 4 * 4 * 72);
  CHECK_THAT(gaps[0].Describe(), Contains("z 26.0-30.0 mm all around") &&
                                     Contains("1152 candidates, none kept (most for view_angle)"));
  // The fin's shadow: one sector, three bands.
  CHECK_FALSE(gaps[1].all_around);
  CHECK(gaps[1].reason == DropReason::kFin);
  CHECK(gaps[1].z_min_mm == 5.0);
  CHECK(gaps[1].z_max_mm == 8.0);
  CHECK(gaps[1].azimuth_min_deg == 60.0);
  CHECK(gaps[1].azimuth_max_deg == 90.0);
  // Across +-180 deg: one gap, not two; max < min says it wraps.
  CHECK(gaps[2].reason == DropReason::kReach);
  CHECK(gaps[2].azimuth_min_deg == 150.0);
  CHECK(gaps[2].azimuth_max_deg == -150.0);
  CHECK(gaps[2].z_min_mm == 12.0);
  CHECK(gaps[2].z_max_mm == 13.0);
  const nlohmann::json j = gaps[2].ToJson();
  CHECK(j["reason"] == "reach");
  CHECK_THAT(j["text"].get<std::string>(), Contains("at azimuth 150 to 180 and -180 to -150 deg"));

  // A cell with a single candidate says nothing; bad options name the field.
  CoverageTally sparse(30.0, o);
  sparse.Add(Ring(0, 15), DropReason::kFov);
  CHECK(sparse.Gaps().empty());
  o.sectors = 0;
  CHECK_THROWS_WITH(CoverageTally(30.0, o), Contains("CoverageOptions.sectors"));
  CHECK_THROWS_WITH(CoverageTally(0.0), Contains("height"));
}

TEST_CASE("A plan says before the run which parts of the sensor it cannot probe, and why",
          "[plan]") {
  const auto list = [](const ProbePlan& plan) {
    std::string all;
    for (const CoverageGap& g : plan.coverage_gaps) all += g.Describe() + "\n";
    return all;
  };
  RigConfig rig;
  PlanOptions o;
  o.probe_count = 1500;
  {
    // The camera looks up the axis from below: the higher on the wall, the more grazing its
    // view. With a strict view angle, the upper wall gets no probe all around.
    o.max_view_angle_rad = 60.0 * kDeg;
    const ProbePlan plan = MakeProbePlan(MakeRigGeometry(rig), o);
    INFO(list(plan));
    const auto grazing = std::find_if(
        plan.coverage_gaps.begin(), plan.coverage_gaps.end(),
        [](const CoverageGap& g) { return g.all_around && g.reason == DropReason::kViewAngle; });
    REQUIRE(grazing != plan.coverage_gaps.end());
    CHECK(grazing->z_min_mm > 10.0);
    // The summary stored with the run (and so the report's error map) carries them.
    const nlohmann::json summary = PlanSummaryJson(plan, o);
    REQUIRE(summary["coverage_gaps"].size() == plan.coverage_gaps.size());
    CHECK(summary["coverage_gaps"][0]["text"] == plan.coverage_gaps[0].Describe());
  }
  // The default plan: nothing within about 2 mm of the base, all around (out of the lens's field,
  // then the ball would hit the base), and that is said; elsewhere it leaves out only patches
  // (at the fins, at the apex), never a whole band.
  o.max_view_angle_rad = PlanOptions{}.max_view_angle_rad;
  const ProbePlan plan = MakeProbePlan(MakeRigGeometry(rig), o);
  INFO(list(plan));
  int bands = 0;
  for (const CoverageGap& g : plan.coverage_gaps) {
    if (!g.all_around) continue;
    ++bands;
    CHECK(g.z_max_mm <= 3.0);
    CHECK((g.reason == DropReason::kReach || g.reason == DropReason::kFov));
  }
  CHECK(bands >= 1);
}
