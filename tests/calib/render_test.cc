#include "calib/render.h"

#include <catch2/catch.hpp>
#include <cmath>
#include <memory>
#include <numbers>

#include <opencv2/core.hpp>

#include "geometry/bvh.h"
#include "geometry/mesh.h"
#include "recon/surface_map.h"

namespace gs360 {
namespace {

// A flat gel plate at sensor z = plate_z facing +z (outward = away from the camera), seen by the
// nominal 160-degree camera on the axis at sensor z = -1.5 (cam_from_sensor: identity rotation).
constexpr double kPlateZ = 10.0;
constexpr double kCameraZ = -1.5;
constexpr double kPlateCam = kPlateZ - kCameraZ;  // plate distance in the camera frame
constexpr double kRadius = 2.0;

TriangleMesh Plate(double z, double half, int cells) {
  TriangleMesh mesh;
  for (int j = 0; j <= cells; ++j) {
    for (int i = 0; i <= cells; ++i) {
      mesh.vertices.emplace_back(-half + 2.0 * half * i / cells, -half + 2.0 * half * j / cells, z);
      mesh.normals.emplace_back(0.0, 0.0, 1.0);
    }
  }
  for (int j = 0; j < cells; ++j) {
    for (int i = 0; i < cells; ++i) {
      const int a = j * (cells + 1) + i;
      mesh.triangles.emplace_back(a, a + 1, a + cells + 2);  // CCW seen from +z
      mesh.triangles.emplace_back(a, a + cells + 2, a + cells + 1);
    }
  }
  return mesh;
}

struct PlateScene {
  FisheyeCamera camera;
  Rigid3d cam_from_sensor{Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.0, 0.0, -kCameraZ)};
  SurfaceMap map;
  PlateScene() {
    const Bvh plate(Plate(kPlateZ, 200.0, 40));
    map = SurfaceMap::Build(camera, cam_from_sensor, plate, nullptr);
  }
};

const PlateScene& Scene() {
  static const auto* scene = new PlateScene();
  return *scene;
}

// Entry distance of a ray into the ball (NaN if missed), in double precision.
double BallEntry(const Eigen::Vector3d& d, const Eigen::Vector3d& c, double r) {
  const double b = d.dot(c);
  const double disc = b * b - c.squaredNorm() + r * r;
  return disc < 0.0 ? std::nan("") : b - std::sqrt(disc);
}

TEST_CASE("RenderProbe: a ball pressed head-on into a flat plate", "[render]") {
  const PlateScene& s = Scene();
  const double depth = 1.0;
  const Eigen::Vector3d c(0.0, 0.0, kPlateCam + kRadius - depth);
  const ProbeRender pr = RenderProbe(s.map, s.camera, c, kRadius);
  REQUIRE(!pr.roi.empty());
  REQUIRE(pr.contact.size() == pr.roi.size());

  // The contact is the disc of rays inside the circle where the sphere cuts the plate:
  // radius a = sqrt(r^2 - (r - depth)^2) at distance kPlateCam.
  const double a = std::sqrt(kRadius * kRadius - (kRadius - depth) * (kRadius - depth));
  const double theta_edge = std::atan2(a, kPlateCam);
  int checked = 0, expected_contact = 0;
  double max_rho_error = 0.0, max_normal_error = 0.0, max_slope_error = 0.0;
  for (int y = 0; y < pr.roi.height; ++y) {
    for (int x = 0; x < pr.roi.width; ++x) {
      const int u = pr.roi.x + x, v = pr.roi.y + y;
      const Eigen::Vector3d d = *s.camera.PixelToRay(Eigen::Vector2d(u, v));
      const double theta = std::acos(d.z());
      const bool in_contact = pr.contact.at<std::uint8_t>(y, x) == 255;
      if (std::abs(theta - theta_edge) > 1e-4) {
        CHECK(in_contact == (theta < theta_edge));
        ++checked;
      }
      if (!in_contact) {
        CHECK(pr.gx.at<float>(y, x) == 0.0f);
        CHECK(pr.rho.at<double>(y, x) == Approx(kPlateCam / d.z()).epsilon(1e-6));
        continue;
      }
      ++expected_contact;
      const double t_b = BallEntry(d, c, kRadius);
      max_rho_error = std::max(max_rho_error, std::abs(pr.rho.at<double>(y, x) - t_b));
      const Eigen::Vector3d n_true = (c - t_b * d) / kRadius;
      const double gx = pr.gx.at<float>(y, x), gy = pr.gy.at<float>(y, x);
      const Eigen::Vector3d n = s.map.NormalFromSlopes(u, v, gx, gy);
      max_normal_error = std::max(max_normal_error, (n - n_true).norm());
      // A sphere cap on a plate: |slope| = tan of the normal's tilt from the plate normal.
      const double slope = std::hypot(n_true.x(), n_true.y()) / n_true.z();
      max_slope_error = std::max(max_slope_error, std::abs(std::hypot(gx, gy) - slope));
      CHECK(pr.steep.at<std::uint8_t>(y, x) == 0);
    }
  }
  CHECK(checked > 1000);
  CHECK(pr.contact_pixels == expected_contact);
  // Area: pi R^2 with R = fx theta_edge (equidistant lens).
  const double radius_px = s.camera.intrinsics().fx * theta_edge;
  CHECK(pr.contact_pixels == Approx(std::numbers::pi * radius_px * radius_px).epsilon(0.03));
  CHECK(max_rho_error < 1e-5);
  CHECK(max_normal_error < 1e-5);
  CHECK(max_slope_error < 1e-4);
  CHECK(pr.max_indentation_mm == Approx(depth).margin(0.01));
  CHECK(pr.max_indentation_mm <= depth + 1e-9);
  CHECK(pr.contact_centroid.x() == Approx(s.camera.intrinsics().cx).margin(0.05));
  CHECK(pr.contact_centroid.y() == Approx(s.camera.intrinsics().cy).margin(0.05));
}

TEST_CASE("RenderProbe: the box holds every contact pixel of an oblique press", "[render]") {
  const PlateScene& s = Scene();
  // A press far off the axis, where the fisheye stretches the imprint.
  const Eigen::Vector3d c(25.0, -18.0, kPlateCam + kRadius - 0.8);
  const ProbeRender pr = RenderProbe(s.map, s.camera, c, kRadius);
  ProbeRenderOptions whole;
  whole.margin_px = 2000.0;
  const ProbeRender all = RenderProbe(s.map, s.camera, c, kRadius, whole);
  CHECK(all.roi == cv::Rect(0, 0, s.map.width(), s.map.height()));
  REQUIRE(pr.contact_pixels > 50);
  CHECK(pr.contact_pixels == all.contact_pixels);
  CHECK(pr.roi.area() < all.roi.area() / 20);
  CHECK(pr.contact_centroid.isApprox(all.contact_centroid, 1e-12));
  // Ball partly outside the image: the box is clipped to the image.
  // A press straddling the border of the lens's field (80 deg): the box stops at the field.
  const double z = kPlateCam + kRadius - 0.8;
  const Eigen::Vector3d edge(0.0, z * std::tan(1.36), z);
  const ProbeRender clipped = RenderProbe(s.map, s.camera, edge, kRadius);
  const ProbeRender clipped_all = RenderProbe(s.map, s.camera, edge, kRadius, whole);
  REQUIRE(!clipped.roi.empty());
  CHECK(clipped.contact_pixels > 0);
  CHECK(clipped.contact_pixels == clipped_all.contact_pixels);
  const double circle_px = s.camera.intrinsics().fx * s.camera.MaxValidTheta();
  CHECK(clipped.roi.y + clipped.roi.height - 1 <= s.camera.intrinsics().cy + circle_px + 3.0);
  CHECK((clipped.roi & cv::Rect(0, 0, s.map.width(), s.map.height())) == clipped.roi);
}

TEST_CASE("RenderProbe: out of view, not touching, invalid input", "[render]") {
  const PlateScene& s = Scene();
  const ProbeRender behind = RenderProbe(s.map, s.camera, Eigen::Vector3d(0, 0, -20), kRadius);
  CHECK(behind.roi.empty());
  CHECK(behind.contact_pixels == 0);
  CHECK(std::isnan(behind.contact_centroid.x()));
  const ProbeRender aside = RenderProbe(s.map, s.camera, Eigen::Vector3d(40, 0, -3), kRadius);
  CHECK(aside.roi.empty());

  const Eigen::Vector3d above(3.0, 2.0, kPlateCam + kRadius + 0.2);
  const ProbeRender free = RenderProbe(s.map, s.camera, above, kRadius);
  REQUIRE(!free.roi.empty());
  CHECK(free.contact_pixels == 0);
  CHECK(cv::countNonZero(free.contact) == 0);
  CHECK(free.max_indentation_mm == 0.0);
  CHECK(std::isnan(free.contact_centroid.x()));
  const int u = free.roi.x + free.roi.width / 2, v = free.roi.y + free.roi.height / 2;
  CHECK(free.rho.at<double>(v - free.roi.y, u - free.roi.x) == s.map.rho0(u, v));

  CHECK_THROWS_AS(RenderProbe(s.map, s.camera, above, 0.0), std::invalid_argument);
  ProbeRenderOptions bad;
  bad.max_slope_deg = 90.0;
  CHECK_THROWS_WITH(RenderProbe(s.map, s.camera, above, kRadius, bad),
                    Catch::Contains("max_slope_deg"));
}

TEST_CASE("RenderProbe: steep slopes are clamped and flagged", "[render]") {
  const PlateScene& s = Scene();
  // A deep press: near the rim of the contact the ball's normal turns far from the plate's.
  const Eigen::Vector3d c(0.0, 0.0, kPlateCam + kRadius - 1.9);
  ProbeRenderOptions options;
  options.max_slope_deg = 40.0;
  const ProbeRender pr = RenderProbe(s.map, s.camera, c, kRadius, options);
  const double bound = std::tan(40.0 * std::numbers::pi / 180.0);
  int steep = 0;
  for (int y = 0; y < pr.roi.height; ++y) {
    for (int x = 0; x < pr.roi.width; ++x) {
      const double g = std::hypot(pr.gx.at<float>(y, x), pr.gy.at<float>(y, x));
      CHECK(g <= bound + 1e-5);
      if (pr.steep.at<std::uint8_t>(y, x)) {
        ++steep;
        CHECK(pr.contact.at<std::uint8_t>(y, x) == 255);
        CHECK(g == Approx(bound).epsilon(1e-5));
      }
    }
  }
  CHECK(steep > 20);
  CHECK(steep < pr.contact_pixels);
}

}  // namespace
}  // namespace gs360

namespace gs360 {

TEST_CASE("NormalPenetration: signed depth of the ball along the plate's normal", "[render]") {
  const PlateScene& s = Scene();
  const double depth = 1.0;
  const Eigen::Vector3d c(0.0, 0.0, kPlateCam + kRadius - depth);
  const ProbeRender pr = RenderProbe(s.map, s.camera, c, kRadius);
  const cv::Rect roi(pr.roi.x - 10, pr.roi.y - 10, pr.roi.width + 20, pr.roi.height + 20);
  const cv::Mat pen = NormalPenetration(s.map, roi, c, kRadius);
  REQUIRE(pen.size() == roi.size());
  int inside = 0, outside = 0;
  for (int y = 0; y < roi.height; ++y) {
    for (int x = 0; x < roi.width; ++x) {
      const Eigen::Vector3d x0 = s.map.point0(roi.x + x, roi.y + y);
      const double lateral = std::hypot(x0.x() - c.x(), x0.y() - c.y());
      const double p = pen.at<float>(y, x);
      // On a plate the normal line meets the sphere at the same height inside and outside the
      // contact: p = sqrt(r^2 - l^2) - (r - depth); beyond l = r it misses: p = r - |x0 - c|.
      const double want = lateral < kRadius
                              ? std::sqrt(kRadius * kRadius - lateral * lateral) - (kRadius - depth)
                              : kRadius - (x0 - c).norm();
      CHECK(p == Approx(want).margin(1e-4));
      (p > 0 ? inside : outside)++;
      const int rx = roi.x + x - pr.roi.x, ry = roi.y + y - pr.roi.y;
      if (rx >= 0 && ry >= 0 && rx < pr.roi.width && ry < pr.roi.height && std::abs(p) > 1e-3) {
        CHECK((pr.contact.at<std::uint8_t>(ry, rx) == 255) == (p > 0));
      }
    }
  }
  CHECK(inside > 100);
  CHECK(outside > 100);
  CHECK_THROWS_AS(NormalPenetration(s.map, roi, c, 0.0), std::invalid_argument);
}

}  // namespace gs360
