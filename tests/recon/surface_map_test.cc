#include "recon/surface_map.h"

#include <catch2/catch.hpp>
#include <cmath>
#include <numbers>
#include <opencv2/core.hpp>
#include <random>
#include <stdexcept>

#include "geometry/bvh.h"
#include "geometry/fisheye.h"
#include "geometry/shapes.h"
#include "tests/angles.h"
#include "tests/recon/integration_scene.h"

namespace gs360 {
namespace {

using gs360::test::kDeg;

// A square plate at z = `z` (sensor frame), normal facing -z (toward a camera at the origin).
TriangleMesh PlateFacingCamera(double z, double half) {
  TriangleMesh m;
  m.vertices = {{-half, -half, z}, {half, -half, z}, {half, half, z}, {-half, half, z}};
  // (v1 - v0) x (v2 - v0) must be -z: wind clockwise seen from -z... (0,1,2) gives +z, so flip.
  m.triangles = {{0, 2, 1}, {0, 3, 2}};
  m.normals.assign(4, Eigen::Vector3d(0, 0, -1));
  return m;
}

void CheckFrame(const SurfaceMap& map, int u, int v) {
  const Eigen::Vector3d n0 = map.normal0(u, v), t1 = map.t1(u, v), t2 = map.t2(u, v);
  REQUIRE(n0.norm() == Approx(1.0).margin(1e-6));
  REQUIRE(t1.norm() == Approx(1.0).margin(1e-6));
  REQUIRE(t2.norm() == Approx(1.0).margin(1e-6));
  REQUIRE(std::abs(t1.dot(n0)) < 1e-5);
  REQUIRE(std::abs(t2.dot(n0)) < 1e-5);
  REQUIRE(std::abs(t1.dot(t2)) < 1e-5);
  REQUIRE(t1.cross(t2).dot(n0) == Approx(1.0).margin(1e-5));  // right-handed
}

}  // namespace

TEST_CASE("SurfaceMapOptions::Check names the bad field", "[surface_map]") {
  SurfaceMapOptions o;
  REQUIRE_NOTHROW(o.Check());
  o.max_view_angle_deg = 90.0;
  REQUIRE_THROWS_WITH(o.Check(), Catch::Contains("max_view_angle_deg"));
  o = {};
  o.fin_margin_px = -1.0;
  REQUIRE_THROWS_WITH(o.Check(), Catch::Contains("fin_margin_px"));
  o = {};
  o.threads = 0;
  REQUIRE_THROWS_WITH(o.Check(), Catch::Contains("threads"));
}

TEST_CASE("Surface map of a flat plate: rho0, n0, tangent frame, view angle", "[surface_map]") {
  const FisheyeCamera camera;
  const Bvh plate(PlateFacingCamera(10.0, 100.0));
  SurfaceMapOptions options;
  options.max_view_angle_deg = 60.0;
  options.threads = 2;
  const SurfaceMap map = SurfaceMap::Build(camera, Rigid3d::Identity(), plate, nullptr, options);
  REQUIRE(map.width() == 640);
  REQUIRE(map.height() == 480);
  REQUIRE(map.stats().visible > 50000);
  REQUIRE(map.stats().grazing > 10000);
  REQUIRE(map.stats().fin == 0);
  REQUIRE(map.stats().visible + map.stats().grazing + map.stats().outside + map.stats().no_hit ==
          640 * 480);

  int checked = 0;
  for (int v = 2; v < 478; v += 7) {
    for (int u = 2; u < 638; u += 7) {
      const auto ray = camera.PixelToRay(Eigen::Vector2d(u, v));
      if (!ray) {
        REQUIRE(map.status(u, v) == SurfacePixel::kOutside);
        continue;
      }
      const double theta = std::acos(ray->z());
      if (theta > 59.9 * kDeg && theta < 60.1 * kDeg) continue;  // float rounding at the bound
      REQUIRE(map.status(u, v) ==
              (theta > 60.0 * kDeg ? SurfacePixel::kGrazing : SurfacePixel::kVisible));
      if (map.status(u, v) != SurfacePixel::kVisible) continue;
      ++checked;
      REQUIRE((map.ray(u, v) - *ray).norm() < 1e-6);
      REQUIRE(map.rho0(u, v) == Approx(10.0 / ray->z()).epsilon(1e-12));
      REQUIRE((map.point0(u, v).z()) == Approx(10.0).epsilon(1e-6));
      REQUIRE((map.normal0(u, v) - Eigen::Vector3d(0, 0, -1)).norm() < 1e-6);
      REQUIRE(map.view_angle(u, v) == Approx(theta).margin(1e-6));
      CheckFrame(map, u, v);
      // Ray derivatives against finite differences of PixelToRay.
      const double h = 1e-3;
      const Eigen::Vector3d du = (*camera.PixelToRay(Eigen::Vector2d(u + h, v)) -
                                  *camera.PixelToRay(Eigen::Vector2d(u - h, v))) /
                                 (2 * h);
      const Eigen::Vector3d dv = (*camera.PixelToRay(Eigen::Vector2d(u, v + h)) -
                                  *camera.PixelToRay(Eigen::Vector2d(u, v - h))) /
                                 (2 * h);
      REQUIRE((map.ray_du(u, v) - du).norm() < 1e-6 * du.norm() + 1e-9);
      REQUIRE((map.ray_dv(u, v) - dv).norm() < 1e-6 * dv.norm() + 1e-9);
      // t1 along +u: the direction of dx0/du on the plate (x0 = rho0 d).
      const auto x0 = [&](double uu) {
        const Eigen::Vector3d d = *camera.PixelToRay(Eigen::Vector2d(uu, v));
        return Eigen::Vector3d(d * (10.0 / d.z()));
      };
      const Eigen::Vector3d dx0_du = ((x0(u + h) - x0(u - h)) / (2 * h)).normalized();
      REQUIRE((map.t1(u, v).normalized() - dx0_du).norm() < 1e-6);  // floats: ~1e-7
    }
  }
  REQUIRE(checked > 1000);
  // Near the image centre, +u is camera +x on the plate: t1 ~ +x, and t2 = n0 x t1 = -z x x = -y.
  REQUIRE((map.t1(320, 240) - Eigen::Vector3d::UnitX()).norm() < 1e-2);
  REQUIRE((map.t2(320, 240) + Eigen::Vector3d::UnitY()).norm() < 1e-2);
  // The status image and mask agree with status().
  const cv::Mat mask = map.VisibleMask();
  const cv::Mat status = map.StatusImage();
  REQUIRE(cv::countNonZero(mask) == map.stats().visible);
  REQUIRE(status.at<std::uint8_t>(240, 320) == static_cast<std::uint8_t>(SurfacePixel::kVisible));
  REQUIRE(status.at<std::uint8_t>(0, 0) == static_cast<std::uint8_t>(SurfacePixel::kOutside));
}

TEST_CASE("Surface map from inside a sphere matches the analytic sphere", "[surface_map]") {
  const FisheyeCamera camera;
  const Eigen::Vector3d centre(1.0, -2.0, 6.0);  // sensor frame
  const double radius = 15.0;
  const Bvh sphere(gs360::testing::Sphere(centre, radius, 384, 192));
  // A rotated, translated camera: tests the frame handling.
  const Rigid3d cam_from_sensor =
      Rigid3d::FromAxisAngle(Eigen::Vector3d(0.3, -0.2, 1.0), 0.4, Eigen::Vector3d(0.5, 1.0, -2.0));
  SurfaceMapOptions options;
  options.threads = 1;
  const SurfaceMap map = SurfaceMap::Build(camera, cam_from_sensor, sphere, nullptr, options);
  const Eigen::Vector3d c = cam_from_sensor * centre;  // the centre in the camera frame
  REQUIRE(map.stats().no_hit == 0);
  int checked = 0;
  double max_rho_err = 0.0, max_n_err = 0.0;
  for (int v = 0; v < 480; v += 5) {
    for (int u = 0; u < 640; u += 5) {
      if (!map.visible(u, v)) continue;
      ++checked;
      const Eigen::Vector3d d = map.ray(u, v).normalized();
      // |t d - c| = R, camera inside: the positive root.
      const double b = d.dot(c);
      const double t = b + std::sqrt(b * b - c.squaredNorm() + radius * radius);
      max_rho_err = std::max(max_rho_err, std::abs(map.rho0(u, v) - t));
      const Eigen::Vector3d n = (t * d - c) / radius;  // outward
      max_n_err = std::max(max_n_err, (map.normal0(u, v) - n).norm());
      REQUIRE(map.view_angle(u, v) == Approx(std::acos(std::min(1.0, n.dot(d)))).margin(2e-3));
      CheckFrame(map, u, v);
    }
  }
  REQUIRE(checked > 4000);
  // Chord sag of a 384 x 192 tessellation of R = 15: R (1 - cos(pi / 192)) ~ 2e-3 mm.
  REQUIRE(max_rho_err < 2.5e-3);
  REQUIRE(max_n_err < 2e-3);
}

TEST_CASE("Surface map of a cylinder wall around the axis, seen out to 80 deg from it",
          "[surface_map]") {
  // The side wall the base camera sees: its normal is square to the optical axis (n0.z = 0),
  // where the paper's camera-frame slope -nx/nz has no value; the tangent frame must not care.
  const FisheyeCamera camera;
  const Rigid3d cam_from_sensor(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0, 0, 1.5));
  const double radius = 10.0;
  const Bvh wall(gs360::testing::DenseCylinder(radius, 45.0, 4096, 2));
  const SurfaceMap map = SurfaceMap::Build(camera, cam_from_sensor, wall, nullptr);
  int checked = 0, beyond_78 = 0;
  double max_off_axis = 0.0, max_rho_err = 0.0, max_n_err = 0.0, max_slope_err = 0.0;
  for (int v = 0; v < 480; v += 3) {
    for (int u = 0; u < 640; u += 3) {
      if (!map.visible(u, v)) continue;
      const Eigen::Vector3d d = map.ray(u, v).normalized();
      const double off_axis = std::acos(d.z()) / kDeg;
      if (off_axis < 30.0) continue;  // the far end of the tube: seen nearly along its axis
      ++checked;
      beyond_78 += off_axis > 78.0;
      max_off_axis = std::max(max_off_axis, off_axis);
      const double radial = std::hypot(d.x(), d.y());
      max_rho_err = std::max(max_rho_err, std::abs(map.rho0(u, v) - radius / radial));
      const Eigen::Vector3d n(d.x() / radial, d.y() / radial, 0.0);  // outward
      max_n_err = std::max(max_n_err, (map.normal0(u, v) - n).norm());
      REQUIRE(map.view_angle(u, v) / kDeg == Approx(90.0 - off_axis).margin(0.15));
      CheckFrame(map, u, v);
      // A tilted normal goes to tangent-frame slopes and back, finite, with n0.z ~ 0.
      const Eigen::Vector3d tilted = map.NormalFromSlopes(u, v, 0.6, -0.4);
      const Eigen::Vector2d g = map.SlopesFromNormal(u, v, tilted);
      REQUIRE(g.allFinite());
      max_slope_err = std::max(max_slope_err, (g - Eigen::Vector2d(0.6, -0.4)).norm());
    }
  }
  REQUIRE(checked > 2000);
  REQUIRE(beyond_78 > 20);  // the lens's field reaches 80 deg, and the wall is seen there
  REQUIRE(max_off_axis > 79.0);
  WARN("cylinder wall: " << checked << " pixels checked, out to " << max_off_axis
                         << " deg off axis; rho0 error " << max_rho_err << " mm, n0 error "
                         << max_n_err);
  REQUIRE(max_rho_err < 2e-3);
  REQUIRE(max_n_err < 2e-3);
  REQUIRE(max_slope_err < 1e-6);
}

TEST_CASE("Surface map of the cylinder sensor: fins excluded and dilated, grazing flagged",
          "[surface_map]") {
  const FisheyeCamera camera;
  SensorShapeOptions shape;
  const Bvh gel(MakeSensorMesh(shape));
  const Bvh fins(MakeFins(FinOptions{}, *MakeProfile(shape)));
  const Rigid3d cam_from_sensor(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0, 0, 1.5));
  SurfaceMapOptions options;
  options.max_view_angle_deg = 50.0;
  options.fin_margin_px = 0.0;
  const SurfaceMap raw = SurfaceMap::Build(camera, cam_from_sensor, gel, &fins, options);
  options.fin_margin_px = 1.5;
  const SurfaceMap map = SurfaceMap::Build(camera, cam_from_sensor, gel, &fins, options);

  const int in_circle = 640 * 480 - raw.stats().outside;
  REQUIRE(raw.stats().fin > in_circle / 50);
  REQUIRE(raw.stats().fin < in_circle / 3);
  REQUIRE(raw.stats().grazing > 1000);
  REQUIRE(raw.stats().visible > in_circle / 3);
  REQUIRE(map.stats().fin > raw.stats().fin);
  REQUIRE(map.stats().visible < raw.stats().visible);

  const Rigid3d sensor_from_cam = cam_from_sensor.Inverse();
  int fin_checked = 0, visible_checked = 0;
  for (int v = 0; v < 480; ++v) {
    for (int u = 0; u < 640; ++u) {
      const SurfacePixel s = raw.status(u, v);
      if (s == SurfacePixel::kOutside || s == SurfacePixel::kNoHit) {
        REQUIRE(map.status(u, v) == s);
        continue;
      }
      // Cast the pixel ray ourselves: is a fin in front of the gel?
      Ray ray;
      ray.origin = sensor_from_cam.translation;
      ray.direction = sensor_from_cam.RotateDirection(*camera.PixelToRay(Eigen::Vector2d(u, v)));
      const auto hit = gel.Intersect(ray);
      REQUIRE(hit);
      const bool behind_fin = fins.Occluded(ray, 0.0, hit->t);
      if ((u + v) % 13 == 0) {
        REQUIRE((s == SurfacePixel::kFin) == behind_fin);
        if (s == SurfacePixel::kFin) ++fin_checked;
        if (s == SurfacePixel::kVisible || s == SurfacePixel::kGrazing) {
          ++visible_checked;
          REQUIRE(raw.rho0(u, v) == Approx(hit->t).epsilon(1e-12));
          const double angle = std::acos(std::abs(hit->normal.dot(ray.direction)));
          REQUIRE(raw.view_angle(u, v) == Approx(angle).margin(1e-6));
          if (std::abs(angle - 50.0 * kDeg) > 1e-4) {
            REQUIRE((s == SurfacePixel::kGrazing) == (angle > 50.0 * kDeg));
          }
          // Outward normal seen from inside: it points away from the camera.
          REQUIRE(raw.normal0(u, v).dot(raw.ray(u, v)) > 0.0);
          CheckFrame(raw, u, v);
        }
      }
      // Dilation: a pixel that became kFin has a raw fin pixel within 1.5 px; and every pixel
      // next to a raw fin pixel (4-neighbours) is no longer visible.
      if (map.status(u, v) != s) {
        REQUIRE(map.status(u, v) == SurfacePixel::kFin);
        bool near = false;
        for (int dv = -1; dv <= 1; ++dv)
          for (int du = -1; du <= 1; ++du) {
            const int uu = u + du, vv = v + dv;
            if (uu >= 0 && vv >= 0 && uu < 640 && vv < 480 &&
                raw.status(uu, vv) == SurfacePixel::kFin)
              near = true;
          }
        REQUIRE(near);
      }
      if (s == SurfacePixel::kFin) {
        for (const auto& [du, dv] : {std::pair{1, 0}, {-1, 0}, {0, 1}, {0, -1}, {1, 1}}) {
          const int uu = u + du, vv = v + dv;
          if (uu >= 0 && vv >= 0 && uu < 640 && vv < 480) {
            REQUIRE(map.status(uu, vv) != SurfacePixel::kVisible);
          }
        }
      }
    }
  }
  REQUIRE(fin_checked > 100);
  REQUIRE(visible_checked > 1000);
  // Nothing visible: a pose with the camera looking down, away from the finger.
  const Rigid3d away = Rigid3d::FromAxisAngle(Eigen::Vector3d::UnitX(), std::numbers::pi,
                                              Eigen::Vector3d(0, 0, -1.5));
  const Bvh plate_only(PlateFacingCamera(10.0, 5.0));
  REQUIRE_THROWS_AS(SurfaceMap::Build(camera, away, plate_only, nullptr), std::runtime_error);
}

TEST_CASE("Surface map serialisation round trip is exact and damage is rejected", "[surface_map]") {
  const FisheyeCamera camera(FisheyeIntrinsics::Default160(160, 120));
  SensorShapeOptions shape;
  const Bvh gel(MakeSensorMesh(shape));
  const Bvh fins(MakeFins(FinOptions{}, *MakeProfile(shape)));
  const Rigid3d cam_from_sensor =
      Rigid3d::FromAxisAngle(Eigen::Vector3d(1, 2, 0), 0.05, Eigen::Vector3d(0.1, -0.2, 1.5));
  SurfaceMapOptions options;
  options.max_view_angle_deg = 70.0;
  options.fin_margin_px = 0.5;
  const SurfaceMap map = SurfaceMap::Build(camera, cam_from_sensor, gel, &fins, options);
  const std::vector<std::uint8_t> bytes = map.Serialize();
  const SurfaceMap back = SurfaceMap::Deserialize(bytes);
  REQUIRE(back.Serialize() == bytes);
  REQUIRE(back.width() == 160);
  REQUIRE(back.height() == 120);
  REQUIRE(back.options().max_view_angle_deg == 70.0);
  REQUIRE(back.options().fin_margin_px == 0.5);
  REQUIRE(back.stats().visible == map.stats().visible);
  REQUIRE(back.stats().fin == map.stats().fin);
  REQUIRE(back.cam_from_sensor().translation == map.cam_from_sensor().translation);
  REQUIRE(back.cam_from_sensor().rotation.coeffs() == map.cam_from_sensor().rotation.coeffs());
  for (int v = 0; v < 120; ++v) {
    for (int u = 0; u < 160; ++u) {
      REQUIRE(back.status(u, v) == map.status(u, v));
      REQUIRE(back.rho0(u, v) == map.rho0(u, v));
      REQUIRE(back.ray_du(u, v) == map.ray_du(u, v));
      REQUIRE(back.t2(u, v) == map.t2(u, v));
      REQUIRE(back.view_angle(u, v) == map.view_angle(u, v));
    }
  }

  SECTION("truncated") {
    for (std::size_t keep :
         {std::size_t{0}, std::size_t{5}, std::size_t{40}, bytes.size() / 2, bytes.size() - 1}) {
      const std::span<const std::uint8_t> cut(bytes.data(), keep);
      REQUIRE_THROWS_AS(SurfaceMap::Deserialize(cut), std::runtime_error);
    }
    REQUIRE_THROWS_WITH(
        SurfaceMap::Deserialize(std::span<const std::uint8_t>(bytes.data(), bytes.size() - 8)),
        Catch::Contains("truncated"));
  }
  SECTION("corrupted") {
    std::vector<std::uint8_t> bad = bytes;
    bad[bad.size() / 2] ^= 0x10;
    REQUIRE_THROWS_WITH(SurfaceMap::Deserialize(bad), Catch::Contains("checksum"));
    bad = bytes;
    bad[0] = 'X';
    REQUIRE_THROWS_WITH(SurfaceMap::Deserialize(bad), Catch::Contains("magic"));
    bad = bytes;
    bad[8] = 99;  // version
    REQUIRE_THROWS_WITH(SurfaceMap::Deserialize(bad), Catch::Contains("version"));
    bad = bytes;
    bad.push_back(0);
    REQUIRE_THROWS_AS(SurfaceMap::Deserialize(bad), std::runtime_error);
  }
}

TEST_CASE("Slopes and normals round trip on the surface map", "[surface_map]") {
  const FisheyeCamera camera(FisheyeIntrinsics::Default160(160, 120));
  SensorShapeOptions shape;
  const Bvh gel(MakeSensorMesh(shape));
  const Rigid3d cam_from_sensor(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0, 0, 1.5));
  const SurfaceMap map = SurfaceMap::Build(camera, cam_from_sensor, gel, nullptr);
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> slope(-2.0, 2.0);
  int checked = 0;
  for (int v = 0; v < 120; v += 3) {
    for (int u = 0; u < 160; u += 3) {
      if (!map.visible(u, v)) continue;
      const double gx = slope(rng), gy = slope(rng);
      const Eigen::Vector3d n = map.NormalFromSlopes(u, v, gx, gy);
      REQUIRE(n.norm() == Approx(1.0).margin(1e-12));
      const Eigen::Vector2d g = map.SlopesFromNormal(u, v, n);
      // The frame is stored in floats (t1 . n0 ~ 1e-7): round trip to ~1e-7 (1 + |g|^2).
      REQUIRE(g.x() == Approx(gx).margin(2e-6));
      REQUIRE(g.y() == Approx(gy).margin(2e-6));
      REQUIRE((map.NormalFromSlopes(u, v, 0.0, 0.0) - map.normal0(u, v)).norm() < 1e-6);
      ++checked;
    }
  }
  REQUIRE(checked > 300);
  int u0 = 80, v0 = 60;
  REQUIRE(map.visible(u0, v0));
  REQUIRE_THROWS_AS(map.SlopesFromNormal(u0, v0, -map.normal0(u0, v0)), std::invalid_argument);
}

}  // namespace gs360
