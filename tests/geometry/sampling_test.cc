#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <numeric>
#include <vector>

#include "geometry/sampling.h"
#include "geometry/shapes.h"
#include "tests/angles.h"

using namespace gs360;

namespace {

using gs360::test::kPi;

struct Finger {
  std::shared_ptr<const RevolutionProfile> profile = MakeCylinderCapProfile({});
  TriangleMesh mesh = MakeRevolutionMesh(*profile);  // small triangles at the tip fan
};

const Finger& TheFinger() {
  static const Finger f;
  return f;
}

// Archimedes: on a cylinder with a hemispherical cap of the same radius the area per unit
// height is 2 pi R everywhere, so equal z bands times equal azimuth sectors are equal-area
// regions. Returns Pearson's chi-square of the counts against the uniform expectation.
double ChiSquare(const std::vector<SurfaceSample>& s, double z_lo, double z_hi, int bands,
                 int sectors) {
  std::vector<int> counts(bands * sectors, 0);
  for (const auto& x : s) {
    const int b =
        std::min(bands - 1, static_cast<int>((x.point.z() - z_lo) / (z_hi - z_lo) * bands));
    const double phi = std::atan2(x.point.y(), x.point.x()) + kPi;
    const int k = std::min(sectors - 1, static_cast<int>(phi / (2 * kPi) * sectors));
    ++counts[b * sectors + k];
  }
  const double expected = static_cast<double>(s.size()) / counts.size();
  double chi2 = 0.0;
  for (int c : counts) chi2 += (c - expected) * (c - expected) / expected;
  return chi2;
}

}  // namespace

TEST_CASE("Blue-noise samples: count, spacing, determinism", "[sampling]") {
  const Finger& f = TheFinger();
  BlueNoiseOptions o;
  o.count = 4000;
  const auto a = SampleBlueNoise(f.mesh, o);
  REQUIRE(a.size() == 4000);
  // Minimum spacing against the hexagonal-packing distance 2 sqrt(A / (2 sqrt(3) N)). Weighted
  // sample elimination with 5x candidates gives ~0.69 here; independent uniform points ~0.01.
  const double ideal = IdealBlueNoiseSpacing(f.mesh.Area(), 4000);
  CHECK(ideal == Approx(2.0 * std::sqrt(f.mesh.Area() / (2.0 * std::sqrt(3.0) * 4000))));
  CHECK(MinimumSpacing(a) >= 0.6 * ideal);
  CHECK(MinimumSpacing(SampleUniform(f.mesh, 4000, 1)) < 0.1 * ideal);

  // Same seed, same points; another seed, other points.
  const auto b = SampleBlueNoise(f.mesh, o);
  bool identical = true;
  for (std::size_t i = 0; i < a.size(); ++i) identical = identical && a[i].point == b[i].point;
  CHECK(identical);
  o.seed = 2;
  const auto c = SampleBlueNoise(f.mesh, o);
  int same = 0;
  for (std::size_t i = 0; i < a.size(); ++i) same += a[i].point == c[i].point;
  CHECK(same < 10);

  // Samples lie on their triangles, with unit smooth normals close to the analytic ones.
  for (const auto& s : a) {
    const Eigen::Vector3i& t = f.mesh.triangles[s.triangle];
    const Eigen::Vector3d p = (1 - s.b1 - s.b2) * f.mesh.vertices[t[0]] +
                              s.b1 * f.mesh.vertices[t[1]] + s.b2 * f.mesh.vertices[t[2]];
    CHECK((p - s.point).norm() < 1e-12);
    CHECK(s.normal.norm() == Approx(1.0));
    CHECK(s.normal.dot(f.profile->ClosestPoint(s.point).normal) > std::cos(2.0 * kPi / 180.0));
  }
}

TEST_CASE("Blue-noise and uniform samples are area-uniform", "[sampling]") {
  const Finger& f = TheFinger();
  BlueNoiseOptions o;
  o.count = 4000;
  const auto blue = SampleBlueNoise(f.mesh, o);
  const auto white = SampleUniform(f.mesh, 4000, 5);
  // 10 height bands x 8 sectors = 80 equal-area regions of 50 expected points. Chi-square with
  // 79 degrees of freedom exceeds 124.8 with probability 0.001 for truly uniform independent
  // points; blue noise is far more even than that (its counts barely fluctuate).
  const double chi_blue = ChiSquare(blue, 0.0, 30.0, 10, 8);
  const double chi_white = ChiSquare(white, 0.0, 30.0, 10, 8);
  CHECK(chi_white < 124.8);
  CHECK(chi_blue < 40.0);
  // Sampling each triangle equally (ignoring area) would crowd the small tip triangles: the
  // test above detects it.
  std::vector<SurfaceSample> per_triangle;
  for (int i = 0; i < 4000; ++i) {
    SurfaceSample s;
    s.triangle = (i * 7919) % f.mesh.NumTriangles();
    const auto& t = f.mesh.triangles[s.triangle];
    s.point = (f.mesh.vertices[t[0]] + f.mesh.vertices[t[1]] + f.mesh.vertices[t[2]]) / 3.0;
    per_triangle.push_back(s);
  }
  CHECK(ChiSquare(per_triangle, 0.0, 30.0, 10, 8) > 124.8);
}

TEST_CASE("Blue-noise sampling of a region given by a predicate", "[sampling]") {
  const Finger& f = TheFinger();
  BlueNoiseOptions o;
  o.count = 2000;
  int calls = 0;
  const auto cap = SampleBlueNoise(f.mesh, o, [&](const SurfaceSample& s) {
    ++calls;
    return s.point.z() > 20.0;
  });
  REQUIRE(cap.size() == 2000);
  CHECK(calls >= 2000 * 5);
  for (const auto& s : cap) CHECK(s.point.z() > 20.0);
  // Spacing relative to the region's area (the hemisphere: 2 pi R^2), not the whole finger's.
  const double region_area = 2.0 * kPi * 100.0;
  CHECK(MinimumSpacing(cap) >= 0.6 * IdealBlueNoiseSpacing(region_area, 2000));
  CHECK(ChiSquare(cap, 20.0, 30.0, 5, 8) < 40.0);

  // A region too small to supply the candidates: fewer samples, all inside it.
  const auto tiny =
      SampleBlueNoise(f.mesh, o, [](const SurfaceSample& s) { return s.point.z() > 29.99; });
  CHECK(tiny.size() < 2000);
  CHECK(!tiny.empty());
  for (const auto& s : tiny) CHECK(s.point.z() > 29.99);
  CHECK(SampleBlueNoise(f.mesh, o, [](const SurfaceSample&) { return false; }).empty());
}

TEST_CASE("Sampling options and degenerate input", "[sampling]") {
  const Finger& f = TheFinger();
  BlueNoiseOptions o;
  o.count = -1;
  CHECK_THROWS_WITH(SampleBlueNoise(f.mesh, o), Catch::Contains("BlueNoiseOptions.count"));
  o = {};
  o.candidate_factor = 0.5;
  CHECK_THROWS_WITH(o.Check(), Catch::Contains("BlueNoiseOptions.candidate_factor"));
  o = {};
  o.count = 0;
  CHECK(SampleBlueNoise(f.mesh, o).empty());
  TriangleMesh flat;
  flat.vertices = {{0, 0, 0}, {1, 0, 0}, {2, 0, 0}};
  flat.triangles = {{0, 1, 2}};
  CHECK_THROWS_WITH(SampleBlueNoise(flat, {}), Catch::Contains("zero area"));
  CHECK(IdealBlueNoiseSpacing(100.0, 0) == 0.0);
  CHECK(MinimumSpacing({}) == std::numeric_limits<double>::infinity());
  std::vector<SurfaceSample> two(2);
  two[1].point = Eigen::Vector3d(3, 4, 0);
  CHECK(MinimumSpacing(two) == Approx(5.0));
}

TEST_CASE("Farthest-point order: every prefix covers the whole set evenly", "[sampling]") {
  const Finger& f = TheFinger();
  BlueNoiseOptions o;
  o.count = 1200;
  std::vector<Eigen::Vector3d> points;
  for (const SurfaceSample& s : SampleBlueNoise(f.mesh, o)) points.push_back(s.point);
  const std::vector<int> order = FarthestPointOrder(points, 7);
  REQUIRE(order.size() == points.size());
  CHECK(order.front() == 7);
  std::vector<int> sorted = order;
  std::sort(sorted.begin(), sorted.end());
  for (int i = 0; i < static_cast<int>(sorted.size()); ++i) REQUIRE(sorted[i] == i);
  // The candidate-draw order (what the sampler returns) against the progressive one: a prefix
  // of either is a k-point subset; the progressive prefix leaves no part of the surface far
  // from it. Against the hexagonal spacing of k points, its covering radius stays within a
  // small factor; the draw order's prefixes leave holes several spacings wide.
  std::vector<int> draw(points.size());
  std::iota(draw.begin(), draw.end(), 0);
  for (const int k : {50, 150, 400}) {
    const double spacing = IdealBlueNoiseSpacing(f.mesh.Area(), k);
    const double progressive = PrefixCoveringRadius(points, order, k);
    INFO("k " << k << " spacing " << spacing << " progressive " << progressive << " draw "
              << PrefixCoveringRadius(points, draw, k));
    CHECK(progressive < 1.0 * spacing);
    CHECK(PrefixCoveringRadius(points, draw, k) > 1.3 * progressive);
  }
  CHECK(PrefixCoveringRadius(points, order, static_cast<int>(points.size())) == 0.0);
  // Deterministic, and the degenerate cases.
  CHECK(FarthestPointOrder(points, 7) == order);
  CHECK(FarthestPointOrder({}).empty());
  CHECK(FarthestPointOrder({Eigen::Vector3d::Zero()}) == std::vector<int>{0});
  CHECK_THROWS_WITH(FarthestPointOrder(points, -1), Catch::Contains("first = -1"));
  CHECK_THROWS_AS(PrefixCoveringRadius(points, order, 0), std::invalid_argument);
}
