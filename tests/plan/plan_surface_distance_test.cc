// The planner's signed distance to the sensor surface: polyline of the profile and mesh BVH,
// against the analytic closest point and brute force.

#include <catch2/catch.hpp>
#include <cmath>
#include <cstdint>
#include <limits>

#include "plan/surface_distance.h"
#include "tests/plan/lcg.h"

using namespace gs360;

using test::Lcg;

TEST_CASE("Profile distance matches the analytic closest point", "[plan]") {
  for (SensorShape shape : {SensorShape::kCylinderCap, SensorShape::kCone, SensorShape::kSpline}) {
    SensorShapeOptions so;
    so.shape = shape;
    const auto profile = MakeProfile(so);
    const SurfaceDistance d = SurfaceDistance::FromProfile(profile);
    CHECK(d.IsRevolution());
    Lcg rng{static_cast<std::uint64_t>(shape) + 3};
    for (int i = 0; i < 150; ++i) {
      const Eigen::Vector3d p(30 * rng.Uniform() - 15, 30 * rng.Uniform() - 15,
                              1 + 35 * rng.Uniform());
      const auto exact = profile->ClosestPoint(p);
      const auto ours = d.ClosestPoint(p);
      INFO(profile->Describe() << " p " << p.transpose());
      CHECK(d.Signed(p) == Approx(exact.signed_distance).margin(1e-4));
      CHECK(ours.signed_distance == Approx(exact.signed_distance).margin(1e-4));
      // The returned point is on the exact surface and its normal is exact there.
      CHECK(std::abs(profile->ClosestPoint(ours.point).signed_distance) < 1e-9);
      CHECK((ours.point - exact.point).norm() < 1e-3);
      CHECK(ours.normal.dot(exact.normal) > 0.9999);
    }
    // Radii: RadiusAt and MaxRadius against the profile.
    for (double z = 0.0; z <= profile->Height(); z += 0.37) {
      CHECK(d.RadiusAt(z) == Approx(profile->RadiusAt(z)).margin(1e-4));
    }
    std::vector<double> table;  // RadiusAt every 0.01 mm
    for (double z = 0.0; z <= profile->Height(); z += 0.01) table.push_back(profile->RadiusAt(z));
    for (int i = 0; i < 50; ++i) {
      const double z0 = 40 * rng.Uniform() - 5, z1 = z0 + 20 * rng.Uniform();
      const double lo = std::max(z0, 0.0), hi = std::min(z1, profile->Height());
      double brute = -std::numeric_limits<double>::infinity();
      if (lo <= hi) brute = std::max(profile->RadiusAt(lo), profile->RadiusAt(hi));
      for (int k = static_cast<int>(std::ceil(lo / 0.01));
           k < static_cast<int>(table.size()) && k * 0.01 <= hi; ++k) {
        brute = std::max(brute, table[k]);
      }
      if (std::isinf(brute)) {
        CHECK(std::isinf(d.MaxRadius(z0, z1)));
      } else {
        CHECK(d.MaxRadius(z0, z1) == Approx(brute).margin(2e-3));
      }
    }
  }
}

TEST_CASE("Mesh distance agrees with the profile up to the tessellation error", "[plan]") {
  SensorShapeOptions so;
  so.shape = SensorShape::kSpline;
  const auto profile = MakeProfile(so);
  const TriangleMesh mesh = MakeSensorMesh(so);
  const SurfaceDistance m = SurfaceDistance::FromMesh(mesh);
  CHECK_FALSE(m.IsRevolution());
  CHECK_THROWS_AS(m.RadiusAt(1.0), std::logic_error);
  Lcg rng{11};
  int inside = 0, outside = 0;
  for (int i = 0; i < 400; ++i) {
    const Eigen::Vector3d p(30 * rng.Uniform() - 15, 30 * rng.Uniform() - 15,
                            0.5 + 34 * rng.Uniform());
    const double exact = profile->ClosestPoint(p).signed_distance;
    INFO("p " << p.transpose());
    CHECK(m.Signed(p) == Approx(exact).margin(0.02));  // chord error of the default tessellation
    if (std::abs(exact) > 0.05) CHECK((m.Signed(p) > 0) == (exact > 0));
    (exact < 0 ? inside : outside)++;
  }
  CHECK(inside > 20);
  CHECK(outside > 20);
  // Brute force over all triangles for a few points.
  for (int i = 0; i < 5; ++i) {
    const Eigen::Vector3d p(20 * rng.Uniform() - 10, 20 * rng.Uniform() - 10, 30 * rng.Uniform());
    Eigen::Vector3d closest;
    const double d = std::abs(m.Signed(p, &closest));
    double best = 1e9;
    for (const Eigen::Vector3d& v : mesh.vertices) best = std::min(best, (v - p).norm());
    CHECK(d <= best + 1e-12);  // never farther than the nearest vertex
    CHECK(std::abs((closest - p).norm() - d) < 1e-12);
  }
  CHECK_THROWS_AS(SurfaceDistance::FromMesh(TriangleMesh{}), std::invalid_argument);
  CHECK_THROWS_AS(SurfaceDistance::FromProfile(nullptr), std::invalid_argument);
}
