// Real meshes: a closed fingertip solid (a CAD export of the elastomer with its flat base) plans
// as its open sensing surface does, in mm and in metres, and the advice for a finger beyond the
// machine's reach or the stylus's says by how much.

#include <catch2/catch.hpp>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>

#include "plan/plan.h"
#include "rig/rig_config.h"
#include "rig/rig_shape.h"
#include "tests/angles.h"

using namespace gs360;
using Catch::Matchers::Contains;
namespace fs = std::filesystem;

namespace {

constexpr int kSegments = 96;
using gs360::test::kPi;

fs::path TempDir() {
  const fs::path dir = fs::path(GS360_BINARY_DIR) / "test_tmp" / "plan_mesh";
  fs::create_directories(dir);
  return dir;
}

// GelTip-like: a cylinder of radius 11.5 mm, 44 mm tall, under a hemispherical cap (55.5 mm in
// all), with its flat base at z = 0 closed by a fan of triangles (a watertight solid, outward), or
// left open. Written as binary STL with `mm_per_unit` mm per file unit (1000: in metres).
fs::path WriteGelTip(const std::string& name, bool closed, double mm_per_unit) {
  CylinderCapOptions cylinder;
  cylinder.radius = 11.5;
  cylinder.height = 55.5;
  TessellationOptions t;
  t.segments = kSegments;
  TriangleMesh m = MakeRevolutionMesh(*MakeCylinderCapProfile(cylinder), t);
  if (closed) {
    // Vertices 0..segments-1 are the base rim, counter-clockwise seen from +z.
    m.vertices.emplace_back(0.0, 0.0, 0.0);
    const int centre = m.NumVertices() - 1;
    for (int k = 0; k < kSegments; ++k) m.triangles.emplace_back(centre, (k + 1) % kSegments, k);
  }
  m.normals.clear();
  for (Eigen::Vector3d& v : m.vertices) v /= mm_per_unit;
  const fs::path path = TempDir() / name;
  WriteStlBinary(path, m);
  return path;
}

RigConfig GelTipRig(const fs::path& mesh, double mesh_scale = 1.0) {
  RigConfig rig;
  rig.mesh_path = mesh.string();
  rig.mesh_scale = mesh_scale;
  return rig;
}

PlanOptions SmallPlan() {
  PlanOptions o;
  o.probe_count = 600;
  return o;
}

// The number after `prefix` in the first advice line that contains `key`.
double NumberAfter(const std::vector<std::string>& advice, const std::string& key,
                   const std::string& prefix) {
  for (const std::string& line : advice) {
    if (line.find(key) == std::string::npos) continue;
    const std::size_t at = line.find(prefix);
    if (at == std::string::npos) continue;
    return std::stod(line.substr(at + prefix.size()));
  }
  FAIL("no advice line with \"" << key << "\" and \"" << prefix << "\"");
  return 0.0;
}

std::string Joined(const std::vector<std::string>& lines) {
  std::string all;
  for (const std::string& l : lines) all += l + "\n";
  return all;
}

}  // namespace

TEST_CASE("A closed solid's flat base is dropped, in mm and in metres", "[plan][mesh]") {
  const RigShape open = BuildRigShape(GelTipRig(WriteGelTip("geltip_open.stl", false, 1.0)));
  const RigShape mm = BuildRigShape(GelTipRig(WriteGelTip("geltip_mm.stl", true, 1.0)));
  const RigShape metres =
      BuildRigShape(GelTipRig(WriteGelTip("geltip_m.stl", true, 1000.0), 1000.0));
  CHECK(open.base_faces_removed == 0);
  CHECK(mm.base_faces_removed == kSegments);
  CHECK(metres.base_faces_removed == kSegments);
  for (const RigShape* shape : {&mm, &metres}) {
    CHECK(shape->gel.NumTriangles() == open.gel.NumTriangles());
    CHECK(shape->gel.NumVertices() == open.gel.NumVertices());
    CHECK(shape->gel.Area() == Approx(open.gel.Area()).epsilon(1e-6));
    // Nothing faces down any more, and the rim's normals no longer lean toward -z.
    for (int t = 0; t < shape->gel.NumTriangles(); ++t) {
      REQUIRE(shape->gel.TriangleNormal(t).z() > -0.5);
    }
    for (const Eigen::Vector3d& n : shape->gel.normals) REQUIRE(n.z() > -0.05);
  }
  // The camera (on the axis, below the base) sees the wall through the base.
  const RigConfig defaults;
  const Eigen::Vector3d camera(0.0, 0.0, defaults.camera_z);
  const Eigen::Vector3d wall(11.5 * std::cos(0.3), 11.5 * std::sin(0.3), 20.0);
  const auto hit = Bvh(mm.gel).Intersect(Ray{camera, (wall - camera).normalized()});
  REQUIRE(hit);
  CHECK(hit->t == Approx((wall - camera).norm()).margin(0.05));

  // A mesh that is nothing but a base has no finger left.
  TriangleMesh plate;
  plate.vertices = {{-5, -5, 0}, {5, -5, 0}, {5, 5, 0}, {-5, 5, 0}};
  plate.triangles = {{0, 2, 1}, {0, 3, 2}};  // facing -z
  WriteStlBinary(TempDir() / "plate.stl", plate);
  CHECK_THROWS_WITH(BuildRigShape(GelTipRig(TempDir() / "plate.stl")),
                    Contains("plate.stl") && Contains("only a flat base"));
}

TEST_CASE("A closed GelTip-like solid plans as its open surface, in mm and in metres",
          "[plan][mesh]") {
  // Mounted 20 mm lower than the default, so that the machine reaches its tip.
  auto plan_of = [](RigConfig rig) {
    rig.base_in_machine.z() -= 20.0;
    return MakeProbePlan(MakeRigGeometry(rig), SmallPlan());
  };
  const ProbePlan open = plan_of(GelTipRig(WriteGelTip("geltip_open.stl", false, 1.0)));
  const ProbePlan mm = plan_of(GelTipRig(WriteGelTip("geltip_mm.stl", true, 1.0)));
  const ProbePlan metres = plan_of(GelTipRig(WriteGelTip("geltip_m.stl", true, 1000.0), 1000.0));
  INFO("open: " << open.probes.size() << " kept\n" << Joined(PlanAdvice(open)));
  INFO("mm: " << mm.probes.size() << " kept\n" << Joined(PlanAdvice(mm)));
  INFO("metres: " << metres.probes.size() << " kept\n" << Joined(PlanAdvice(metres)));
  for (const ProbePlan* plan : {&open, &mm, &metres}) {
    // A convex finger hides nothing from a camera inside it.
    CHECK(plan->dropped[DropReason::kGel] == 0);
    CHECK(plan->probes.size() >= 100);
    for (const std::string& line : PlanAdvice(*plan)) {
      CHECK_THAT(line, !Contains("closed") && !Contains("outward"));
    }
  }
  // The same surface: the same candidates, dropped alike (the file in metres passes through
  // float32 at another scale: a few candidates may fall otherwise). The wall just under the cap
  // is seen edge-on (past 75 deg from 41 mm up) on every mesh, the base hides nothing.
  CHECK(mm.dropped[DropReason::kViewAngle] > 0);
  CHECK(mm.probes.size() == open.probes.size());
  CHECK(mm.dropped.counts == open.dropped.counts);
  CHECK(std::abs(static_cast<int>(metres.probes.size()) - static_cast<int>(open.probes.size())) <=
        6);
}

TEST_CASE("A finger beyond the machine's reach is told where to mount it and how much travel",
          "[plan][mesh]") {
  // At the default mount (base at machine z = -93, the ball 50 mm below the spindle), the ball
  // 3 mm over the tip (55.5 mm above the base) needs the spindle at z = +15.5, 16 mm above the
  // top of the travel (-0.5, its margin): the tool cannot pass over the finger. The plan says so,
  // made (its advice) or not (its error: no way back to the start).
  const RigConfig rig = GelTipRig(WriteGelTip("geltip_mm.stl", true, 1.0));
  const PlanOptions options = SmallPlan();
  auto advice_of = [&](const RigConfig& r, const PlanOptions& o, int* travel_dropped) {
    try {
      const ProbePlan plan = MakeProbePlan(MakeRigGeometry(r), o);
      *travel_dropped = plan.dropped[DropReason::kTravel];
      return Joined(PlanAdvice(plan));
    } catch (const std::runtime_error& e) {
      *travel_dropped = -1;
      return std::string(e.what());
    }
  };
  int dropped = 0;
  const std::string advice = advice_of(rig, options, &dropped);
  INFO(advice);
  CHECK(dropped != 0);
  CHECK_THAT(advice,
             Contains("The tool cannot pass over the sensor: that takes machine z = 15.5") &&
                 Contains("mm above the top of the travel") && !Contains("closed"));
  const double base_z = NumberAfter({advice}, "travel", "base_in_machine z to ");
  CHECK(rig.base_in_machine.z() - base_z >= 15.5);
  CHECK(rig.base_in_machine.z() - base_z <= 16.1);

  // Mounted (and given the travel) as the advice says, nothing the tool can press is out of
  // travel; a millimetre higher, some is.
  RigConfig moved = rig;
  moved.base_in_machine.z() = base_z;
  PlanOptions more = options;
  if (advice.find("max_travel_mm z to ") != std::string::npos) {
    more.machine.max_travel_mm.z() = NumberAfter({advice}, "travel", "max_travel_mm z to ");
  }
  const ProbePlan fixed = MakeProbePlan(MakeRigGeometry(moved), more);
  INFO(Joined(PlanAdvice(fixed)));
  CHECK(fixed.dropped[DropReason::kTravel] == 0);
  CHECK_THAT(Joined(PlanAdvice(fixed)), !Contains("travel"));
  RigConfig higher = moved;
  higher.base_in_machine.z() += 1.0;
  CHECK_THAT(advice_of(higher, more, &dropped), Contains("above the top of the travel"));
  CHECK(dropped != 0);
}

TEST_CASE("Presses spanning more than the Z travel are told how much travel they need",
          "[plan][mesh]") {
  // With a stylus long enough for the whole wall, the positions span from the lowest press (the
  // ball at z = 2.5 mm, over the mount) to the plane over the tip (55.5 + 3 mm): 56 mm, where
  // the default travel leaves 44 mm. Mounted 16 mm lower than the default, the top just fits.
  RigConfig rig = GelTipRig(WriteGelTip("geltip_mm.stl", true, 1.0));
  PlanOptions options = SmallPlan();
  options.probe_count = 300;  // a long stylus is slow to check against a mesh
  options.stylus_length = 60.0;
  rig.base_in_machine.z() -= 16.0;
  std::string advice;
  int dropped = 0;
  try {
    const ProbePlan plan = MakeProbePlan(MakeRigGeometry(rig), options);
    advice = Joined(PlanAdvice(plan));
    dropped = plan.dropped[DropReason::kTravel];
  } catch (const std::runtime_error& e) {
    advice = e.what();
    dropped = -1;
  }
  INFO(advice);
  CHECK(dropped != 0);
  const double travel_z = NumberAfter({advice}, "travel", "max_travel_mm z to ");
  char envelope[64];  // the daemon's safety envelope follows the travel
  std::snprintf(envelope, sizeof envelope, "[limits] envelope_min z to %.1f", -travel_z);
  CHECK_THAT(advice, Contains(envelope));
  CHECK(travel_z - options.machine.max_travel_mm.z() >= 10.0);  // the lowest sample, a bit higher
  CHECK(travel_z - options.machine.max_travel_mm.z() <= 12.1);
  // Given that travel (and the mount the advice says), every position fits; 1 mm less does not.
  if (advice.find("base_in_machine z to ") != std::string::npos) {
    rig.base_in_machine.z() = NumberAfter({advice}, "travel", "base_in_machine z to ");
  }
  PlanOptions more = options;
  more.machine.max_travel_mm.z() = travel_z;
  CHECK(MakeProbePlan(MakeRigGeometry(rig), more).dropped[DropReason::kTravel] == 0);
  PlanOptions less = more;
  less.machine.max_travel_mm.z() -= 1.0;
  const ProbePlan short_travel = MakeProbePlan(MakeRigGeometry(rig), less);
  CHECK(short_travel.dropped[DropReason::kTravel] > 0);
}

TEST_CASE("A stylus too short for the lower part is told the length that reaches it",
          "[plan][mesh]") {
  // Pressing the wall at height z, the ball's centre is at z, 12.5 mm from the axis. Against a
  // mesh the planner takes the holder's bottom (radius 4, stylus_length above the ball) for a
  // sphere of about that radius, which must stay 0.1 mm clear of the cap (radius 11.5 about
  // (0, 0, 44)): up to z = 44 + sqrt(15.61^2 - 12.5^2) = 53.35 mm. The lowest wall point the ball
  // presses clear of the mount (0.5 mm under the ball at the approach) is at z = 2.5: a stylus of
  // about 51 mm reaches down there.
  RigConfig rig = GelTipRig(WriteGelTip("geltip_mm.stl", true, 1.0));
  rig.base_in_machine.z() -= 20.0;
  PlanOptions options = SmallPlan();
  options.machine.max_travel_mm.z() = 80.0;
  const RigGeometry geometry = MakeRigGeometry(rig);
  const ProbePlan plan = MakeProbePlan(geometry, options);
  const std::vector<std::string> advice = PlanAdvice(plan);
  INFO(Joined(advice));
  REQUIRE(plan.dropped[DropReason::kReach] * 10 >= plan.candidates);
  const double length = NumberAfter(advice, "cannot be pressed", "plan.stylus_length = ");
  const double lowest_z = NumberAfter(advice, "cannot be pressed", "presses down to z = ");
  CHECK(length == plan.reach.stylus_length_needed);
  CHECK(length >= 50.0);
  CHECK(length <= 52.0);
  CHECK(lowest_z >= 2.4);
  CHECK(lowest_z <= 3.5);

  // With that stylus the wall is pressed down there; two millimetres shorter, it is not.
  const Eigen::Vector3d normal(std::cos(kPi / 4), std::sin(kPi / 4), 0.0);  // on a mesh edge
  const Eigen::Vector3d point = 11.5 * normal + Eigen::Vector3d(0.0, 0.0, lowest_z + 0.2);
  PlanOptions longer = options;
  longer.stylus_length = length;
  CHECK(ProbePointFilter(geometry, longer).Classify(point, normal).reason != DropReason::kReach);
  PlanOptions shorter = options;
  shorter.stylus_length = length - 2.0;
  CHECK(ProbePointFilter(geometry, shorter).Classify(point, normal).reason == DropReason::kReach);
  // And the plan with it presses most of what the short one could not.
  const ProbePlan reached = MakeProbePlan(geometry, longer);
  INFO(Joined(PlanAdvice(reached)));
  CHECK(4 * reached.dropped[DropReason::kReach] < plan.dropped[DropReason::kReach]);
  CHECK(reached.probes.size() > 2 * plan.probes.size());
}
