#include "plan/motion_estimate.h"

#include <catch2/catch.hpp>
#include <cmath>
#include <stdexcept>

using namespace gs360;
using Catch::Matchers::Contains;

namespace {

MachineSettings Settings() {
  MachineSettings s;
  s.max_rate_mm_per_min = {2000.0, 2000.0, 800.0};
  s.acceleration_mm_per_s2 = {150.0, 150.0, 80.0};
  s.junction_deviation_mm = 0.010;
  return s;
}

// Rest-to-rest trapezoid, written out by hand.
double HandRestToRest(double length, double v, double a) {
  if (length >= v * v / a) return length / v + v / a;
  return 2.0 * std::sqrt(length / a);
}

}  // namespace

TEST_CASE("MaxAlongDirection takes the tightest axis along the direction", "[motion]") {
  const Eigen::Vector3d max(2000.0, 2000.0, 800.0);
  CHECK(MaxAlongDirection(max, Eigen::Vector3d::UnitX()) == Approx(2000.0));
  CHECK(MaxAlongDirection(max, -Eigen::Vector3d::UnitZ()) == Approx(800.0));
  // 45 deg in xy: each axis may run at 2000, so the path runs at 2000 * sqrt(2).
  CHECK(MaxAlongDirection(max, Eigen::Vector3d(1, 1, 0).normalized()) ==
        Approx(2000.0 * std::sqrt(2.0)));
  // 45 deg in xz: z binds (800 / cos 45).
  CHECK(MaxAlongDirection(max, Eigen::Vector3d(1, 0, 1).normalized()) ==
        Approx(800.0 * std::sqrt(2.0)));
}

TEST_CASE("TrapezoidTime matches hand-computed trapezoids and triangles", "[motion]") {
  // 10 mm, cruise 10 mm/s, 100 mm/s^2: 0.1 s up (0.5 mm), 9 mm at 10 mm/s, 0.1 s down.
  CHECK(TrapezoidTime(10.0, 0.0, 10.0, 0.0, 100.0) == Approx(1.1));
  // Too short to cruise: peak sqrt(a L) = sqrt(50), time 2 sqrt(L / a).
  CHECK(TrapezoidTime(0.5, 0.0, 10.0, 0.0, 100.0) == Approx(2.0 * std::sqrt(0.005)));
  // Entry 5 mm/s, exit 2 mm/s: up 0.05 s (0.375 mm), down 0.08 s (0.48 mm), cruise 9.145 mm.
  CHECK(TrapezoidTime(10.0, 5.0, 10.0, 2.0, 100.0) == Approx(0.05 + 0.08 + 9.145 / 10.0));
  // Triangle with entry / exit: peak^2 = (2 a L + v0^2 + v1^2) / 2 = (100 + 25 + 4) / 2.
  const double peak = std::sqrt(64.5);
  CHECK(TrapezoidTime(0.5, 5.0, 10.0, 2.0, 100.0) ==
        Approx((peak - 5.0) / 100 + (peak - 2.0) / 100));
  // Pure deceleration over exactly the braking distance.
  CHECK(TrapezoidTime(0.5, 10.0, 10.0, 0.0, 100.0) == Approx(0.1));
  CHECK(TrapezoidTime(0.0, 0.0, 10.0, 0.0, 100.0) == 0.0);
  CHECK_THROWS_WITH(TrapezoidTime(0.1, 0.0, 10.0, 10.0, 100.0), Contains("cannot be met"));
  CHECK_THROWS_AS(TrapezoidTime(1.0, 0.0, 0.0, 0.0, 100.0), std::invalid_argument);
}

TEST_CASE("Junction speeds follow GRBL's junction deviation", "[motion]") {
  const MachineSettings s = Settings();
  const Eigen::Vector3d x = Eigen::Vector3d::UnitX(), y = Eigen::Vector3d::UnitY();
  CHECK(std::isinf(JunctionSpeedSqr(x, x, s)));
  CHECK(JunctionSpeedSqr(x, -x, s) == 0.0);
  // 90 deg in xy: junction unit (-1, 1)/sqrt2 -> accel 150 sqrt2; sin(theta/2) = sqrt(0.5).
  const double a = 150.0 * std::sqrt(2.0), sin_half = std::sqrt(0.5);
  CHECK(JunctionSpeedSqr(x, y, s) == Approx(a * 0.010 * sin_half / (1.0 - sin_half)));
  // Sharper corners are slower.
  const Eigen::Vector3d back45 = Eigen::Vector3d(-1, 1, 0).normalized();
  CHECK(JunctionSpeedSqr(x, back45, s) < JunctionSpeedSqr(x, y, s));
}

TEST_CASE("Single rapid and feed moves equal the closed form", "[motion]") {
  const MachineSettings s = Settings();
  const Eigen::Vector3d o = Eigen::Vector3d::Zero();
  // 100 mm along x at 2000 mm/min, 150 mm/s^2.
  CHECK(RapidTime(o, {-100, 0, 0}, s) == Approx(HandRestToRest(100.0, 2000.0 / 60, 150.0)));
  CHECK(RapidTime(o, {-100, 0, 0}, s) == Approx(100.0 / (100.0 / 3.0) + (100.0 / 3.0) / 150.0));
  // 2 mm along z: a triangle at 80 mm/s^2.
  CHECK(RapidTime(o, {0, 0, -2}, s) == Approx(2.0 * std::sqrt(2.0 / 80.0)));
  // A slow feed is limited by F, not by the rapid rate.
  CHECK(MoveTime(o, Move{{0, 0, -2}, 120.0}, s) == Approx(HandRestToRest(2.0, 2.0, 80.0)));
  // Diagonal xz: rate 800 sqrt2 / 60, accel 80 sqrt2.
  const double v = 800.0 * std::sqrt(2.0) / 60.0, acc = 80.0 * std::sqrt(2.0);
  CHECK(RapidTime(o, {-10, 0, -10}, s) == Approx(HandRestToRest(10.0 * std::sqrt(2.0), v, acc)));
  CHECK(MoveTime(o, Move{o, 0.0}, s) == 0.0);
}

TEST_CASE("PathTime: stop model sums isolated moves, GRBL model carries speed", "[motion]") {
  const MachineSettings s = Settings();
  const Eigen::Vector3d o = Eigen::Vector3d::Zero();
  // Two collinear halves: stopping costs time; GRBL runs them as one block.
  const std::vector<Move> halves{{{-50, 0, 0}, 0.0}, {{-100, 0, 0}, 0.0}};
  CHECK(PathTime(o, halves, s, JunctionModel::kStop) == Approx(2.0 * RapidTime(o, {-50, 0, 0}, s)));
  CHECK(PathTime(o, halves, s, JunctionModel::kGrbl) == Approx(RapidTime(o, {-100, 0, 0}, s)));

  // Right-angle corner, 10 mm then 10 mm: entry / exit at the junction speed.
  const std::vector<Move> corner{{{-10, 0, 0}, 0.0}, {{-10, -10, 0}, 0.0}};
  const double vj = std::sqrt(JunctionSpeedSqr({-1, 0, 0}, {0, -1, 0}, s));
  const double v = 2000.0 / 60.0, a = 150.0;
  // Each block: accelerate 0 -> v (v^2/2a), cruise, decelerate v -> vj ((v^2 - vj^2)/2a).
  const double cruise = 10.0 - v * v / (2 * a) - (v * v - vj * vj) / (2 * a);
  REQUIRE(cruise > 0.0);
  const double block = v / a + (v - vj) / a + cruise / v;
  CHECK(PathTime(o, corner, s, JunctionModel::kGrbl) == Approx(2.0 * block).epsilon(1e-12));
  CHECK(PathTime(o, corner, s, JunctionModel::kStop) == Approx(2.0 * HandRestToRest(10.0, v, a)));

  // A slow press after a rapid: the junction is capped by the press's nominal speed.
  const std::vector<Move> press{{{-10, 0, 0}, 0.0}, {{-12, 0, 0}, 120.0}};
  const auto blocks = PlanPath(o, press, s, JunctionModel::kGrbl);
  REQUIRE(blocks.size() == 2);
  CHECK(blocks[0].exit_speed == Approx(2.0));
  CHECK(blocks[1].entry_speed == Approx(2.0));
  CHECK(blocks[1].exit_speed == 0.0);
  // 2 mm at 2 mm/s, entered at full speed, braking at the end for 2/150 s over 2^2/300 mm.
  CHECK(blocks[1].time == Approx((2.0 - 4.0 / 300.0) / 2.0 + 2.0 / 150.0));
  // A reversal always stops.
  const auto rev = PlanPath(o, {{{-10, 0, 0}, 0.0}, {{-5, 0, 0}, 0.0}}, s, JunctionModel::kGrbl);
  CHECK(rev[0].exit_speed == 0.0);
  // Zero-length moves are dropped.
  CHECK(PlanPath(o, {{o, 0.0}, {{-1, 0, 0}, 0.0}, {{-1, 0, 0}, 0.0}}, s, JunctionModel::kGrbl)
            .size() == 1);
}

TEST_CASE("GRBL model is bounded by the stop model and limited by the look-ahead", "[motion]") {
  MachineSettings s = Settings();
  const Eigen::Vector3d o = Eigen::Vector3d::Zero();
  // 200 collinear 0.1 mm blocks: with 15 blocks (1.5 mm) of look-ahead the machine cannot reach
  // the rapid rate (braking distance 3.7 mm), because it must be able to stop within the
  // planned blocks; unbounded look-ahead runs them as one 20 mm move.
  std::vector<Move> many;
  for (int i = 1; i <= 200; ++i) many.push_back({{-0.1 * i, 0, 0}, 0.0});
  s.planner_blocks = 1000;
  const double unbounded = PathTime(o, many, s, JunctionModel::kGrbl);
  CHECK(unbounded == Approx(RapidTime(o, {-20, 0, 0}, s)));
  s.planner_blocks = 15;
  const double windowed = PathTime(o, many, s, JunctionModel::kGrbl);
  CHECK(windowed > unbounded * 1.001);
  s.planner_blocks = 1;  // every block planned alone: stops at each
  CHECK(PathTime(o, many, s, JunctionModel::kGrbl) ==
        Approx(PathTime(o, many, s, JunctionModel::kStop)));
  CHECK(windowed < PathTime(o, many, s, JunctionModel::kStop));
  // Speeds never exceed nominal or jump beyond the acceleration.
  for (const auto& b : PlanPath(o, many, s, JunctionModel::kGrbl)) {
    CHECK(b.entry_speed <= b.nominal_speed + 1e-12);
    CHECK(std::abs(b.exit_speed * b.exit_speed - b.entry_speed * b.entry_speed) <=
          2.0 * b.acceleration * b.length * (1 + 1e-9));
  }
}

TEST_CASE("EstimateProgram parses G-code and syncs at G4", "[motion]") {
  const MachineSettings s = Settings();
  const Eigen::Vector3d o = Eigen::Vector3d::Zero();
  const std::vector<std::string> lines{"G21",
                                       "G90 ; absolute",
                                       "(comment) G53 G0 X-10 Y0 Z0",
                                       "G1 X-20 F600",
                                       "G4 P0.5",
                                       "g91",
                                       "g0 y-5",
                                       "G4 P0",
                                       "$X",
                                       ""};
  const ProgramEstimate e = EstimateProgram(lines, o, s, JunctionModel::kStop);
  const double expected = RapidTime(o, {-10, 0, 0}, s) +
                          MoveTime({-10, 0, 0}, {{-20, 0, 0}, 600}, s) +
                          RapidTime({-20, 0, 0}, {-20, -5, 0}, s);
  CHECK(e.motion_s == Approx(expected));
  CHECK(e.dwell_s == Approx(0.5));
  CHECK(e.syncs == 2);
  CHECK(e.moves == 3);
  CHECK(e.end_position.isApprox(Eigen::Vector3d(-20, -5, 0)));
  // Work coordinates are shifted by the work offset; G53 lines are not.
  const ProgramEstimate w = EstimateProgram({"G0 X1", "G53 G0 X1"}, o, s, JunctionModel::kStop,
                                            Eigen::Vector3d(-11, 0, 0));
  CHECK(w.motion_s == Approx(RapidTime(o, {-10, 0, 0}, s) + RapidTime({-10, 0, 0}, {1, 0, 0}, s)));
  // Inches.
  const ProgramEstimate in = EstimateProgram({"G20", "G0 X-1"}, o, s, JunctionModel::kStop);
  CHECK(in.end_position.x() == Approx(-25.4));
  CHECK_THROWS_WITH(EstimateProgram({"G0 X1", "G1 X2"}, o, s, JunctionModel::kStop),
                    Contains("line 2") && Contains("feed rate"));
  CHECK_THROWS_WITH(EstimateProgram({"G2 X1 Y1 I1"}, o, s, JunctionModel::kStop),
                    Contains("unsupported"));
  CHECK_THROWS_WITH(EstimateProgram({"G0 X1.2.3"}, o, s, JunctionModel::kStop), Contains("line 1"));
}

TEST_CASE("MachineSettings checks fields and reads $$ values", "[motion]") {
  MachineSettings s;
  CHECK_NOTHROW(s.Check());
  s.acceleration_mm_per_s2.y() = 0.0;
  CHECK_THROWS_WITH(s.Check(), Contains("acceleration_mm_per_s2[1]"));
  const MachineSettings g =
      MachineSettings::FromGrblSettings({{110, 5000.0}, {122, 50.0}, {131, 400.0}, {11, 0.02}});
  CHECK(g.max_rate_mm_per_min.x() == 5000.0);
  CHECK(g.max_rate_mm_per_min.y() == MachineSettings().max_rate_mm_per_min.y());
  CHECK(g.acceleration_mm_per_s2.z() == 50.0);
  CHECK(g.max_travel_mm.y() == 400.0);
  CHECK(g.junction_deviation_mm == 0.02);
  CHECK_THROWS_WITH(MachineSettings::FromGrblSettings({{11, -1.0}}),
                    Contains("junction_deviation"));
}
