#include "recon/grid_solver.h"

#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>
#include <catch2/catch.hpp>
#include <cmath>
#include <limits>
#include <random>
#include <vector>

namespace gs360 {
namespace {

struct Problem {
  int w = 0, h = 0;
  std::vector<double> weight_u, weight_v, rhs;
};

// Weights as the height field gives them: most near 1, a share at the membrane's 1e-3.
Problem RandomProblem(int w, int h, std::uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  Problem p{w, h, {}, {}, {}};
  const std::size_t n = static_cast<std::size_t>(w) * static_cast<std::size_t>(h);
  auto weight = [&] { return unit(rng) < 0.3 ? 1e-3 : 0.05 + unit(rng); };
  for (std::size_t i = 0; i < n; ++i) {
    p.weight_u.push_back(weight());
    p.weight_v.push_back(weight());
    p.rhs.push_back(unit(rng) - 0.5);
  }
  return p;
}

bool Interior(const Problem& p, int i) {
  const int x = i % p.w, y = i / p.w;
  return x >= 1 && y >= 1 && x <= p.w - 2 && y <= p.h - 2;
}

// The same system assembled edge by edge as a sparse matrix and solved by Eigen's LDLT.
std::vector<double> Reference(const Problem& p) {
  const int n = p.w * p.h;
  std::vector<int> var(static_cast<std::size_t>(n), -1);
  int unknowns = 0;
  for (int i = 0; i < n; ++i) {
    if (Interior(p, i)) var[static_cast<std::size_t>(i)] = unknowns++;
  }
  std::vector<Eigen::Triplet<double>> t;
  auto edge = [&](int a, int b, double w) {
    const int va = var[static_cast<std::size_t>(a)], vb = var[static_cast<std::size_t>(b)];
    if (va >= 0) t.emplace_back(va, va, w);
    if (vb >= 0) t.emplace_back(vb, vb, w);
    if (va >= 0 && vb >= 0) t.emplace_back(va, vb, -w), t.emplace_back(vb, va, -w);
  };
  for (int i = 0; i < n; ++i) {
    if (i % p.w + 1 < p.w) edge(i, i + 1, p.weight_u[static_cast<std::size_t>(i)]);
    if (i / p.w + 1 < p.h) edge(i, i + p.w, p.weight_v[static_cast<std::size_t>(i)]);
  }
  Eigen::SparseMatrix<double> a(unknowns, unknowns);
  a.setFromTriplets(t.begin(), t.end());
  Eigen::VectorXd b(unknowns);
  for (int i = 0; i < n; ++i) {
    if (var[static_cast<std::size_t>(i)] >= 0) b[var[static_cast<std::size_t>(i)]] = p.rhs[i];
  }
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt(a);
  REQUIRE(ldlt.info() == Eigen::Success);
  const Eigen::VectorXd x = ldlt.solve(b);
  std::vector<double> out(static_cast<std::size_t>(n), 0.0);
  for (int i = 0; i < n; ++i) {
    if (var[static_cast<std::size_t>(i)] >= 0) out[i] = x[var[static_cast<std::size_t>(i)]];
  }
  return out;
}

double MaxDifference(const std::vector<double>& a, const std::vector<double>& b) {
  double worst = 0.0;
  for (std::size_t i = 0; i < a.size(); ++i) worst = std::max(worst, std::abs(a[i] - b[i]));
  return worst;
}

TEST_CASE("grid solver: matches a sparse LDLT on grids of every shape", "[recon][grid_solver]") {
  const std::vector<std::pair<int, int>> sizes = {{3, 3},  {3, 9},   {9, 3},   {4, 4},   {5, 40},
                                                  {40, 5}, {17, 23}, {60, 60}, {61, 33}, {3, 70}};
  std::uint32_t seed = 1;
  for (const auto& [w, h] : sizes) {
    CAPTURE(w, h);
    const Problem p = RandomProblem(w, h, seed++);
    GridLaplacianSolver solver(w, h);
    REQUIRE(solver.Factorize(p.weight_u, p.weight_v));
    std::vector<double> x = p.rhs;
    solver.Solve(&x);
    const std::vector<double> expected = Reference(p);
    double scale = 0.0;
    for (double v : expected) scale = std::max(scale, std::abs(v));
    CHECK(MaxDifference(x, expected) <= 1e-10 * std::max(1.0, scale));
    for (int i = 0; i < w * h; ++i) {
      if (!Interior(p, i)) CHECK(x[static_cast<std::size_t>(i)] == 0.0);
    }
  }
}

TEST_CASE("grid solver: refactorises with new weights and solves again", "[recon][grid_solver]") {
  GridLaplacianSolver solver(31, 27);
  for (std::uint32_t seed = 10; seed < 13; ++seed) {
    const Problem p = RandomProblem(31, 27, seed);
    REQUIRE(solver.Factorize(p.weight_u, p.weight_v));
    std::vector<double> x = p.rhs;
    solver.Solve(&x);
    CHECK(MaxDifference(x, Reference(p)) < 1e-9);
  }
}

TEST_CASE("grid solver: a unit load on unit weights has the grid's symmetries",
          "[recon][grid_solver]") {
  // Unit weights and a right-hand side of one unit load at the centre: the discrete Green's
  // function is symmetric under the grid's mirror symmetries.
  const int w = 21, h = 21;
  std::vector<double> ones(w * h, 1.0), x(w * h, 0.0);
  x[10 * w + 10] = 1.0;
  GridLaplacianSolver solver(w, h);
  REQUIRE(solver.Factorize(ones, ones));
  solver.Solve(&x);
  for (int y = 1; y < h - 1; ++y) {
    for (int xx = 1; xx < w - 1; ++xx) {
      const double v = x[y * w + xx];
      CHECK(v > 0.0);
      CHECK(std::abs(v - x[y * w + (w - 1 - xx)]) < 1e-12);
      CHECK(std::abs(v - x[xx * w + y]) < 1e-12);
    }
  }
}

TEST_CASE("grid solver: bad weights are refused and leave no factorisation",
          "[recon][grid_solver]") {
  Problem p = RandomProblem(12, 9, 7);
  GridLaplacianSolver solver(12, 9);
  for (double bad : {0.0, -1.0, std::numeric_limits<double>::quiet_NaN(),
                     std::numeric_limits<double>::infinity()}) {
    CAPTURE(bad);
    Problem q = p;
    q.weight_v[4 * 12 + 5] = bad;
    CHECK_FALSE(solver.Factorize(q.weight_u, q.weight_v));
    std::vector<double> x = q.rhs;
    CHECK_THROWS_AS(solver.Solve(&x), std::logic_error);
  }
  // An edge past the last column does not exist: its entry is ignored.
  p.weight_u[3 * 12 + 11] = std::numeric_limits<double>::quiet_NaN();
  CHECK(solver.Factorize(p.weight_u, p.weight_v));
  CHECK_THROWS_AS(GridLaplacianSolver(2, 10), std::invalid_argument);
  std::vector<double> short_weights(10, 1.0);
  CHECK_THROWS_AS(solver.Factorize(short_weights, short_weights), std::invalid_argument);
}

}  // namespace
}  // namespace gs360
