// The planner's per-point filters: each drop reason on a point chosen to trigger it, and the
// counts of a whole plan.

#include <catch2/catch.hpp>
#include <cmath>
#include <numbers>

#include <nlohmann/json.hpp>

#include "plan/plan.h"
#include "rig/rig_config.h"
#include "tests/angles.h"

using namespace gs360;
using Catch::Matchers::Contains;

namespace {

using gs360::test::kDeg;

RigGeometry Rig(SensorShape shape = SensorShape::kCylinderCap) {
  RigConfig o;
  o.shape.shape = shape;
  return MakeRigGeometry(o);
}

// A point on the built-in cylinder's wall (radius 10) at azimuth phi and height z, and its normal.
Eigen::Vector3d WallPoint(double phi_deg, double z) {
  return {10.0 * std::cos(phi_deg * kDeg), 10.0 * std::sin(phi_deg * kDeg), z};
}
Eigen::Vector3d WallNormal(double phi_deg) {
  return {std::cos(phi_deg * kDeg), std::sin(phi_deg * kDeg), 0.0};
}

// A point on the cylinder's hemispherical cap (centre (0, 0, 20), radius 10), 40 deg from the
// axis at azimuth 45 deg (clear of the fins), and its normal.
Eigen::Vector3d CapNormal() {
  return {std::sin(40 * kDeg) * std::cos(45 * kDeg), std::sin(40 * kDeg) * std::sin(45 * kDeg),
          std::cos(40 * kDeg)};
}
Eigen::Vector3d CapPoint() {
  return Eigen::Vector3d(0, 0, 20) + 10.0 * CapNormal();
}

std::optional<DropReason> Reason(const ProbePointFilter& f, const Eigen::Vector3d& p,
                                 const Eigen::Vector3d& n) {
  return f.Classify(p, n).reason;
}

}  // namespace

TEST_CASE("A visible, reachable wall point is kept", "[plan]") {
  const ProbePointFilter f(Rig(), PlanOptions{});
  const auto r = f.Classify(WallPoint(45, 15), WallNormal(45));
  CHECK_FALSE(r.reason.has_value());
  CHECK(r.point.isApprox(WallPoint(45, 15), 1e-6));
  CHECK(r.normal.isApprox(WallNormal(45), 1e-6));
  // Escapes exist and lie inside the travel.
  CHECK((r.node.radial || r.node.up));
  // A point on the cap is kept too.
  CHECK_FALSE(Reason(f, CapPoint(), CapNormal()));
}

TEST_CASE("A point behind a fin is dropped as fin", "[plan]") {
  const ProbePointFilter f(Rig(), PlanOptions{});
  // The xz fin (y = 0) and the yz fin (x = 0) lie between the camera on the axis and these.
  CHECK(Reason(f, WallPoint(0, 15), WallNormal(0)) == DropReason::kFin);
  CHECK(Reason(f, WallPoint(90, 15), WallNormal(90)) == DropReason::kFin);
  CHECK(Reason(f, WallPoint(180.5, 15), WallNormal(180.5)) == DropReason::kFin);
  // A little off the board the ray passes by.
  CHECK_FALSE(Reason(f, WallPoint(10, 15), WallNormal(10)));
  // Without fins the same point is kept.
  RigGeometry no_fins = Rig();
  no_fins.fins = TriangleMesh{};
  CHECK_FALSE(Reason(ProbePointFilter(no_fins, PlanOptions{}), WallPoint(0, 15), WallNormal(0)));
}

TEST_CASE("A point outside the image circle is dropped as fov", "[plan]") {
  const ProbePointFilter f(Rig(), PlanOptions{});
  // Camera on the axis at z = -1.5: the wall at z = 0.2 is 81.3 deg off the axis (lens: 80).
  CHECK(Reason(f, WallPoint(45, 0.2), WallNormal(45)) == DropReason::kFov);
  // A narrower field drops the lower wall too.
  RigGeometry narrow = Rig();
  narrow.camera.max_theta = 50.0 * kDeg;
  CHECK(Reason(ProbePointFilter(narrow, PlanOptions{}), WallPoint(45, 5), WallNormal(45)) ==
        DropReason::kFov);
  // fov_margin_rad shrinks the accepted field: the wall at z = 2 is at 70.7 deg.
  PlanOptions margin;
  margin.fov_margin_rad = 10.0 * kDeg;
  CHECK(Reason(ProbePointFilter(Rig(), margin), WallPoint(45, 2), WallNormal(45)) ==
        DropReason::kFov);
  CHECK_FALSE(Reason(ProbePointFilter(Rig(), PlanOptions{}), WallPoint(45, 4), WallNormal(45)));
}

TEST_CASE("A point seen too obliquely is dropped as view_angle", "[plan]") {
  PlanOptions o;
  o.max_view_angle_rad = 30.0 * kDeg;
  const ProbePointFilter f(Rig(), o);
  // Ray to the wall at z = 5 from (0, 0, -1.5): 33 deg from the wall normal.
  CHECK(Reason(f, WallPoint(45, 5), WallNormal(45)) == DropReason::kViewAngle);
  // At z = 3, 24 deg: fine.
  CHECK_FALSE(Reason(f, WallPoint(45, 3), WallNormal(45)));
}

TEST_CASE("A point hidden behind the gel itself is dropped as gel", "[plan]") {
  // An hourglass: the neck at z = 10 hides the wall just above it from a camera at the base.
  RigConfig ro;
  ro.shape.shape = SensorShape::kSpline;
  ro.shape.spline.control_points = {{0.0, 10.0}, {10.0, 4.0}, {20.0, 10.0}, {30.0, 0.0}};
  ro.fins.inset = 1.0;
  const RigGeometry rig = MakeRigGeometry(ro);
  PlanOptions o;
  o.max_view_angle_rad = 89.0 * kDeg;
  const ProbePointFilter f(rig, o);
  const Bvh bvh(rig.sensor_mesh);
  const Eigen::Vector3d camera(0, 0, -1.5);
  int gel = 0;
  for (double z = 10.5; z < 29.0; z += 0.5) {
    const double r = rig.profile->RadiusAt(z);
    const double t = rig.profile->ParameterAtZ(z);
    const Eigen::Vector3d p = rig.profile->SurfacePoint(t, 0.6);
    const Eigen::Vector3d n = rig.profile->SurfaceNormal(t, 0.6);
    INFO("z " << z << " r " << r);
    if (Reason(f, p, n) != DropReason::kGel) continue;
    ++gel;
    // Independently: the first gel hit on the camera ray is well before the point.
    const Eigen::Vector3d d = (p - camera).normalized();
    const auto hit = bvh.Intersect(Ray{camera, d});
    REQUIRE(hit);
    CHECK(hit->t < (p - camera).norm() - 0.1);
  }
  CHECK(gel >= 3);
}

TEST_CASE("Unreachable points are dropped as reach", "[plan]") {
  const PlanOptions o;
  SECTION("under the spline's bulb the vertical stylus hits the bulb") {
    const RigGeometry rig = Rig(SensorShape::kSpline);
    const ProbePointFilter f(rig, o);
    const double t = rig.profile->ParameterAtZ(12.0);  // the waist (r = 8.5), bulb above (9)
    CHECK(Reason(f, rig.profile->SurfacePoint(t, 0.7), rig.profile->SurfaceNormal(t, 0.7)) ==
          DropReason::kReach);
    // Undercut (normal pointing down) below the bulb's widest point.
    const double t2 = rig.profile->ParameterAtZ(14.0);
    REQUIRE(rig.profile->SurfaceNormal(t2, 0.7).z() < 0.0);
    CHECK(Reason(f, rig.profile->SurfacePoint(t2, 0.7), rig.profile->SurfaceNormal(t2, 0.7)) ==
          DropReason::kReach);
    // Above the bulb the stylus is free.
    const double t3 = rig.profile->ParameterAtZ(24.0);
    CHECK_FALSE(Reason(f, rig.profile->SurfacePoint(t3, 0.7), rig.profile->SurfaceNormal(t3, 0.7)));
  }
  SECTION("a groove narrower than the ball touches it twice") {
    SensorShapeOptions so;
    so.shape = SensorShape::kSpline;
    so.spline.control_points = {{0.0, 10.0},  {12.0, 10.0}, {13.0, 8.5},
                                {14.0, 10.0}, {20.0, 10.0}, {30.0, 0.0}};
    RigGeometry rig = MakeRigGeometry();
    rig.profile = MakeProfile(so);
    rig.sensor_mesh = MakeRevolutionMesh(*rig.profile);
    rig.fins = TriangleMesh{};  // fins cannot follow so tight a groove
    const ProbePointFilter f(rig, o);
    const double t = rig.profile->ParameterAtZ(13.0);
    CHECK(Reason(f, rig.profile->SurfacePoint(t, 0.7), rig.profile->SurfaceNormal(t, 0.7)) ==
          DropReason::kReach);
  }
  SECTION("the holder hits the cap when pressing low on the wall") {
    PlanOptions no_mount = o;
    no_mount.base_is_obstacle = false;
    // The holder (radius 4) starts 25 mm above the ball: pressing at z = 2 its edge (7 mm from
    // the axis) meets the cap at z = 27 (radius 7.14 there).
    CHECK(Reason(ProbePointFilter(Rig(), no_mount), WallPoint(45, 2.0), WallNormal(45)) ==
          DropReason::kReach);
    CHECK_FALSE(Reason(ProbePointFilter(Rig(), no_mount), WallPoint(45, 3.0), WallNormal(45)));
    PlanOptions thin = no_mount;
    thin.holder_radius = 0.0;
    CHECK_FALSE(Reason(ProbePointFilter(Rig(), thin), WallPoint(45, 2.0), WallNormal(45)));
  }
  SECTION("the ball would touch the mount near the base") {
    PlanOptions wide = o;
    wide.holder_radius = 0.0;
    const ProbePointFilter f(Rig(), wide);
    CHECK(Reason(f, WallPoint(45, 1.0), WallNormal(45)) == DropReason::kReach);
    wide.base_is_obstacle = false;
    CHECK_FALSE(Reason(ProbePointFilter(Rig(), wide), WallPoint(45, 2.0), WallNormal(45)));
  }
}

TEST_CASE("Points whose positions leave the machine travel are dropped as travel", "[plan]") {
  // Raise the sensor so that presses on the top need Z above 0 (the machine's top).
  RigConfig ro;
  ro.base_in_machine.z() = -65.0;  // the ball 50 mm below the spindle
  const RigGeometry rig = MakeRigGeometry(ro);
  const ProbePointFilter f(rig, PlanOptions{});
  CHECK(Reason(f, CapPoint(), CapNormal()) == DropReason::kTravel);
  // The lower wall is still inside.
  CHECK_FALSE(Reason(f, WallPoint(45, 6), WallNormal(45)));
}

TEST_CASE("A sensor without fins: no fin mesh, nothing dropped for fins, the config says so",
          "[plan]") {
  RigConfig config;
  config.shape.shape = SensorShape::kSpline;
  config.fins.enabled = false;
  const RigGeometry rig = MakeRigGeometry(config);
  CHECK(rig.fins.Empty());
  PlanOptions o;
  o.probe_count = 800;
  const ProbePlan plan = MakeProbePlan(rig, o);
  CHECK(plan.dropped[DropReason::kFin] == 0);
  // The points a fin hid with fins are kept now (the plan with fins drops some: next test).
  const ProbePlan with_fins = MakeProbePlan(Rig(SensorShape::kSpline), o);
  CHECK(plan.probes.size() > with_fins.probes.size());
  // The switch reads and writes with the rest of the rig ([rig.fins] enabled).
  const RigConfig read =
      RigConfigFromJson(nlohmann::json{{"fins", {{"enabled", false}}}}, "test.json");
  CHECK_FALSE(read.fins.enabled);
  CHECK(RigConfigToJson(config)["fins"]["enabled"] == false);
  const RigConfig defaults;
  CHECK(RigConfigFromJson(RigConfigToJson(defaults), "test.json").fins.enabled);
}

TEST_CASE("A plan that keeps little says which setting would change that", "[plan]") {
  DropCounts dropped;
  dropped[DropReason::kReach] = 300;
  dropped[DropReason::kFin] = 500;
  dropped[DropReason::kFov] = 50;  // under a tenth: not worth a line
  const std::vector<std::string> advice = PlanAdvice(dropped, 150, 1000);
  REQUIRE(advice.size() == 2);
  CHECK_THAT(advice[0], Contains("500 of 1000 candidates") && Contains("[rig.fins] enabled"));
  CHECK_THAT(advice[1], Contains("300 of 1000") && Contains("stylus"));
  CHECK(PlanAdvice(dropped, 600, 1000).empty());  // keeps more than half: nothing to say

  // Nothing kept: the error says why and what to change.
  RigConfig far;
  far.base_in_machine.z() = -400.0;  // below anything the machine reaches
  PlanOptions o;
  o.probe_count = 200;
  try {
    MakeProbePlan(MakeRigGeometry(far), o);
    FAIL("a plan with no reachable point was made");
  } catch (const std::runtime_error& e) {
    CHECK_THAT(e.what(), Contains("no probe point survives") && Contains("base_in_machine"));
  }
}

TEST_CASE("A plan counts every candidate once", "[plan]") {
  PlanOptions o;
  o.probe_count = 800;
  const ProbePlan plan = MakeProbePlan(Rig(SensorShape::kSpline), o);
  CHECK(plan.candidates == 800);
  CHECK(plan.dropped.Total() + static_cast<int>(plan.probes.size()) == 800);
  CHECK(plan.dropped[DropReason::kFin] > 0);
  CHECK(plan.dropped[DropReason::kReach] > 0);
  CHECK(plan.dropped[DropReason::kFov] > 0);
  // Every kept probe passes the filter again, every plan position is in travel.
  const ProbePointFilter f(Rig(SensorShape::kSpline), o);
  for (const PlannedProbe& p : plan.probes) {
    CHECK_FALSE(f.Classify(p.point_sensor, p.normal_sensor).reason);
  }
  CHECK_NOTHROW(CheckTravel(plan, o.machine, o.travel_limit_margin));

  // count_is_kept: exactly probe_count kept; rejected draws are counted.
  o.count_is_kept = true;
  o.probe_count = 300;
  const ProbePlan kept = MakeProbePlan(Rig(SensorShape::kSpline), o);
  CHECK(kept.probes.size() == 300);
  CHECK(kept.dropped.Total() > 0);
  CHECK(kept.candidates == kept.dropped.Total() + 300 * 5);  // candidate_factor draws kept
}

TEST_CASE("Planning fails clearly when nothing survives", "[plan]") {
  RigGeometry rig = Rig();
  rig.cam_from_sensor =
      Rigid3d(Eigen::Quaterniond(Eigen::AngleAxisd(std::numbers::pi, Eigen::Vector3d::UnitX())),
              Eigen::Vector3d(0, 0, -100));  // looking away
  PlanOptions o;
  o.probe_count = 50;
  CHECK_THROWS_WITH(MakeProbePlan(rig, o),
                    Contains("no probe point survives") && Contains("fov 50"));
}

TEST_CASE("PlanOptions::Check names the field", "[plan]") {
  PlanOptions o;
  CHECK_NOTHROW(o.Check());
  o.press_depth = 2.5;
  CHECK_THROWS_WITH(o.Check(), Contains("press_depth") && Contains("2.5"));
  o = PlanOptions{};
  o.travel_clearance = 2.0;
  CHECK_THROWS_WITH(o.Check(), Contains("travel_clearance"));
  o = PlanOptions{};
  o.stylus_radius = 2.0;
  CHECK_THROWS_WITH(o.Check(), Contains("stylus_radius"));
  o = PlanOptions{};
  o.machine.max_travel_mm.z() = -1;
  CHECK_THROWS_WITH(o.Check(), Contains("max_travel_mm[2]"));
}
