// Positions, travel limits, order and serialisation of a plan.

#include <algorithm>
#include <catch2/catch.hpp>
#include <cmath>
#include <nlohmann/json.hpp>
#include <numbers>

#include "geometry/sampling.h"
#include "plan/plan.h"

using namespace gs360;
using Catch::Matchers::Contains;

namespace {

// A rig whose mount rotates the sensor about the machine z axis and shifts it, with a tool
// offset that is not purely vertical, so that every term of the mapping matters.
RigGeometry RotatedRig() {
  RigConfig o;
  RigGeometry rig = MakeRigGeometry(o);
  rig.machine_from_sensor =
      Rigid3d::FromAxisAngle(Eigen::Vector3d::UnitZ(), 0.5, Eigen::Vector3d(-140.0, -85.0, -84.0));
  rig.tool_offset = Eigen::Vector3d(0.3, -0.2, -40.0);
  return rig;
}

PlanOptions SmallPlan(int probes) {
  PlanOptions o;
  o.probe_count = probes;
  o.reference_every = 25;
  return o;
}

}  // namespace

TEST_CASE("Approach, press and retract map through the mount and tool offset exactly", "[plan]") {
  const RigGeometry rig = RotatedRig();
  const PlanOptions o = SmallPlan(300);
  const ProbePlan plan = MakeProbePlan(rig, o);
  REQUIRE(plan.probes.size() > 100);
  const double r = o.ball_radius;
  for (const PlannedProbe& p : plan.probes) {
    const Eigen::Vector3d press_sensor = p.point_sensor + p.normal_sensor * (r - o.press_depth);
    const Eigen::Vector3d approach_sensor = p.point_sensor + p.normal_sensor * (r + o.clearance);
    const Eigen::Vector3d press = rig.machine_from_sensor * press_sensor - rig.tool_offset;
    const Eigen::Vector3d approach = rig.machine_from_sensor * approach_sensor - rig.tool_offset;
    CHECK((p.press_machine - press).norm() < 1e-9);
    CHECK((p.approach_machine - approach).norm() < 1e-9);
    CHECK(p.retract_machine == p.approach_machine);
    // Points are on the exact surface with unit outward normals.
    CHECK(std::abs(rig.profile->ClosestPoint(p.point_sensor).signed_distance) < 1e-4);
    CHECK(p.normal_sensor.norm() == Approx(1.0));
    CHECK(p.normal_sensor.dot(rig.profile->ClosestPoint(p.point_sensor).normal) > 0.99999);
    // Press depth along the normal: the ball centre is exactly r - depth from the surface.
    CHECK((press_sensor - p.point_sensor).norm() == Approx(r - o.press_depth));
  }
  // References: before plan index 0 and every 25th.
  for (const PlannedProbe& p : plan.probes) {
    CHECK(p.reference_before == (p.plan_index % 25 == 0));
  }
}

TEST_CASE("CheckTravel throws naming the probe, the position and the axis", "[plan]") {
  const PlanOptions o = SmallPlan(200);
  ProbePlan plan = MakeProbePlan(MakeRigGeometry(), o);
  REQUIRE(plan.probes.size() > 20);
  CHECK_NOTHROW(CheckTravel(plan, o.machine, o.travel_limit_margin));
  plan.probes[17].press_machine.z() = -45.2;  // below $132 = 45
  try {
    CheckTravel(plan, o.machine, 0.0);
    FAIL("no exception");
  } catch (const TravelLimitError& e) {
    CHECK(e.plan_index() == 17);
    CHECK(e.axis() == 2);
    CHECK_THAT(e.what(), Contains("probe 17") && Contains("press") && Contains("Z = -45.200"));
  }
  plan.probes[17].press_machine.z() = -44.9;
  CHECK_NOTHROW(CheckTravel(plan, o.machine, 0.0));
  CHECK_THROWS_AS(CheckTravel(plan, o.machine, 0.5), TravelLimitError);  // inside the margin
  // Rounding as the G-code writes it: -45.0004 prints as -45.000, inside.
  plan.probes[17].press_machine.z() = -45.0004;
  CHECK_NOTHROW(CheckTravel(plan, o.machine, 0.0));
  plan.probes[3].travel_machine.push_back(Eigen::Vector3d(0.2, -10, -10));
  CHECK_THROWS_WITH(CheckTravel(plan, o.machine, 0.0),
                    Contains("probe 3") && Contains("waypoint") && Contains("X = 0.200"));
}

TEST_CASE("The tour is a deterministic permutation no slower than the sampling order", "[plan]") {
  const PlanOptions o = SmallPlan(600);
  const RigGeometry rig = MakeRigGeometry();
  const ProbePlan a = MakeProbePlan(rig, o);
  const ProbePlan b = MakeProbePlan(rig, o);
  const int n = static_cast<int>(a.probes.size());
  REQUIRE(n > 300);
  std::vector<int> seen;
  for (int k = 0; k < n; ++k) {
    CHECK(a.probes[k].plan_index == k);
    seen.push_back(a.probes[k].sample_index);
    // Identical, bit for bit.
    CHECK(a.probes[k].sample_index == b.probes[k].sample_index);
    CHECK(a.probes[k].press_machine == b.probes[k].press_machine);
  }
  std::sort(seen.begin(), seen.end());
  for (int k = 0; k < n; ++k) CHECK(seen[k] == k);
  CHECK(a.estimate.Total() == b.estimate.Total());
  CHECK(a.options_hash == b.options_hash);
  // Much faster than the random sampling order, and no slower than nearest neighbour.
  CHECK(a.estimate.Total() <= a.sampling_order_estimate.Total());
  CHECK(a.estimate.travel_s < 0.5 * a.sampling_order_estimate.travel_s);
  CHECK(a.estimate.Total() <= a.nearest_neighbour_s + 1e-9);
  CHECK(a.TourGain() > 1.2);
  // Press, dwell and host time do not depend on the order.
  CHECK(a.estimate.press_s == Approx(a.sampling_order_estimate.press_s).epsilon(0.01));
  CHECK(a.estimate.dwell_s == a.sampling_order_estimate.dwell_s);
  CHECK(a.estimate.host_s == a.sampling_order_estimate.host_s);
  // Another seed gives another plan (and another hash).
  PlanOptions o2 = o;
  o2.seed = 2;
  const ProbePlan c = MakeProbePlan(rig, o2);
  CHECK(c.options_hash != a.options_hash);
  CHECK(c.probes.front().point_sensor != a.probes.front().point_sensor);
}

TEST_CASE("Rounds: every checkpoint's prefix covers the reachable surface evenly", "[plan]") {
  PlanOptions o = SmallPlan(600);
  const RigGeometry rig = MakeRigGeometry();
  const ProbePlan tour = MakeProbePlan(rig, o);
  o.checkpoint_probes = 100;
  const ProbePlan rounds = MakeProbePlan(rig, o);
  const int n = static_cast<int>(rounds.probes.size());
  REQUIRE(n == static_cast<int>(tour.probes.size()));
  CHECK(rounds.checkpoint_probes == 100);
  CHECK(rounds.options_hash != tour.options_hash);
  // The same probes, another order.
  std::vector<int> a, b;
  for (const PlannedProbe& p : rounds.probes) a.push_back(p.sample_index);
  for (const PlannedProbe& p : tour.probes) b.push_back(p.sample_index);
  CHECK(a != b);
  std::sort(a.begin(), a.end());
  std::sort(b.begin(), b.end());
  CHECK(a == b);
  // At every checkpoint, no kept point is far from a probe already pressed. The single tour
  // sweeps the surface region by region: its prefixes leave whole parts unprobed.
  std::vector<Eigen::Vector3d> points;
  std::vector<int> rounds_order(n), tour_order(n);
  for (int k = 0; k < n; ++k) points.push_back(rounds.probes[k].point_sensor);
  for (int k = 0; k < n; ++k) rounds_order[k] = k;
  for (int k = 0; k < n; ++k) {
    for (int j = 0; j < n; ++j) {
      if (tour.probes[k].sample_index == rounds.probes[j].sample_index) tour_order[k] = j;
    }
  }
  for (int k = 100; k < n; k += 100) {
    const double r_rounds = PrefixCoveringRadius(points, rounds_order, k);
    const double r_tour = PrefixCoveringRadius(points, tour_order, k);
    INFO("checkpoint " << k << ": covering radius " << r_rounds << " mm, single tour " << r_tour);
    CHECK(r_rounds < 0.5 * r_tour);
  }
  // Each round is toured: the rounds cost time against the single tour, but far less than
  // visiting the probes in their progressive order one by one would.
  CHECK(rounds.estimate.Total() > tour.estimate.Total());
  CHECK(rounds.estimate.travel_s < 0.5 * rounds.sampling_order_estimate.travel_s);
  // The plan says so, and reads back.
  CHECK(PlanSummaryJson(rounds, o).at("checkpoint_probes") == 100);
  CHECK(PlanFromJson(PlanToJson(rounds, o)).checkpoint_probes == 100);
  o.checkpoint_probes = -1;
  CHECK_THROWS_WITH(o.Check(), Contains("checkpoint_probes"));
}

TEST_CASE("EstimatePlan adds up dwell, host time and references as documented", "[plan]") {
  PlanOptions o = SmallPlan(150);
  const ProbePlan plan = MakeProbePlan(MakeRigGeometry(), o);
  const int n = static_cast<int>(plan.probes.size());
  const int refs = (n + 24) / 25;
  const double host = std::max(o.capture_time_s, o.status_poll_latency_s) + o.host_latency_s;
  CHECK(plan.estimate.dwell_s == Approx(n * o.settle_dwell_s));
  CHECK(plan.estimate.host_s == Approx(n * host));
  CHECK(plan.estimate.reference_s == Approx(refs * (o.reference_dwell_s + host)));
  // Each press: clearance + depth = 2 mm at 120 mm/min, from rest, to rest: ~1 s.
  CHECK(plan.estimate.press_s / n == Approx(1.0).epsilon(0.02));
  // The stop-at-every-block model bounds the GRBL model from above, within a few percent.
  PlanOptions stop = o;
  stop.junction_model = JunctionModel::kStop;
  const PlanEstimate upper = EstimatePlan(plan.probes, plan.park_machine, stop);
  CHECK(upper.Total() >= plan.estimate.Total());
  CHECK(upper.Total() <= 1.05 * plan.estimate.Total());
  // Shares add up.
  CHECK(plan.estimate.TravelShare() + plan.estimate.PressShare() == Approx(1.0));
  // Slower machine, longer run.
  PlanOptions slow = o;
  slow.machine.acceleration_mm_per_s2 /= 4.0;
  CHECK(EstimatePlan(plan.probes, plan.park_machine, slow).Total() > plan.estimate.Total());
}

TEST_CASE("Plans round-trip through JSON and summarise their figures", "[plan]") {
  const PlanOptions o = SmallPlan(120);
  const ProbePlan plan = MakeProbePlan(MakeRigGeometry(), o);
  const nlohmann::json summary = PlanSummaryJson(plan, o);
  CHECK(summary.at("kept").get<int>() == static_cast<int>(plan.probes.size()));
  CHECK(summary.at("candidates").get<int>() == 120);
  CHECK(summary.at("dropped").at("fin").get<int>() == plan.dropped[DropReason::kFin]);
  CHECK(summary.at("estimate").at("hours").get<double>() == Approx(plan.estimate.Hours()));
  CHECK(summary.at("tour_gain").get<double>() == Approx(plan.TourGain()));
  CHECK(summary.at("options").at("junction_model") == "grbl");

  const ProbePlan back = PlanFromJson(nlohmann::json::parse(PlanToJson(plan, o).dump()));
  REQUIRE(back.probes.size() == plan.probes.size());
  for (std::size_t i = 0; i < plan.probes.size(); ++i) {
    CHECK(back.probes[i].press_machine == plan.probes[i].press_machine);
    CHECK(back.probes[i].approach_machine == plan.probes[i].approach_machine);
    CHECK(back.probes[i].normal_sensor == plan.probes[i].normal_sensor);
    CHECK(back.probes[i].travel_machine == plan.probes[i].travel_machine);
    CHECK(back.probes[i].reference_before == plan.probes[i].reference_before);
  }
  CHECK(back.dropped.counts == plan.dropped.counts);
  CHECK(back.estimate.Total() == Approx(plan.estimate.Total()));
  CHECK(back.park_machine == plan.park_machine);
  CHECK(back.options_hash == plan.options_hash);
  CHECK_THROWS_WITH(PlanFromJson(nlohmann::json{{"format", "nope"}}), Contains("format"));
  CHECK_THROWS_AS(PlanFromJson(nlohmann::json::object()), std::invalid_argument);
}
