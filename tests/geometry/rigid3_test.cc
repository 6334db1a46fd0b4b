#include <catch2/catch.hpp>

#include "geometry/rigid3.h"

using gs360::Rigid3d;

TEST_CASE("Rigid3d composes and inverts by frame names", "[rigid3]") {
  const Rigid3d b_from_a = Rigid3d::FromAxisAngle({0, 0, 1}, M_PI / 2, {1, 0, 0});
  const Rigid3d c_from_b = Rigid3d::FromAxisAngle({1, 0, 0}, M_PI / 2, {0, 0, 2});
  const Eigen::Vector3d x_a(1, 2, 3);
  const Eigen::Vector3d x_b = b_from_a * x_a;
  CHECK(x_b.isApprox(Eigen::Vector3d(-2 + 1, 1, 3), 1e-12));
  const Rigid3d c_from_a = c_from_b * b_from_a;
  CHECK((c_from_a * x_a).isApprox(c_from_b * x_b, 1e-12));
  CHECK((c_from_a.Inverse() * (c_from_a * x_a)).isApprox(x_a, 1e-12));
}

TEST_CASE("Rigid3d angle and differences", "[rigid3]") {
  const Rigid3d a = Rigid3d::FromAxisAngle({1, 1, 0}, 0.3, {0, 0, 0});
  CHECK(a.AngleRad() == Approx(0.3).epsilon(1e-12));
  const Rigid3d b = Rigid3d::FromAxisAngle({1, 1, 0}, 0.3 + 1e-7, {0, 0, 1e-3});
  CHECK(gs360::RotationDifferenceRad(a, b) == Approx(1e-7).epsilon(1e-4));
  CHECK(gs360::TranslationDifferenceMm(a, b) == Approx(1e-3));
  CHECK(Rigid3d::FromMatrix(a.ToMatrix3x4()).ToMatrix4().isApprox(a.ToMatrix4(), 1e-12));
}
