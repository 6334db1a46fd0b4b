// A plan sized in machine time (PlanOptions::machine_hours) rather than in candidates.

#include <catch2/catch.hpp>

#include "plan/plan.h"

using namespace gs360;

namespace {

RigConfig Config(SensorShape shape, double radius, double height) {
  RigConfig rig;
  rig.shape.shape = shape;
  rig.shape.cylinder.radius = radius;
  rig.shape.cylinder.height = height;
  rig.shape.cone.base_radius = radius;
  rig.shape.cone.height = height;
  return rig;
}

}  // namespace

TEST_CASE("A plan sized in machine time fills 90-100 % of it on any shape", "[plan]") {
  const std::pair<const char*, RigConfig> cases[] = {
      {"cylinder", Config(SensorShape::kCylinderCap, 10.0, 30.0)},
      {"dome", Config(SensorShape::kCylinderCap, 14.0, 14.0)},
      {"cone", Config(SensorShape::kCone, 10.0, 30.0)}};
  for (const auto& [name, config] : cases) {
    INFO(name);
    const RigGeometry rig = MakeRigGeometry(config);
    PlanOptions o;
    o.probe_count = 100;  // only the first draw
    o.machine_hours = 0.05;
    const ProbePlan small = MakeProbePlan(rig, o);
    CHECK(small.estimate.Total() <= 0.05 * 3600.0);
    CHECK(small.estimate.Total() >= 0.9 * 0.05 * 3600.0);
    o.machine_hours = 0.1;
    const ProbePlan large = MakeProbePlan(rig, o);
    CHECK(large.estimate.Total() <= 0.1 * 3600.0);
    CHECK(large.estimate.Total() >= 0.9 * 0.1 * 3600.0);
    // Twice the time is about twice the probes, spread over the same surface.
    const double ratio =
        static_cast<double>(large.probes.size()) / static_cast<double>(small.probes.size());
    CHECK(ratio > 1.6);
    CHECK(ratio < 2.5);
    CHECK(large.options_hash != small.options_hash);
  }
}

TEST_CASE("machine_hours 0 plans exactly probe_count candidates, as before the option", "[plan]") {
  const RigGeometry rig = MakeRigGeometry(Config(SensorShape::kCylinderCap, 10.0, 30.0));
  PlanOptions o;
  o.probe_count = 150;
  const ProbePlan plan = MakeProbePlan(rig, o);
  CHECK(plan.candidates == 150);
  o.machine_hours = -1.0;
  CHECK_THROWS_WITH(o.Check(), Catch::Contains("machine_hours"));
}

TEST_CASE("A plan sized in time too short for the targets says so before the run", "[plan]") {
  const RigGeometry rig = MakeRigGeometry(Config(SensorShape::kCylinderCap, 10.0, 30.0));
  PlanOptions o;
  o.probe_count = 100;
  o.machine_hours = 0.05;
  const std::vector<std::string> advice = PlanAdvice(MakeProbePlan(rig, o));
  REQUIRE_FALSE(advice.empty());
  CHECK_THAT(advice[0], Catch::Contains("cannot be expected to meet the accuracy targets") &&
                            Catch::Contains("plan.machine_hours = 0.05 h"));
  // A count asked for is the user's choice: nothing said beyond the drops.
  o.machine_hours = 0.0;
  for (const std::string& line : PlanAdvice(MakeProbePlan(rig, o))) {
    CHECK_THAT(line, !Catch::Contains("accuracy targets"));
  }
}
