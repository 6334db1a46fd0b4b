// Travel paths stay clear of the sensor, checked independently of the planner's own distance
// code: the ball against the analytic RevolutionProfile::ClosestPoint, the stylus and holder
// against the profile radius at every height they span.

#include <catch2/catch.hpp>
#include <cmath>
#include <numbers>

#include "plan/plan.h"
#include "plan/tour.h"

using namespace gs360;

namespace {

// The profile's radius tabulated every 0.02 mm from RevolutionProfile::RadiusAt (the geometry
// module's own inversion of z(t)), for the independent check below.
struct RadiusTable {
  explicit RadiusTable(const RevolutionProfile& profile) : height(profile.Height()) {
    for (double z = 0.0; z <= height; z += kStep) radius.push_back(profile.RadiusAt(z));
  }
  // Largest radius over [z0, z1] (table entries, and exact at the ends).
  double Max(const RevolutionProfile& profile, double z0, double z1) const {
    z0 = std::max(z0, 0.0);
    z1 = std::min(z1, height);
    if (z0 > z1) return -1e9;
    double m = std::max(profile.RadiusAt(z0), profile.RadiusAt(z1));
    for (int i = static_cast<int>(std::ceil(z0 / kStep));
         i * kStep <= z1 && i < static_cast<int>(radius.size()); ++i) {
      m = std::max(m, radius[i]);
    }
    return m;
  }
  static constexpr double kStep = 0.02;
  double height;
  std::vector<double> radius;
};

// Smallest gap (mm) of the tool with its ball centre at `ball` (sensor frame, upright sensor),
// independent of the planner: ball vs the analytic surface and the mount plane; stylus / holder
// as flat-ended vertical cylinders vs the discs of the solid at the heights they span (the
// horizontal gap: a vertical cylinder meets a solid of revolution iff one of its discs does).
double IndependentGap(const RevolutionProfile& profile, const RadiusTable& table,
                      const PlanOptions& o, const Eigen::Vector3d& ball) {
  double gap = profile.ClosestPoint(ball).signed_distance - o.ball_radius;
  gap = std::min(gap, ball.z() - o.ball_radius);
  const double rho = std::hypot(ball.x(), ball.y());
  const double exit = std::sqrt(o.ball_radius * o.ball_radius - o.stylus_radius * o.stylus_radius);
  gap = std::min(
      gap, rho - o.stylus_radius - table.Max(profile, ball.z() + exit, ball.z() + o.stylus_length));
  gap = std::min(gap, rho - o.holder_radius -
                          table.Max(profile, ball.z() + o.stylus_length,
                                    ball.z() + o.stylus_length + o.holder_length));
  return gap;
}

// Checks every leg of from -> waypoints -> to (machine frame) at 0.2 mm steps.
void CheckLegsClear(const TravelPlanner& travel, const RevolutionProfile& profile,
                    const RadiusTable& table, const PlanOptions& o, const Eigen::Vector3d& from,
                    const std::vector<Eigen::Vector3d>& waypoints, const Eigen::Vector3d& to) {
  std::vector<Eigen::Vector3d> pts{from};
  pts.insert(pts.end(), waypoints.begin(), waypoints.end());
  pts.push_back(to);
  for (std::size_t i = 0; i + 1 < pts.size(); ++i) {
    const Eigen::Vector3d a = travel.BallFromMachine(pts[i]);
    const Eigen::Vector3d b = travel.BallFromMachine(pts[i + 1]);
    const int steps = std::max(1, static_cast<int>(std::ceil((b - a).norm() / 0.2)));
    for (int k = 0; k <= steps; ++k) {
      const Eigen::Vector3d q = a + (b - a) * (static_cast<double>(k) / steps);
      const double gap = IndependentGap(profile, table, o, q);
      INFO("leg " << i << " step " << k << " ball " << q.transpose());
      // 0.02 mm: the planner's polyline surface vs the analytic one, the radius table's step.
      REQUIRE(gap >= o.travel_clearance - 0.02);
    }
  }
}

}  // namespace

TEST_CASE("Every travel of a plan keeps the tool clear of the sensor", "[plan]") {
  for (SensorShape shape : {SensorShape::kCylinderCap, SensorShape::kSpline}) {
    RigConfig ro;
    ro.shape.shape = shape;
    const RigGeometry rig = MakeRigGeometry(ro);
    PlanOptions o;
    o.probe_count = 120;
    const ProbePlan plan = MakeProbePlan(rig, o);
    const TravelPlanner travel(rig, o);
    const RadiusTable table(*rig.profile);
    Eigen::Vector3d at = o.start_machine;
    for (const PlannedProbe& p : plan.probes) {
      CheckLegsClear(travel, *rig.profile, table, o, at, p.travel_machine, p.approach_machine);
      at = p.retract_machine;
    }
    std::vector<Eigen::Vector3d> park = plan.park_machine;
    REQUIRE_FALSE(park.empty());
    const Eigen::Vector3d end = park.back();
    park.pop_back();
    CHECK(end == o.start_machine);
    CheckLegsClear(travel, *rig.profile, table, o, at, park, end);
  }
}

TEST_CASE("Blocked travels detour around or over the sensor", "[plan]") {
  const RigGeometry rig = MakeRigGeometry();
  const PlanOptions o;
  const ProbePointFilter filter(rig, o);
  const TravelPlanner& travel = filter.travel();
  const RadiusTable table(*rig.profile);
  // Approach points on opposite walls, and on the wall vs the cap.
  const double kDeg = std::numbers::pi / 180.0;
  auto wall = [&](double phi, double z) {
    const Eigen::Vector3d n(std::cos(phi * kDeg), std::sin(phi * kDeg), 0);
    const auto r = filter.Classify(Eigen::Vector3d(0, 0, z) + 10.0 * n, n);
    REQUIRE_FALSE(r.reason);
    return r.approach_machine;
  };
  const Eigen::Vector3d a = wall(30, 12), b = wall(210, 12), c = wall(120, 6);
  // The straight line through the sensor is blocked.
  CHECK_FALSE(travel.SegmentClear(travel.BallFromMachine(a), travel.BallFromMachine(b),
                                  o.travel_clearance));
  for (const auto& [from, to] : {std::pair{a, b}, std::pair{a, c}, std::pair{c, b}}) {
    const auto path = travel.Path(from, to);
    REQUIRE(path);
    CHECK_FALSE(path->empty());
    CheckLegsClear(travel, *rig.profile, table, o, from, *path, to);
    CHECK(travel.PathTimeStop(from, *path, to) > RapidTime(from, to, o.machine));
  }
  // Neighbouring approach points go straight.
  const Eigen::Vector3d d = wall(31, 12.3);
  const auto near = travel.Path(a, d);
  REQUIRE(near);
  CHECK(near->empty());
  // From the home position (above everything) to a probe and back.
  const auto from_home = travel.Path(o.start_machine, b);
  REQUIRE(from_home);
  CheckLegsClear(travel, *rig.profile, table, o, o.start_machine, *from_home, b);
}

TEST_CASE("On a printer's travel box a homed ball lifts off the bed and steps in", "[plan]") {
  // An Ender-3-class printer: travel 0..235 x 0..235 x 0..250, the sensor on the bed at its
  // centre, machine Z 0 where the ball rests on the bed (cli/sim_args.h ApplyPrinterDefaults).
  RigConfig ro;
  ro.base_in_machine = Eigen::Vector3d(117.5, 117.5, 0.0);
  ro.tool_offset = Eigen::Vector3d(0.0, 0.0, ro.ball_radius);
  const RigGeometry rig = MakeRigGeometry(ro);
  PlanOptions o;
  o.probe_count = 60;
  o.machine.max_travel_mm = Eigen::Vector3d(235.0, 235.0, 250.0);
  o.machine.travel_min_mm = Eigen::Vector3d::Zero();
  o.start_machine = Eigen::Vector3d(117.5, 117.5, 60.0);
  CHECK(o.machine.TravelMax().isApprox(Eigen::Vector3d(235.0, 235.0, 250.0)));
  const ProbePlan plan = MakeProbePlan(rig, o);
  REQUIRE(plan.probes.size() > 30);
  CheckTravel(plan, o.machine, o.travel_limit_margin);  // every position in [0.5, 234.5] etc.
  for (const PlannedProbe& p : plan.probes) CHECK(p.press_machine.z() > 0.0);
  // GRBL's box would not hold it: the same plan is outside [-travel, 0].
  MachineSettings grbl = o.machine;
  grbl.travel_min_mm.reset();
  CHECK_THROWS_AS(CheckTravel(plan, grbl, 0.0), TravelLimitError);

  // After G28 the ball rests on the bed at the travel's corner: no gap to the bed, outside the
  // margin. The path rises straight up, steps into the margin, and goes on clear.
  const TravelPlanner travel(rig, o);
  const RadiusTable table(*rig.profile);
  const Eigen::Vector3d home = Eigen::Vector3d::Zero();
  const auto path = travel.Path(home, plan.probes.front().approach_machine);
  REQUIRE(path);
  REQUIRE(path->size() >= 2);
  CHECK((*path)[0].head<2>().isApprox(home.head<2>()));  // straight up
  CHECK((*path)[0].z() > o.travel_clearance);
  CHECK((*path)[1].minCoeff() >= o.travel_limit_margin - 1e-9);  // inside the margin now
  CheckLegsClear(travel, *rig.profile, table, o, (*path)[0],
                 std::vector<Eigen::Vector3d>(path->begin() + 1, path->end()),
                 plan.probes.front().approach_machine);
}

TEST_CASE("The tour solver finds the optimal tour of points on a circle", "[plan]") {
  // 200 points on a circle, shuffled; the depot on the circle too. The optimal closed tour is
  // the circle itself.
  const int n = 200;
  std::vector<Eigen::Vector3d> pts(n);
  std::vector<int> perm(n);
  for (int i = 0; i < n; ++i) perm[i] = (i * 77) % n;  // 77 is coprime with 200
  for (int i = 0; i < n; ++i) {
    const double a = 2.0 * std::numbers::pi * (perm[i] + 0.5) / (n + 1);
    pts[i] = Eigen::Vector3d(50 * std::cos(a), 50 * std::sin(a), 0);
  }
  const Eigen::Vector3d depot(50, 0, 0);
  auto cost = [&](int i, int j) {
    const Eigen::Vector3d& p = i == n ? depot : pts[i];
    const Eigen::Vector3d& q = j == n ? depot : pts[j];
    return (p - q).norm();
  };
  // Around the circle: depot (angle 0) -> 0.5 step -> 199 steps -> 1.5 steps back to the depot.
  const double step = 2.0 * std::numbers::pi / (n + 1);
  const double optimal =
      2.0 * 50.0 * (std::sin(0.25 * step) + (n - 1) * std::sin(0.5 * step) + std::sin(0.75 * step));
  const TourResult t = SolveTour(pts, depot, cost, cost);
  CHECK(t.cost == Approx(optimal).epsilon(1e-9));
  CHECK(t.cost <= t.nearest_neighbour_cost + 1e-9);
  CHECK(TourLength(t.order, n, cost) == Approx(t.cost));
  std::vector<int> sorted = t.order;
  std::sort(sorted.begin(), sorted.end());
  for (int i = 0; i < n; ++i) CHECK(sorted[i] == i);
  // A random-ish instance: the local search improves on nearest neighbour and is deterministic.
  std::vector<Eigen::Vector3d> cloud(400);
  std::uint64_t s = 7;
  for (auto& p : cloud) {
    for (int k = 0; k < 3; ++k) {
      s = s * 6364136223846793005ull + 1442695040888963407ull;
      p[k] = static_cast<double>(s >> 11) * 0x1.0p-53 * 100.0;
    }
  }
  auto cloud_cost = [&](int i, int j) {
    const Eigen::Vector3d& p = i == 400 ? depot : cloud[i];
    const Eigen::Vector3d& q = j == 400 ? depot : cloud[j];
    return (p - q).norm();
  };
  const TourResult r1 = SolveTour(cloud, depot, cloud_cost, cloud_cost);
  const TourResult r2 = SolveTour(cloud, depot, cloud_cost, cloud_cost);
  CHECK(r1.order == r2.order);
  CHECK(r1.cost < 0.95 * r1.nearest_neighbour_cost);
  CHECK(r1.two_opt_moves > 0);
  CHECK(r1.or_opt_moves > 0);
  TourOptions nn_only;
  nn_only.optimise = false;
  CHECK(SolveTour(cloud, depot, cloud_cost, cloud_cost, nn_only).cost ==
        Approx(r1.nearest_neighbour_cost));
}
