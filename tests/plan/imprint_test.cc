// The expected imprint size (plan/imprint.h) and what the plan says of small ones.

#include <catch2/catch.hpp>

#include <cmath>
#include <numbers>

#include "plan/imprint.h"
#include "plan/plan.h"

using namespace gs360;

TEST_CASE("An imprint's expected area follows the lens: face-on, oblique, far, unseen",
          "[plan][imprint]") {
  const FisheyeCamera camera;  // equidistant 160 deg lens, fx = fy
  const double fx = camera.intrinsics().fx;
  const Rigid3d cam_from_sensor;  // the camera at the sensor's origin, looking along +z
  const double a = std::sqrt(2.0 * 2.0 * 1.0 - 1.0);  // contact radius: 2 mm ball, 1 mm deep
  const Eigen::Vector3d facing(0, 0, 1);  // outward: away from the lens, which is inside
  // Face-on on the axis: a disc of radius fx a / D px.
  const double near = ExpectedImprintPixels(camera, cam_from_sensor, {0, 0, 20}, facing, 2.0, 1.0);
  CHECK(near == Approx(std::numbers::pi * std::pow(fx * a / 20.0, 2)).epsilon(0.01));
  // Twice as far: a quarter of the area.
  CHECK(ExpectedImprintPixels(camera, cam_from_sensor, {0, 0, 40}, facing, 2.0, 1.0) ==
        Approx(near / 4.0).epsilon(0.01));
  // Tilted 60 deg away from the line of sight: half the area.
  const double t = 60.0 * std::numbers::pi / 180.0;
  CHECK(ExpectedImprintPixels(camera, cam_from_sensor, {0, 0, 20}, {std::sin(t), 0, std::cos(t)},
                              2.0, 1.0) == Approx(near / 2.0).epsilon(0.02));
  // Seen from outside, behind the lens, or outside its field: not seen.
  CHECK(ExpectedImprintPixels(camera, cam_from_sensor, {0, 0, 20}, -facing, 2.0, 1.0) == 0.0);
  CHECK(ExpectedImprintPixels(camera, cam_from_sensor, {0, 0, -20}, {0, 0, -1}, 2.0, 1.0) == 0.0);
  CHECK(ExpectedImprintPixels(camera, cam_from_sensor, {20, 0, -1}, {1, 0, 0}, 2.0, 1.0) == 0.0);
  // A deeper press leaves a larger disc.
  CHECK(ExpectedImprintPixels(camera, cam_from_sensor, {0, 0, 20}, facing, 2.0, 1.5) > near);

  CHECK_THROWS_WITH(FindSmallImprints(camera, cam_from_sensor, {{0, 0, 20}}, {}, 2.0, 1.0),
                    Catch::Contains("1 points but 0 normals"));
  CHECK_THROWS_WITH(FindSmallImprints(camera, cam_from_sensor, {{0, 0, 20}}, {facing}, 2.0, 2.5),
                    Catch::Contains("press_depth 2.5"));
  const SmallImprints s =
      FindSmallImprints(camera, cam_from_sensor, {{0, 0, 20}, {0, 0, 60}, {0, 0, -5}},
                        {facing, facing, {0, 0, -1}}, 2.0, 1.0);
  CHECK(s.seen == 2);
  CHECK(s.probes == 1);  // 60 mm away: fx a / 60 = 4.9 px radius, 75 px
  CHECK(s.z_min_mm == 60.0);
  CHECK(s.median_px == Approx(std::numbers::pi * std::pow(fx * a / 60.0, 2)).epsilon(0.01));
}

namespace {
RigConfig Cone(double base_radius, double height) {
  RigConfig rig;
  rig.shape.shape = SensorShape::kCone;
  rig.shape.cone.base_radius = base_radius;
  rig.shape.cone.height = height;
  return rig;
}
std::string SmallImprintLine(const ProbePlan& plan) {
  for (const std::string& line : PlanAdvice(plan)) {
    if (line.find("imprints the camera sees in under") != std::string::npos) return line;
  }
  return {};
}
}  // namespace

TEST_CASE("A plan whose gel is largely seen small says so before the run, and where",
          "[plan][imprint]") {
  PlanOptions o;
  o.probe_count = 400;
  // The default cylinder: its top is seen large enough.
  const ProbePlan ordinary = MakeProbePlan(MakeRigGeometry(), o);
  INFO(ordinary.small_imprints.probes << " of " << ordinary.small_imprints.seen);
  CHECK(ordinary.small_imprints.seen > 0);
  CHECK(ordinary.small_imprints.Share() < 0.05);
  CHECK(SmallImprintLine(ordinary).empty());
  // A tall cone: its upper part is far from the lens and seen edge-on.
  RigConfig tall = Cone(12.0, 60.0);
  // A machine whose Z reaches over it and a stylus as long (as `gs360 bench heldout` mounts one).
  tall.base_in_machine.z() = -128.0;
  o.machine.max_travel_mm.z() = 80.0;
  o.stylus_length = 60.0;
  const ProbePlan far = MakeProbePlan(MakeRigGeometry(tall), o);
  INFO(far.small_imprints.probes << " of " << far.small_imprints.seen << ", kept "
                                 << far.probes.size());
  REQUIRE(far.probes.size() > 100);
  CHECK(far.small_imprints.Share() > 0.1);
  CHECK(far.small_imprints.z_min_mm > 20.0);  // the lower part is seen large
  const std::string line = SmallImprintLine(far);
  CHECK_THAT(line, Catch::Contains("cannot be expected to meet the peak target") &&
                       Catch::Contains("under 100 px"));
  CHECK(PlanSummaryJson(far, o).at("small_imprints").at("probes") == far.small_imprints.probes);
}
