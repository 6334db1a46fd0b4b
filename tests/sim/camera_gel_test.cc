// The gel deformation model and the refined, displaced patch the tactile camera ray-casts.
#include <catch2/catch.hpp>

#include <cmath>
#include <numbers>
#include <optional>

#include "camera_test_util.h"
#include "geometry/bvh.h"
#include "geometry/mesh.h"
#include "geometry/shapes.h"
#include "sim/gel_deformation.h"

using namespace gs360;
using namespace gs360::camera_test;

namespace {

struct Finger {
  SensorShapeOptions options;
  std::shared_ptr<const RevolutionProfile> profile = MakeProfile(options);
  TriangleMesh mesh = MakeSensorMesh(options);
};

const Finger& DefaultFinger() {
  static const Finger finger;
  return finger;
}

Eigen::Vector3d Ball(const RevolutionProfile& profile, double t, double phi_deg, double depth) {
  return profile.SurfacePoint(t, Deg(phi_deg)) +
         (2.0 - depth) * profile.SurfaceNormal(t, Deg(phi_deg));
}

}  // namespace

TEST_CASE("gel: penetration and the soft edge on a flat surface", "[sim][camera]") {
  const GelDeformationOptions options;  // w = 0.25
  const double h = 1.2;                 // ball centre 1.2 mm above the plane z = 0: 0.8 mm deep
  const BallIndentation ball(Eigen::Vector3d(0, 0, h), 2.0, options);
  const Eigen::Vector3d n(0, 0, 1);
  for (double rho = 0.0; rho < 3.5; rho += 0.05) {
    CAPTURE(rho);
    const Eigen::Vector3d x(rho, 0, 0);
    const double p = ball.Penetration(x, n);
    if (rho < 2.0) {
      // The normal line meets the ball: exactly the rigid depth (or minus the gap).
      CHECK(p == Approx(std::sqrt(4.0 - rho * rho) - h).margin(1e-12));
    }
    const double gap = (x - Eigen::Vector3d(0, 0, h)).norm() - 2.0;
    if (gap >= 0.0) CHECK(p <= -gap + 1e-12);  // outside the ball: at most minus the gap
    const double s = ball.SoftDepth(p);
    CHECK(s >= std::max(0.0, p) - 1e-15);
    if (p >= options.elastic_length) CHECK(s == p);     // rigid where deep
    if (p <= -options.elastic_length) CHECK(s == 0.0);  // untouched beyond w
  }
  // C1 at both ends of the soft zone.
  const double w = options.elastic_length, e = 1e-7;
  CHECK((ball.SoftDepth(w + e) - ball.SoftDepth(w - e)) / (2 * e) == Approx(1.0).margin(1e-5));
  CHECK((ball.SoftDepth(-w + e) - ball.SoftDepth(-w - e)) / (2 * e) == Approx(0.0).margin(1e-5));
  CHECK(ball.SoftDepth(0.0) == Approx(w / 4.0));
  // The bulge: zero inside the contact and far away, peak bulge_fraction * D halfway.
  const double D = 0.8;
  CHECK(ball.Bulge(Eigen::Vector3d(0, 0, 0), D) == 0.0);
  const double peak_gap = options.bulge_extent / 2.0;
  const double rho_peak = std::sqrt(std::pow(2.0 + peak_gap, 2) - h * h);
  CHECK(ball.Bulge(Eigen::Vector3d(rho_peak, 0, 0), D) == Approx(options.bulge_fraction * D));
  CHECK(ball.Bulge(Eigen::Vector3d(3.5, 0, 0), D) == 0.0);
  CHECK(ball.InfluenceRadius() == Approx(2.0 + options.bulge_extent));

  const BallIndentation rigid(Eigen::Vector3d(0, 0, h), 2.0, GelDeformationOptions::Rigid());
  CHECK(rigid.SoftDepth(-0.01) == 0.0);
  CHECK(rigid.SoftDepth(0.3) == 0.3);
  CHECK(rigid.Bulge(Eigen::Vector3d(rho_peak, 0, 0), D) == 0.0);
}

TEST_CASE("gel: the displaced patch follows the ball, with a soft edge and a bulge",
          "[sim][camera]") {
  const Finger& finger = DefaultFinger();
  const GelDeformationOptions options;
  const GelPatchBuilder builder(finger.mesh, options);
  const Eigen::Vector3d c = Ball(*finger.profile, 0.3, 45.0, 1.0);
  const DisplacedPatch patch = builder.Build(c, 2.0);
  REQUIRE(!patch.Empty());
  CHECK(patch.max_depth == Approx(1.0).margin(0.01));
  CHECK(patch.max_displacement == Approx(1.0).margin(0.01));
  double min_delta = 0.0;
  int firm = 0;
  for (std::size_t v = 0; v < patch.rest_vertices.size(); ++v) {
    const Eigen::Vector3d& x = patch.mesh.vertices[v];
    min_delta = std::min(min_delta, patch.displacement[v]);
    // Displaced along the smooth normal by delta (exactly, except for the vertices placed on a
    // coarser neighbour's edge, which are interpolated: off by second-order terms).
    CHECK((patch.rest_vertices[v] - patch.displacement[v] * patch.rest_normals[v] - x).norm() <
          1e-4);
    // Never inside the ball.
    CHECK((x - c).norm() > 2.0 - 1e-9);
    if (patch.penetration[v] > options.elastic_length + 0.05) {
      // Firm contact: on the ball, normal along the ball's radius (gel outward = toward c).
      CHECK((x - c).norm() == Approx(2.0).margin(1e-6));
      CHECK(patch.mesh.normals[v].dot((c - x).normalized()) > std::cos(Deg(3.0)));
      ++firm;
    }
  }
  CHECK(firm > 100);
  CHECK(min_delta < -0.5 * options.bulge_fraction * patch.max_depth);  // the bulge is there
  CHECK(min_delta > -1.01 * options.bulge_fraction * patch.max_depth);

  // Watertight: every ray that met a replaced triangle of the undeformed mesh meets the patch.
  const Bvh before(finger.mesh);
  const Bvh after(patch.mesh);
  const Eigen::Vector3d camera(0.0, 0.0, -1.5);
  const Eigen::Vector3d aim = finger.profile->SurfacePoint(0.3, Deg(45.0));
  const Eigen::Vector3d axis = (aim - camera).normalized();
  const Eigen::Vector3d e1 = axis.cross(Eigen::Vector3d::UnitZ()).normalized();
  const Eigen::Vector3d e2 = axis.cross(e1);
  int replaced_hits = 0;
  for (int i = -60; i <= 60; ++i) {
    for (int j = -60; j <= 60; ++j) {
      Ray ray;
      ray.origin = camera;
      ray.direction = (axis + 0.003 * i * e1 + 0.003 * j * e2).normalized();
      const auto hit = before.Intersect(ray);
      if (!hit || patch.replaced[hit->triangle] == 0) continue;
      ++replaced_hits;
      CHECK(after.Intersect(ray).has_value());
    }
  }
  CHECK(replaced_hits > 2000);
}

TEST_CASE("gel: the rigid model is the pipeline's sharp imprint", "[sim][camera]") {
  const Finger& finger = DefaultFinger();
  const GelPatchBuilder soft(finger.mesh, GelDeformationOptions{});
  const GelPatchBuilder rigid(finger.mesh, GelDeformationOptions::Rigid());
  const Eigen::Vector3d c = Ball(*finger.profile, 0.5, 200.0, 0.7);
  const DisplacedPatch s = soft.Build(c, 2.0), r = rigid.Build(c, 2.0);
  REQUIRE(!s.Empty());
  REQUIRE(!r.Empty());
  double area_soft = 0.0, area_rigid = 0.0;
  auto moved_area = [](const DisplacedPatch& p) {
    double a = 0.0;
    for (std::size_t t = 0; t < p.mesh.triangles.size(); ++t) {
      const Eigen::Vector3i& f = p.mesh.triangles[t];
      if (p.displacement[f[0]] > 1e-4 && p.displacement[f[1]] > 1e-4 &&
          p.displacement[f[2]] > 1e-4) {
        a += 0.5 * (p.rest_vertices[f[1]] - p.rest_vertices[f[0]])
                       .cross(p.rest_vertices[f[2]] - p.rest_vertices[f[0]])
                       .norm();
      }
    }
    return a;
  };
  area_soft = moved_area(s);
  area_rigid = moved_area(r);
  // Rigid: delta = max(0, p) exactly, so the moved area is the contact disc, pi (r^2 - h^2).
  for (std::size_t v = 0; v < r.rest_vertices.size(); ++v) {
    CHECK(r.displacement[v] == Approx(std::max(0.0, r.penetration[v])).margin(1e-12));
  }
  // On a convex wall the contact patch is smaller than the flat-surface disc pi (r^2 - h^2).
  const double h = 2.0 - 0.7;
  const double flat = std::numbers::pi * (4.0 - h * h);
  CHECK(area_rigid < flat);
  CHECK(area_rigid > 0.75 * flat);
  CHECK(area_soft > 1.15 * area_rigid);
}

TEST_CASE("gel: a ball clear of the surface deforms nothing, options are checked",
          "[sim][camera]") {
  const Finger& finger = DefaultFinger();
  const GelPatchBuilder builder(finger.mesh, GelDeformationOptions{});
  CHECK(builder.Build(Ball(*finger.profile, 0.4, 10.0, -1.0), 2.0).Empty());  // 1 mm away
  CHECK(builder.Build(Eigen::Vector3d(0, 0, 80), 2.0).Empty());
  CHECK(builder.TrianglesNear(Eigen::Vector3d(0, 0, 80), 3.0).empty());

  GelDeformationOptions bad;
  bad.elastic_length = -0.1;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("elastic_length"));
  bad = GelDeformationOptions{};
  bad.max_edge = 0.0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("max_edge"));
  TriangleMesh no_normals = finger.mesh;
  no_normals.normals.clear();
  CHECK_THROWS_AS(GelPatchBuilder(no_normals, GelDeformationOptions{}), std::invalid_argument);
}
