#include <catch2/catch.hpp>

#include <cmath>
#include <numbers>

#include "geometry/bvh.h"
#include "geometry/mesh.h"
#include "geometry/shapes.h"
#include "tests/angles.h"

using namespace gs360;

namespace {

using gs360::test::kPi;

SensorShapeOptions ShapeOptions(SensorShape shape) {
  SensorShapeOptions o;
  o.shape = shape;
  o.tessellation.segments = 96;
  return o;
}

// Volume of the surface of revolution closed by the base disc: integral of pi r(z)^2 dz.
double ProfileVolume(const RevolutionProfile& p) {
  const int n = 20000;
  const double h = p.Height();
  double v = 0.0;
  for (int i = 0; i < n; ++i) {
    const double z = (i + 0.5) * h / n;
    const double r = p.RadiusAt(z);
    v += kPi * r * r * h / n;
  }
  return v;
}

}  // namespace

TEST_CASE("Built-in shapes are closed except at the base and face outward", "[shapes]") {
  for (SensorShape shape : {SensorShape::kCylinderCap, SensorShape::kCone, SensorShape::kSpline}) {
    INFO(SensorShapeName(shape));
    const SensorShapeOptions opt = ShapeOptions(shape);
    const auto profile = MakeProfile(opt);
    TriangleMesh mesh = MakeSensorMesh(opt);
    const TriangleMesh before = mesh;
    const MeshReport r = ValidateAndRepair(mesh);
    CHECK(r.problems.empty());
    CHECK(r.fixes.empty());
    CHECK(mesh.Hash() == before.Hash());
    CHECK(r.components == 1);
    CHECK(r.boundary_edges == 96);
    CHECK(r.boundary_edges_on_base == 96);
    CHECK(r.Ok());
    // Counts documented in the header.
    const int rings = (mesh.NumVertices() - 1) / 96;
    CHECK(mesh.NumVertices() == 96 * rings + 1);
    CHECK(mesh.NumTriangles() == 96 * (2 * rings - 1));
    // Vertices on the analytic profile; z = 0 only on the rim; the tip on the axis.
    for (int i = 0; i < mesh.NumVertices(); ++i) {
      const Eigen::Vector3d& v = mesh.vertices[i];
      CHECK(std::hypot(v.x(), v.y()) == Approx(profile->RadiusAt(v.z())).margin(1e-9));
      CHECK((i < 96) == (v.z() == 0.0));
    }
    CHECK(mesh.vertices.back() == Eigen::Vector3d(0, 0, profile->Height()));
    // Exact normals: unit, outward (agree with the faceted mesh's own normals to a few degrees).
    TriangleMesh faceted = mesh;
    faceted.ComputeVertexNormals();
    for (int i = 96; i < mesh.NumVertices(); ++i) {
      CHECK(mesh.normals[i].norm() == Approx(1.0).epsilon(1e-12));
      CHECK(mesh.normals[i].dot(faceted.normals[i]) > std::cos(5.0 * kPi / 180.0));
    }
    // Enclosed volume and area match the analytic surface (faceting error < 0.5%).
    CHECK(mesh.SignedVolume() == Approx(ProfileVolume(*profile)).epsilon(5e-3));
    CHECK(mesh.Area() == Approx(profile->SurfaceArea()).epsilon(5e-3));
  }
}

TEST_CASE("Cylinder with a hemispherical cap matches its closed form", "[shapes]") {
  CylinderCapOptions o;
  o.radius = 10.0;
  o.height = 30.0;
  const auto p = MakeCylinderCapProfile(o);
  CHECK(p->Height() == 30.0);
  CHECK(p->BaseRadius() == 10.0);
  CHECK(p->RadiusAt(0.0) == Approx(10.0));
  CHECK(p->RadiusAt(19.99) == Approx(10.0));
  for (double z : {20.5, 25.0, 29.0, 29.99}) {
    CHECK(p->RadiusAt(z) == Approx(std::sqrt(100.0 - (z - 20.0) * (z - 20.0))).epsilon(1e-10));
  }
  CHECK(p->RadiusAt(30.0) == 0.0);
  CHECK(p->ArcLength() == Approx(20.0 + 5.0 * kPi).epsilon(1e-9));
  // Archimedes: the area is 2 pi R per mm of height, cap included.
  CHECK(p->SurfaceArea() == Approx(2.0 * kPi * 10.0 * 30.0).epsilon(1e-8));
  // Normals: radial on the wall, from the cap centre on the cap.
  const double t_cap = p->ParameterAtZ(25.0);
  const Eigen::Vector2d q = p->Point(t_cap);
  CHECK(p->Normal(t_cap).isApprox((q - Eigen::Vector2d(0, 20)).normalized(), 1e-12));
  CHECK(p->Normal(p->ParameterAtZ(10.0)).isApprox(Eigen::Vector2d(1, 0)));
  CHECK(p->Normal(1.0).isApprox(Eigen::Vector2d(0, 1)));
  // Closest point and signed distance.
  const auto c = p->ClosestPoint(Eigen::Vector3d(0.0, 12.0, 10.0));
  CHECK(c.signed_distance == Approx(2.0).epsilon(1e-9));
  CHECK(c.point.isApprox(Eigen::Vector3d(0, 10, 10), 1e-9));
  CHECK(c.normal.isApprox(Eigen::Vector3d(0, 1, 0), 1e-9));
  const auto inside = p->ClosestPoint(Eigen::Vector3d(3.0, 4.0, 25.0));  // |r| = 5 at the cap
  const double d_cap = std::hypot(5.0, 5.0);
  CHECK(inside.signed_distance == Approx(d_cap - 10.0).epsilon(1e-8));
  CHECK(p->ClosestPoint(Eigen::Vector3d(0, 0, 33)).signed_distance == Approx(3.0).epsilon(1e-9));

  CylinderCapOptions bad;
  bad.height = 5.0;
  CHECK_THROWS_WITH(bad.Check(),
                    Catch::Contains("CylinderCapOptions.height") && Catch::Contains("5"));
  bad = {};
  bad.radius = -1.0;
  CHECK_THROWS_WITH(MakeCylinderCapProfile(bad), Catch::Contains("CylinderCapOptions.radius"));
}

TEST_CASE("Cone with a rounded tip: straight side tangent to the tip sphere", "[shapes]") {
  ConeOptions o;  // base 10, height 30, tip radius 3
  const auto p = MakeConeProfile(o);
  CHECK(p->Height() == Approx(30.0));
  CHECK(p->BaseRadius() == 10.0);
  // The tip sphere: centre (0, 27), radius 3.
  const double z_top = 29.5;
  CHECK(p->RadiusAt(z_top) == Approx(std::sqrt(9.0 - 2.5 * 2.5)).epsilon(1e-10));
  // The side is a straight line: r is linear in z below the tangent point.
  const double r1 = p->RadiusAt(2.0), r2 = p->RadiusAt(8.0), r3 = p->RadiusAt(14.0);
  CHECK(r2 - r1 == Approx(r3 - r2).epsilon(1e-10));
  CHECK(r1 > r2);
  // The side's normal is constant and perpendicular to the side; the line is tangent to the
  // sphere: its distance to the sphere centre is the tip radius.
  const Eigen::Vector2d a = p->Point(p->ParameterAtZ(2.0)), b = p->Point(p->ParameterAtZ(14.0));
  const Eigen::Vector2d n = p->Normal(p->ParameterAtZ(8.0));
  CHECK(n.dot((b - a).normalized()) == Approx(0.0).margin(1e-12));
  CHECK(n.dot(Eigen::Vector2d(0, 27) - a) == Approx(-3.0).epsilon(1e-9));
  CHECK(n.y() > 0.0);
  // Normal continuity across the tangent point (no kink).
  for (int i = 1; i < 2000; ++i) {
    const double t0 = (i - 1) / 2000.0, t1 = i / 2000.0;
    CHECK(p->Normal(t0).dot(p->Normal(t1)) > std::cos(0.01));
  }
  ConeOptions bad;
  bad.tip_radius = 12.0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("ConeOptions.tip_radius"));
}

TEST_CASE("Spline of revolution: through its control points, smooth, rounded tip", "[shapes]") {
  const SplineOptions o;
  const auto p = MakeSplineProfile(o);
  CHECK(p->Height() == Approx(30.0));
  for (const auto& cp : o.control_points) {
    CHECK(p->RadiusAt(cp.x()) == Approx(cp.y()).margin(1e-9));
  }
  // Monotone interpolation: no overshoot between control points.
  for (std::size_t i = 0; i + 1 < o.control_points.size(); ++i) {
    const double lo = std::min(o.control_points[i].y(), o.control_points[i + 1].y());
    const double hi = std::max(o.control_points[i].y(), o.control_points[i + 1].y());
    for (int k = 1; k < 50; ++k) {
      const double z = o.control_points[i].x() +
                       (o.control_points[i + 1].x() - o.control_points[i].x()) * k / 50;
      const double r = p->RadiusAt(z);
      CHECK(r >= lo - 1e-12);
      CHECK(r <= hi + 1e-12);
    }
  }
  // C1: the normal turns smoothly everywhere, and the tip is horizontal (normal +z) with a
  // finite curvature: r^2 ~ c (H - z) near the tip with c = -slope of the last interval.
  for (int i = 1; i <= 4000; ++i) {
    CHECK(p->Normal((i - 1) / 4000.0).dot(p->Normal(i / 4000.0)) > std::cos(0.02));
  }
  CHECK(p->Normal(1.0).isApprox(Eigen::Vector2d(0, 1)));
  CHECK(p->Normal(1.0 - 1e-7).y() > 0.99999);
  const double c = 5.5 * 5.5 / 3.0;
  CHECK(p->RadiusAt(30.0 - 1e-4) == Approx(std::sqrt(c * 1e-4)).epsilon(1e-3));
  // Normal really is the profile's normal: perpendicular to a finite-difference tangent.
  for (double t : {0.1, 0.3, 0.5, 0.7, 0.9, 0.99}) {
    const Eigen::Vector2d tan = (p->Point(t + 1e-6) - p->Point(t - 1e-6)).normalized();
    CHECK(std::abs(p->Normal(t).dot(tan)) < 1e-6);
  }

  SplineOptions bad;
  bad.control_points = {{0, 10}, {10, 8}, {5, 6}, {20, 0}};
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("control_points[2].z"));
  bad.control_points = {{0, 10}, {10, 8}, {20, 1}};
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("control_points[2].r"));
  bad.control_points = {{1, 10}, {20, 0}};
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("control_points[0].z"));
}

TEST_CASE("Tessellation resolution and the shape factory", "[shapes]") {
  const auto p = MakeCylinderCapProfile({});
  const TessellationOptions t = TessellationOptions::ForTriangleCount(*p, 200000);
  const TriangleMesh big = MakeRevolutionMesh(*p, t);
  CHECK(big.NumTriangles() > 190000);
  CHECK(big.NumTriangles() < 210000);
  TessellationOptions bad;
  bad.segments = 2;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("TessellationOptions.segments"));

  CHECK(ParseSensorShape("cylinder") == SensorShape::kCylinderCap);
  CHECK(ParseSensorShape("Cylinder-Cap") == SensorShape::kCylinderCap);
  CHECK(ParseSensorShape("cone") == SensorShape::kCone);
  CHECK(ParseSensorShape("spline") == SensorShape::kSpline);
  CHECK_THROWS_WITH(ParseSensorShape("banana"),
                    Catch::Contains("banana") && Catch::Contains("cylinder, cone or spline"));
  for (SensorShape s : {SensorShape::kCylinderCap, SensorShape::kCone, SensorShape::kSpline}) {
    CHECK(ParseSensorShape(SensorShapeName(s)) == s);
  }
  SensorShapeOptions so;
  so.shape = SensorShape::kCone;
  so.cone.base_radius = 8.0;
  CHECK(MakeProfile(so)->BaseRadius() == 8.0);
  CHECK_THAT(MakeProfile(so)->Describe(), Catch::Contains("cone"));
}

TEST_CASE("LED fins: two closed orthogonal slabs inside the inner wall", "[shapes]") {
  const auto p = MakeCylinderCapProfile({});
  FinOptions o;  // thickness 0.45, inset 1.5
  TriangleMesh xz = MakeFin(o, *p, FinPlane::kXZ);
  TriangleMesh yz = MakeFin(o, *p, FinPlane::kYZ);
  for (const TriangleMesh* fin : {&xz, &yz}) {
    TriangleMesh m = *fin;
    const MeshReport r = ValidateAndRepair(m);
    CHECK(r.boundary_edges == 0);
    CHECK(r.non_manifold_edges == 0);
    CHECK(r.reoriented_components == 0);
    CHECK(r.flipped_triangles == 0);
    CHECK(r.components == 1);
    CHECK(r.Ok());
  }
  // Thickness and orientation: the xz fin spans |y| = 0.225, the yz fin |x| = 0.225.
  for (const auto& v : xz.vertices) CHECK(std::abs(v.y()) == Approx(0.225));
  for (const auto& v : yz.vertices) CHECK(std::abs(v.x()) == Approx(0.225));
  CHECK(xz.Bounds().max().x() == Approx(8.5));
  CHECK(yz.Bounds().max().y() == Approx(8.5));
  CHECK(xz.Bounds().min().z() == 0.0);
  CHECK(xz.Bounds().max().z() == Approx(28.5).epsilon(1e-9));
  // Volume = thickness * outline area; outline = 2 * (8.5 * 20 + quarter disc of radius 8.5).
  const double outline_area = 2.0 * (8.5 * 20.0 + 0.25 * kPi * 8.5 * 8.5);
  CHECK(xz.SignedVolume() == Approx(0.45 * outline_area).epsilon(2e-3));
  // Every fin vertex is inside the wall by at least the inset (up to facet error).
  for (const auto& v : xz.vertices) {
    CHECK(p->ClosestPoint(Eigen::Vector3d(v.x(), 0.0, v.z())).signed_distance <= -1.5 + 1e-6);
  }
  CHECK(FinHalfWidthAt(o, *p, 10.0) == Approx(8.5));
  CHECK(FinHalfWidthAt(o, *p, 20.0 + 8.5 * std::sin(kPi / 6)) ==
        Approx(8.5 * std::cos(kPi / 6)).epsilon(1e-9));
  CHECK(FinHalfWidthAt(o, *p, 29.0) == 0.0);

  const TriangleMesh both = MakeFins(o, *p);
  CHECK(both.NumTriangles() == xz.NumTriangles() + yz.NumTriangles());
  CHECK(both.vertices[xz.NumVertices()] == yz.vertices[0]);

  // Cut flat at top_z and started at bottom_z.
  FinOptions cut = o;
  cut.bottom_z = 2.0;
  cut.top_z = 22.0;
  const TriangleMesh c = MakeFin(cut, *p, FinPlane::kXZ);
  CHECK(c.Bounds().min().z() == Approx(2.0));
  CHECK(c.Bounds().max().z() == Approx(22.0));
  TriangleMesh cc = c;
  CHECK(ValidateAndRepair(cc).boundary_edges == 0);

  // Cone: the inner wall is slanted; fins follow it and start at the base plane.
  const auto cone = MakeConeProfile({});
  const TriangleMesh cf = MakeFin(o, *cone, FinPlane::kYZ);
  CHECK(cf.Bounds().min().z() == Approx(0.0).margin(1e-12));
  for (const auto& v : cf.vertices) {
    CHECK(cone->ClosestPoint(Eigen::Vector3d(0.0, v.y(), v.z())).signed_distance <= -1.5 + 1e-6);
  }
  // An inset larger than the cone's tip radius folds the outline over.
  FinOptions deep = o;
  deep.inset = 4.0;
  CHECK_THROWS_WITH(MakeFin(deep, *cone, FinPlane::kXZ), Catch::Contains("FinOptions.inset"));
  FinOptions thin = o;
  thin.thickness = 0.0;
  CHECK_THROWS_WITH(MakeFins(thin, *p), Catch::Contains("FinOptions.thickness"));
}

TEST_CASE("FitInscribedProfile recovers a built-in profile from its mesh", "[shapes][fit]") {
  gs360::SensorShapeOptions options;  // cylinder r = 10, h = 30 with a hemispherical cap
  const auto profile = gs360::MakeProfile(options);
  const gs360::Bvh bvh(gs360::MakeRevolutionMesh(*profile, {}));
  const gs360::SplineOptions fit = gs360::FitInscribedProfile(bvh, 24);
  REQUIRE(fit.control_points.size() == 25);
  CHECK(fit.control_points.back().x() == Approx(30.0).margin(1e-3));
  CHECK(fit.control_points.back().y() == 0.0);
  for (const auto& p : fit.control_points) {
    if (p.x() > 0.0 && p.x() < 29.0) {
      // Inscribed: at or just inside the exact wall (the mesh's chords are inside the circle).
      CHECK(p.y() <= profile->RadiusAt(p.x()) + 1e-9);
      CHECK(p.y() >= profile->RadiusAt(p.x()) - 0.01);
    }
  }
  CHECK_THROWS_AS(gs360::FitInscribedProfile(gs360::Bvh(gs360::TriangleMesh{}), 24),
                  std::invalid_argument);
}

TEST_CASE("Fins end below where their outline would fold, and cut there they build", "[shapes]") {
  FinOptions o;  // inset 1.5
  const auto cylinder = MakeCylinderCapProfile({});
  CHECK(std::isinf(FinFoldZ(o, *cylinder)));
  // A tip that narrows by 3.6 mm over the last 3 mm: the 1.5 mm inset folds there.
  SplineOptions knee;
  knee.control_points = {{0.0, 10.0}, {20.0, 9.5}, {40.0, 8.0}, {54.0, 5.5}, {56.8, 3.7},
                         {57.5, 2.4}, {58.0, 1.2}, {58.3, 0.3}, {58.4, 0.0}};
  const auto folded = MakeSplineProfile(knee);
  const double fold_z = FinFoldZ(o, *folded);
  REQUIRE(std::isfinite(fold_z));
  CHECK(fold_z > 40.0);
  CHECK(fold_z < 58.4);
  CHECK_THROWS_WITH(MakeFins(o, *folded),
                    Catch::Contains("folds over") && Catch::Contains("top_z"));
  o.top_z = fold_z - 1.0;
  const TriangleMesh fins = MakeFins(o, *folded);
  CHECK(fins.Bounds().max().z() == Approx(fold_z - 1.0));
  CHECK(FinHalfWidthAt(o, *folded, fold_z - 2.0) > 0.0);
  CHECK(FinHalfWidthAt(o, *folded, fold_z - 0.5) == 0.0);
}
