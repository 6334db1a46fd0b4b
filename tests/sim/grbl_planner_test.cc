#include <catch2/catch.hpp>

#include <cmath>
#include <random>
#include <vector>

#include "sim/grbl_planner.h"

using gs360::IsolatedMoveDuration;
using gs360::MotionExecutor;
using gs360::MotionLimits;
using gs360::MoveRate;
using gs360::MoveRequest;
using gs360::PlannedPathDuration;
using gs360::TrapezoidDuration;

namespace {

MotionLimits TestLimits() {
  MotionLimits l;
  l.max_rate_mm_per_min = Eigen::Vector3d(3000, 2400, 600);
  l.acceleration_mm_per_s2 = Eigen::Vector3d(200, 150, 50);
  l.junction_deviation_mm = 0.01;
  return l;
}

MoveRate Feed(double mm_per_min) {
  MoveRate r;
  r.rapid = false;
  r.feed_mm_per_min = mm_per_min;
  return r;
}

MoveRate Rapid() {
  return MoveRate();
}

// Queues all moves at t = 0, starts, runs to completion; returns the finish time.
double RunAll(MotionExecutor& ex, const std::vector<MoveRequest>& moves) {
  for (const MoveRequest& m : moves) ex.AddLine(m.target, m.rate, 0.0);
  ex.StartCycle(0.0);
  ex.AdvanceTo(1e6);
  REQUIRE_FALSE(ex.Running());
  return ex.History(0.0, 1e6).back().t1;
}

}  // namespace

TEST_CASE("LimitByAxisMaximum takes the binding axis", "[grbl_planner]") {
  const Eigen::Vector3d unit = Eigen::Vector3d(1, 1, 0).normalized();
  CHECK(gs360::LimitByAxisMaximum({500, 300, 100}, unit) == Approx(300 * std::sqrt(2.0)));
  CHECK(gs360::LimitByAxisMaximum({500, 300, 100}, Eigen::Vector3d::UnitZ()) == Approx(100));
}

TEST_CASE("TrapezoidDuration closed forms", "[grbl_planner]") {
  // 100 mm, cruise 10 mm/s, 10 mm/s^2: 1 s up (5 mm), 9 s cruise (90 mm), 1 s down.
  CHECK(TrapezoidDuration(100, 0, 10, 0, 10) == Approx(11.0));
  // Triangle: 4 mm cannot reach 10 mm/s: peak sqrt(a L) = sqrt(40).
  CHECK(TrapezoidDuration(4, 0, 10, 0, 10) == Approx(2 * std::sqrt(40.0) / 10));
  // Entry and exit speeds.
  CHECK(TrapezoidDuration(100, 5, 10, 2, 10) == Approx(0.5 + (100 - 3.75 - 4.8) / 10 + 0.8));
  // Entry above nominal decelerates first: 20 -> 10 takes 1 s over 15 mm.
  CHECK(TrapezoidDuration(100, 20, 10, 0, 10) == Approx(1.0 + (100 - 15 - 5) / 10 + 1.0));
  CHECK_THROWS_AS(TrapezoidDuration(1, 10, 10, 0, 10), std::invalid_argument);
  CHECK_THROWS_AS(TrapezoidDuration(1, 0, 10, 0, 0), std::invalid_argument);
}

TEST_CASE("JunctionSpeedLimit follows the junction-deviation model", "[grbl_planner]") {
  const MotionLimits l = TestLimits();
  const Eigen::Vector3d x = Eigen::Vector3d::UnitX(), y = Eigen::Vector3d::UnitY();
  CHECK(std::isinf(gs360::JunctionSpeedLimit(x, x, l)));
  CHECK(gs360::JunctionSpeedLimit(x, -x, l) == 0.0);
  // 90 degrees: sin(theta/2) = sqrt(0.5); junction acceleration along (y - x)/sqrt2 is
  // limited by y: 150 * sqrt2.
  const double s = std::sqrt(0.5);
  const double expected = std::sqrt(150 * std::sqrt(2.0) * 0.01 * s / (1 - s));
  CHECK(gs360::JunctionSpeedLimit(x, y, l) == Approx(expected));
}

TEST_CASE("Executor: a single move matches the closed form and the profile", "[grbl_planner]") {
  const MotionLimits l = TestLimits();
  MotionExecutor ex({}, Eigen::Vector3d::Zero(), 0.0);
  ex.SetLimits(l);
  const double finish = RunAll(ex, {{Eigen::Vector3d(-40, 0, 0), Feed(1200)}});
  // 20 mm/s, 200 mm/s^2: 0.1 s ramps of 1 mm each, 38 mm cruise.
  CHECK(finish == Approx(0.1 + 38.0 / 20 + 0.1).epsilon(1e-12));
  CHECK(finish == Approx(IsolatedMoveDuration(Eigen::Vector3d::Zero(),
                                              {Eigen::Vector3d(-40, 0, 0), Feed(1200)}, l)));
  CHECK(ex.PositionAt(0.05)[0] == Approx(-0.5 * 200 * 0.05 * 0.05));
  CHECK(ex.SpeedAt(0.05) == Approx(10.0));
  CHECK(ex.PositionAt(1.0)[0] == Approx(-(1.0 + 20 * 0.9)));
  CHECK(ex.PositionAt(finish + 1)[0] == -40.0);
  CHECK(ex.SpeedAt(finish + 1) == 0.0);
}

TEST_CASE("Executor: collinear moves run as one long move", "[grbl_planner]") {
  const MotionLimits l = TestLimits();
  std::vector<MoveRequest> moves;
  for (int i = 1; i <= 5; ++i) moves.push_back({Eigen::Vector3d(-4.0 * i, -3.0 * i, 0), Feed(900)});
  MotionExecutor ex({}, Eigen::Vector3d::Zero(), 0.0);
  ex.SetLimits(l);
  const double finish = RunAll(ex, moves);
  const double single =
      IsolatedMoveDuration(Eigen::Vector3d::Zero(), {moves.back().target, Feed(900)}, l);
  CHECK(finish == Approx(single).epsilon(1e-9));
  CHECK(finish == Approx(PlannedPathDuration(Eigen::Vector3d::Zero(), moves, l)).epsilon(1e-9));
}

TEST_CASE("Executor: a right-angle corner slows to the junction speed", "[grbl_planner]") {
  const MotionLimits l = TestLimits();
  const std::vector<MoveRequest> moves = {{Eigen::Vector3d(-30, 0, 0), Feed(1800)},
                                          {Eigen::Vector3d(-30, -20, 0), Feed(1800)}};
  MotionExecutor ex({}, Eigen::Vector3d::Zero(), 0.0);
  ex.SetLimits(l);
  const double finish = RunAll(ex, moves);
  const double vj =
      gs360::JunctionSpeedLimit(-Eigen::Vector3d::UnitX(), -Eigen::Vector3d::UnitY(), l);
  const double expected =
      TrapezoidDuration(30, 0, 30, vj, 200) + TrapezoidDuration(20, vj, 30, 0, 150);
  CHECK(finish == Approx(expected).epsilon(1e-9));
  CHECK(finish == Approx(PlannedPathDuration(Eigen::Vector3d::Zero(), moves, l)).epsilon(1e-9));
  // At the corner the speed is the junction speed.
  double t_corner = 0;
  for (const auto& p : ex.History(0, 1e6)) {
    if (p.End().isApprox(Eigen::Vector3d(-30, 0, 0), 1e-9)) t_corner = p.t1;
  }
  REQUIRE(t_corner > 0);
  CHECK(ex.SpeedAt(t_corner) == Approx(vj).epsilon(1e-6));
}

TEST_CASE("Executor: a short move is a triangle that never reaches the feed", "[grbl_planner]") {
  const MotionLimits l = TestLimits();
  MotionExecutor ex({}, Eigen::Vector3d::Zero(), 0.0);
  ex.SetLimits(l);
  const double finish = RunAll(ex, {{Eigen::Vector3d(0, 0, -0.5), Rapid()}});
  // Z: 10 mm/s max, 50 mm/s^2: 0.5 mm needs 2 mm to reach 10 mm/s; peak sqrt(50*0.5) = 5.
  CHECK(finish == Approx(2 * 5.0 / 50).epsilon(1e-12));
  double peak = 0;
  for (double t = 0; t < finish; t += finish / 200) peak = std::max(peak, ex.SpeedAt(t));
  CHECK(peak == Approx(5.0).epsilon(1e-2));
  CHECK(peak < 10.0 * 0.6);
}

TEST_CASE("Executor: random paths match the all-at-once plan", "[grbl_planner]") {
  const MotionLimits l = TestLimits();
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-20, 20);
  std::uniform_int_distribution<int> pick(0, 3);
  for (int trial = 0; trial < 40; ++trial) {
    std::vector<MoveRequest> moves;
    const int n = 1 + trial % 15;
    for (int i = 0; i < n; ++i) {
      const MoveRate rate = pick(rng) == 0 ? Rapid() : Feed(300 + 100 * pick(rng));
      moves.push_back({Eigen::Vector3d(u(rng), u(rng), u(rng) / 4), rate});
    }
    MotionExecutor ex({}, Eigen::Vector3d::Zero(), 0.0);
    ex.SetLimits(l);
    const double finish = RunAll(ex, moves);
    CHECK(finish == Approx(PlannedPathDuration(Eigen::Vector3d::Zero(), moves, l)).epsilon(1e-9));
    // The path is continuous and never exceeds the fastest axis rate.
    const double vmax = 3000.0 / 60 * std::sqrt(3.0);
    Eigen::Vector3d prev = ex.PositionAt(0);
    const double dt = finish / 2000;
    for (double t = dt; t <= finish; t += dt) {
      const Eigen::Vector3d p = ex.PositionAt(t);
      CHECK((p - prev).norm() <= vmax * dt * 1.0001 + 1e-12);
      prev = p;
    }
    CHECK(ex.PositionAt(finish).isApprox(moves.back().target, 1e-9));
  }
}

TEST_CASE("Executor: blocks streamed while moving", "[grbl_planner]") {
  const MotionLimits l = TestLimits();
  const std::vector<MoveRequest> moves = {{Eigen::Vector3d(-30, 0, 0), Feed(1800)},
                                          {Eigen::Vector3d(-60, 0, 0), Feed(1800)}};
  const double together = PlannedPathDuration(Eigen::Vector3d::Zero(), moves, l);
  {  // The second block arrives while the first is still accelerating: same as planned at once.
    MotionExecutor ex({}, Eigen::Vector3d::Zero(), 0.0);
    ex.SetLimits(l);
    ex.AddLine(moves[0].target, moves[0].rate, 0.0);
    ex.StartCycle(0.0);
    ex.AdvanceTo(0.1);
    ex.AddLine(moves[1].target, moves[1].rate, 0.1);
    ex.AdvanceTo(1e6);
    CHECK(ex.History(0, 1e6).back().t1 == Approx(together).epsilon(1e-9));
  }
  {  // It arrives while the first decelerates: a dip in speed, the total takes longer.
    MotionExecutor ex({}, Eigen::Vector3d::Zero(), 0.0);
    ex.SetLimits(l);
    ex.AddLine(moves[0].target, moves[0].rate, 0.0);
    ex.StartCycle(0.0);
    const double t_decel = TrapezoidDuration(30, 0, 30, 0, 200) - 0.05;
    ex.AdvanceTo(t_decel);
    const double v_before = ex.SpeedAt(t_decel);
    ex.AddLine(moves[1].target, moves[1].rate, t_decel);
    ex.AdvanceTo(1e6);
    CHECK(ex.SpeedAt(t_decel) == Approx(v_before));
    CHECK(ex.History(0, 1e6).back().t1 > together + 0.01);
    CHECK(ex.PositionAt(1e6)[0] == -60.0);
  }
  {  // A new block after the planner emptied starts from rest.
    MotionExecutor ex({}, Eigen::Vector3d::Zero(), 0.0);
    ex.SetLimits(l);
    ex.AddLine(moves[0].target, moves[0].rate, 0.0);
    ex.StartCycle(0.0);
    ex.AdvanceTo(5.0);
    CHECK_FALSE(ex.Running());
    ex.AddLine(moves[1].target, moves[1].rate, 5.0);
    ex.StartCycle(5.0);
    ex.AdvanceTo(1e6);
    CHECK(ex.History(0, 1e6).back().t1 ==
          Approx(5.0 + TrapezoidDuration(30, 0, 30, 0, 200)).epsilon(1e-9));
  }
}

TEST_CASE("Executor: feed hold decelerates and resume finishes the path", "[grbl_planner]") {
  const MotionLimits l = TestLimits();
  MotionExecutor ex({}, Eigen::Vector3d::Zero(), 0.0);
  ex.SetLimits(l);
  ex.AddLine(Eigen::Vector3d(-10, 0, 0), Feed(1200), 0.0);
  ex.AddLine(Eigen::Vector3d(-50, 0, 0), Feed(1200), 0.0);
  ex.StartCycle(0.0);
  ex.AdvanceTo(0.5);  // cruising at 20 mm/s at x = -(1 + 20 * 0.4) = -9
  const double x_hold = ex.PositionAt(0.5)[0];
  CHECK(x_hold == Approx(-9.0));
  ex.FeedHold(0.5);
  CHECK(ex.Holding());
  CHECK_FALSE(ex.HoldComplete());
  ex.AdvanceTo(0.7);  // stops after 0.1 s, 1 mm further, across the block boundary
  CHECK(ex.HoldComplete());
  CHECK(ex.PositionAt(0.7)[0] == Approx(-10.0));
  CHECK(ex.BlockCount() == 1);
  CHECK(ex.SpeedAt(0.65) == 0.0);
  ex.Resume(2.0);
  ex.AdvanceTo(1e6);
  CHECK(ex.PositionAt(1e6)[0] == -50.0);
  CHECK(ex.History(0, 1e6).back().t1 == Approx(2.0 + TrapezoidDuration(40, 0, 20, 0, 200)));
}

TEST_CASE("Executor: an armed alarm stops the block dead at its fraction", "[grbl_planner]") {
  MotionExecutor ex({}, Eigen::Vector3d::Zero(), 0.0);
  ex.SetLimits(TestLimits());
  ex.AddLine(Eigen::Vector3d(-40, 0, 0), Feed(1200), 0.0, gs360::ArmedAlarm{1, 0.5});
  ex.StartCycle(0.0);
  ex.AdvanceTo(10.0);
  const auto fired = ex.TakeFiredAlarm();
  REQUIRE(fired);
  CHECK(fired->code == 1);
  CHECK(fired->position[0] == Approx(-20.0));
  CHECK(fired->time == Approx(0.1 + 19.0 / 20));
  CHECK_FALSE(ex.Running());
  CHECK(ex.BlockCount() == 0);
  CHECK(ex.PositionAt(10.0)[0] == Approx(-20.0));
  CHECK_FALSE(ex.TakeFiredAlarm());
}

TEST_CASE("Executor: planner capacity - stop - history - system moves", "[grbl_planner]") {
  MotionExecutor::Options opt;
  opt.planner_blocks = 15;
  MotionExecutor ex(opt, Eigen::Vector3d::Zero(), 0.0);
  ex.SetLimits(TestLimits());
  CHECK_FALSE(ex.AddLine(Eigen::Vector3d::Zero(), Feed(600), 0.0));  // zero length: dropped
  CHECK(ex.BlockCount() == 0);
  for (int i = 1; i <= 15; ++i) {
    CHECK_FALSE(ex.PlannerFull());
    REQUIRE(ex.AddLine(Eigen::Vector3d(-i, 0, 0), Feed(600), 0.0));
  }
  CHECK(ex.PlannerFull());
  CHECK(ex.PlannerPosition()[0] == -15.0);
  ex.StartCycle(0.0);
  ex.AdvanceTo(0.3);
  const Eigen::Vector3d at_stop = ex.PositionAt(0.3);
  ex.Stop(0.3);
  CHECK(ex.BlockCount() == 0);
  CHECK_FALSE(ex.Running());
  CHECK(ex.PositionAt(5.0).isApprox(at_stop));
  CHECK(ex.PositionAt(0.1)[0] < 0.0);  // from history
  // A system move with an abrupt end (homing onto a switch) never decelerates.
  ex.AddSystemLine(at_stop + Eigen::Vector3d(10, 0, 0), 600, true, 1.0);
  ex.StartCycle(1.0);
  ex.AdvanceTo(100.0);
  // 10 mm/s at 200 mm/s^2: 0.05 s ramp (0.25 mm), then 9.75 mm at 10 mm/s.
  CHECK(ex.History(0, 1e6).back().t1 == Approx(1.0 + 0.05 + 0.975));
  CHECK(ex.PositionAt(100.0).isApprox(at_stop + Eigen::Vector3d(10, 0, 0)));
}

TEST_CASE("Executor: the past before the kept history is an error, not a guess", "[grbl_planner]") {
  MotionExecutor::Options options;
  options.history_pieces = 4;
  MotionExecutor ex(options, Eigen::Vector3d::Zero(), 0.0);
  ex.SetLimits(TestLimits());
  std::vector<MoveRequest> moves;
  for (int i = 1; i <= 6; ++i)
    moves.push_back({Eigen::Vector3d(-5.0 * i, -3.0 * (i % 2), 0), Feed(1200)});
  const double finish = RunAll(ex, moves);
  CHECK(ex.PositionAt(finish + 1.0)[0] == Approx(-30.0));   // the end is still known
  CHECK_THROWS_AS(ex.PositionAt(0.01), std::out_of_range);  // evicted
  // Without eviction, the time before the first piece is the starting position.
  MotionExecutor full({}, Eigen::Vector3d(-1, -2, -3), 0.0);
  full.SetLimits(TestLimits());
  RunAll(full, {{Eigen::Vector3d(-10, -2, -3), Feed(1200)}});
  CHECK(full.PositionAt(-1.0).isApprox(Eigen::Vector3d(-1, -2, -3)));
}
