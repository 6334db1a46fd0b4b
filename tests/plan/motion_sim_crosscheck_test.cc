// Cross-check of the planner's time model (plan/motion_estimate.h) against the virtual CNC's
// independent implementation of GRBL's planner (sim/grbl_planner.h), which times the simulated
// machine: the estimate of a run is only as good as this agreement.

#include <catch2/catch.hpp>
#include <cmath>
#include <cstdint>

#include "plan/motion_estimate.h"
#include "sim/grbl_planner.h"
#include "tests/plan/lcg.h"

using namespace gs360;

using test::Lcg;

TEST_CASE("Path times agree with the virtual CNC's planner on random paths", "[motion][sim]") {
  MachineSettings mine;
  mine.planner_blocks = 100000;  // the sim's PlannedPathDuration has unbounded look-ahead
  MotionLimits limits;
  limits.max_rate_mm_per_min = mine.max_rate_mm_per_min;
  limits.acceleration_mm_per_s2 = mine.acceleration_mm_per_s2;
  limits.junction_deviation_mm = mine.junction_deviation_mm;
  Lcg rng{42};
  for (int path = 0; path < 200; ++path) {
    const Eigen::Vector3d start(-100 * rng.Uniform(), -100 * rng.Uniform(), -40 * rng.Uniform());
    std::vector<Move> moves;
    std::vector<MoveRequest> requests;
    Eigen::Vector3d at = start;
    Eigen::Vector3d prev_dir = Eigen::Vector3d::UnitX();
    const int n = 1 + static_cast<int>(rng.Uniform() * 12);
    for (int i = 0; i < n; ++i) {
      // Mix of long rapids, short hops, slow feeds, collinear continuations and reversals.
      const double kind = rng.Uniform();
      Eigen::Vector3d step(rng.Uniform() - 0.5, rng.Uniform() - 0.5, rng.Uniform() - 0.5);
      if (i > 0 && kind < 0.15) step = prev_dir;                   // collinear continuation
      if (i > 0 && kind >= 0.15 && kind < 0.25) step = -prev_dir;  // reversal
      const double len = kind < 0.5 ? 0.2 + 3.0 * rng.Uniform() : 5.0 + 40.0 * rng.Uniform();
      prev_dir = step.normalized();
      at += prev_dir * len;
      const double feed = rng.Uniform() < 0.4 ? 60.0 + 1500.0 * rng.Uniform() : 0.0;
      moves.push_back(Move{at, feed});
      MoveRequest r;
      r.target = at;
      r.rate.rapid = feed <= 0.0;
      r.rate.feed_mm_per_min = feed;
      requests.push_back(r);
    }
    const double ours = PathTime(start, moves, mine, JunctionModel::kGrbl);
    const double sims = PlannedPathDuration(start, requests, limits);
    INFO("path " << path << " with " << n << " moves");
    CHECK(ours == Approx(sims).epsilon(1e-9).margin(1e-9));
    // The stop model bounds the machine from above.
    CHECK(PathTime(start, moves, mine, JunctionModel::kStop) >= sims - 1e-9);
  }
}

TEST_CASE("Single moves agree with the virtual CNC's closed form", "[motion][sim]") {
  const MachineSettings mine;
  MotionLimits limits;
  limits.max_rate_mm_per_min = mine.max_rate_mm_per_min;
  limits.acceleration_mm_per_s2 = mine.acceleration_mm_per_s2;
  const Eigen::Vector3d o(-50, -50, -20);
  for (const Eigen::Vector3d& d : {Eigen::Vector3d(-30, 0, 0), Eigen::Vector3d(0, 0, -2),
                                   Eigen::Vector3d(3, -4, 1), Eigen::Vector3d(0.1, 0.1, 0.1)}) {
    MoveRequest r;
    r.target = o + d;
    CHECK(RapidTime(o, o + d, mine) == Approx(IsolatedMoveDuration(o, r, limits)).epsilon(1e-12));
    r.rate.rapid = false;
    r.rate.feed_mm_per_min = 120.0;
    CHECK(MoveTime(o, Move{o + d, 120.0}, mine) ==
          Approx(IsolatedMoveDuration(o, r, limits)).epsilon(1e-12));
  }
}
