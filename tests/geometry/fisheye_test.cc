#include <catch2/catch.hpp>

#include <cmath>
#include <numbers>
#include <opencv2/calib3d.hpp>
#include <vector>

#include "geometry/fisheye.h"
#include "geometry/fisheye_cv.h"
#include "tests/angles.h"

using namespace gs360;

namespace {

using gs360::test::kDeg;

// A lens with every parameter non-trivial (as cv::fisheye::calibrate would return).
FisheyeIntrinsics DistortedLens() {
  FisheyeIntrinsics in;
  in.width = 640;
  in.height = 480;
  in.fx = 165.3;
  in.fy = 166.1;
  in.cx = 321.7;
  in.cy = 238.2;
  in.skew = 0.002;
  in.k = {0.031, -0.012, 0.004, -0.0006};
  in.max_theta = 85.0 * kDeg;
  return in;
}

// Camera-frame directions on a dense (theta, phi) grid up to max_theta.
std::vector<cv::Point3d> DirectionGrid(double max_theta) {
  std::vector<cv::Point3d> pts;
  for (int i = 0; i <= 170; ++i) {
    const double theta = max_theta * i / 170.0;
    for (int j = 0; j < 180; ++j) {
      const double phi = 2.0 * std::numbers::pi * j / 180.0;
      const double r = 3.0 + 0.1 * j;  // arbitrary distance: only the direction matters
      pts.emplace_back(r * std::sin(theta) * std::cos(phi), r * std::sin(theta) * std::sin(phi),
                       r * std::cos(theta));
    }
  }
  return pts;
}

}  // namespace

TEST_CASE("Fisheye projection agrees with cv::fisheye::projectPoints over the field", "[fisheye]") {
  for (const FisheyeIntrinsics& in : {DistortedLens(), FisheyeIntrinsics::Default160()}) {
    const FisheyeCamera cam(in);
    // OpenCV divides by z: stay short of 90 degrees.
    const std::vector<cv::Point3d> pts = DirectionGrid(std::min(cam.MaxValidTheta(), 89.5 * kDeg));
    std::vector<cv::Point2d> cv_uv;
    // projectPoints takes the skew as its `alpha` argument (it ignores K(0, 1)).
    cv::fisheye::projectPoints(pts, cv_uv, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), ToCvK(in),
                               ToCvD(in), in.skew);
    double worst = 0.0;
    int valid = 0;
    for (std::size_t i = 0; i < pts.size(); ++i) {
      const Eigen::Vector3d x(pts[i].x, pts[i].y, pts[i].z);
      const Eigen::Vector2d ref(cv_uv[i].x, cv_uv[i].y);
      worst = std::max(worst, (cam.ProjectUnchecked(x) - ref).norm());
      const auto uv = cam.CamToPixel(x);
      if (uv) {
        ++valid;
        worst = std::max(worst, (*uv - ref).norm());
      } else {
        // Only points whose pixel is outside the image may be rejected inside the field.
        CHECK_FALSE(cam.InImage(ref));
      }
    }
    CHECK(worst < 1e-6);
    CHECK(valid > static_cast<int>(pts.size()) * 3 / 4);
  }
}

TEST_CASE("Fisheye unprojection agrees with cv::fisheye::undistortPoints", "[fisheye]") {
  // OpenCV 4.6's fisheye::undistortPoints ignores the skew: compare on a skew-free lens.
  FisheyeIntrinsics no_skew = DistortedLens();
  no_skew.skew = 0.0;
  for (const FisheyeIntrinsics& in : {no_skew, FisheyeIntrinsics::Default160()}) {
    const FisheyeCamera cam(in);
    std::vector<cv::Point2d> pixels;
    std::vector<Eigen::Vector3d> rays;
    int invalid = 0;
    for (double v = -0.5; v <= in.height - 0.5; v += 3.0) {
      for (double u = -0.5; u <= in.width - 0.5; u += 3.0) {
        const auto ray = cam.PixelToRay(Eigen::Vector2d(u, v));
        if (!ray) {
          // Invalid only beyond the image circle.
          const auto theta = cam.PixelTheta(Eigen::Vector2d(u, v));
          CHECK_FALSE(theta.has_value());
          ++invalid;
          continue;
        }
        CHECK(ray->norm() == Approx(1.0).epsilon(1e-14));
        pixels.emplace_back(u, v);
        rays.push_back(*ray);
      }
    }
    CHECK(invalid > 0);
    CHECK(pixels.size() > 10000);
    // cv returns normalised coordinates (x/z, y/z); ask it for full convergence.
    std::vector<cv::Point2d> normalised;
    cv::fisheye::undistortPoints(
        pixels, normalised, ToCvK(in), ToCvD(in), cv::noArray(), cv::noArray(),
        cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 100, 1e-15));
    double worst = 0.0, worst_roundtrip = 0.0;
    for (std::size_t i = 0; i < pixels.size(); ++i) {
      const Eigen::Vector3d cv_ray =
          Eigen::Vector3d(normalised[i].x, normalised[i].y, 1.0).normalized();
      // Compare in pixels: project both rays with the same model.
      const Eigen::Vector2d a = cam.ProjectUnchecked(rays[i]);
      const Eigen::Vector2d b = cam.ProjectUnchecked(cv_ray);
      worst = std::max(worst, (a - b).norm());
      worst_roundtrip =
          std::max(worst_roundtrip, (a - Eigen::Vector2d(pixels[i].x, pixels[i].y)).norm());
    }
    CHECK(worst < 1e-6);
    CHECK(worst_roundtrip < 1e-9);
  }
}

TEST_CASE("Fisheye invalid regions: beyond the field, behind, outside the image", "[fisheye]") {
  const FisheyeCamera cam(FisheyeIntrinsics::Default160());
  const FisheyeIntrinsics& in = cam.intrinsics();
  CHECK(cam.MaxValidTheta() == Approx(80.0 * kDeg));
  CHECK(in.fx == Approx(236.0 / (80.0 * kDeg)));
  // The image circle fits in the image with a 4 px margin.
  const auto edge = cam.CamToPixel(Eigen::Vector3d(std::sin(80 * kDeg), 0, std::cos(80 * kDeg)));
  REQUIRE(edge);
  CHECK(edge->x() == Approx(319.5 + 236.0));
  CHECK_FALSE(cam.CamToPixel(Eigen::Vector3d(std::sin(80.01 * kDeg), 0, std::cos(80.01 * kDeg))));
  CHECK_FALSE(cam.CamToPixel(Eigen::Vector3d(0, 0, -1)));  // behind
  CHECK_FALSE(cam.CamToPixel(Eigen::Vector3d(1, 0, 0)));   // 90 degrees
  CHECK_FALSE(cam.CamToPixel(Eigen::Vector3d::Zero()));
  CHECK(cam.CamToPixel(Eigen::Vector3d(0, 0, 5))->isApprox(Eigen::Vector2d(319.5, 239.5)));
  CHECK_FALSE(cam.PixelToRay(Eigen::Vector2d(319.5 + 237.0, 239.5)));  // outside the circle
  CHECK_FALSE(cam.PixelToRay(Eigen::Vector2d(2.0, 2.0)));              // image corner
  CHECK_FALSE(cam.PixelToRay(Eigen::Vector2d(-0.6, 239.5)));           // outside the image
  CHECK(cam.PixelToRay(Eigen::Vector2d(319.5, 239.5))->isApprox(Eigen::Vector3d(0, 0, 1)));

  // A 200-degree lens clipped by a small image: points inside the field but off the sensor.
  FisheyeIntrinsics wide = FisheyeIntrinsics::Default160();
  wide.max_theta = 90.0 * kDeg;
  wide.fx = wide.fy = 300.0;
  const FisheyeCamera wcam(wide);
  CHECK_FALSE(wcam.CamToPixel(Eigen::Vector3d(std::sin(70 * kDeg), 0, std::cos(70 * kDeg))));
  CHECK(wcam.CamToPixel(Eigen::Vector3d(std::sin(20 * kDeg), 0, std::cos(20 * kDeg))));
}

TEST_CASE("Fisheye validity stops where theta_d stops increasing", "[fisheye]") {
  FisheyeIntrinsics in = FisheyeIntrinsics::Default160();
  in.max_theta = 90.0 * kDeg;
  in.k = {-0.35, 0.0, 0.0, 0.0};  // theta_d' = 1 - 1.05 theta^2 = 0 at theta = 0.9759 rad
  const FisheyeCamera cam(in);
  const double root = 1.0 / std::sqrt(1.05);
  CHECK(cam.MaxValidTheta() == Approx(root).epsilon(1e-12));
  CHECK(cam.ThetaDToTheta(cam.ThetaToThetaD(0.9 * root)).value() ==
        Approx(0.9 * root).epsilon(1e-14));
  CHECK_FALSE(cam.ThetaDToTheta(cam.ThetaToThetaD(root) * 1.0001));
  const Eigen::Vector3d beyond(std::sin(root + 0.01), 0.0, std::cos(root + 0.01));
  CHECK_FALSE(cam.CamToPixel(beyond));
  // ... although the unchecked formula maps it inside the circle (the fold).
  CHECK(cam.InImage(cam.ProjectUnchecked(beyond)));
  // Inverse is exact inside the valid range.
  for (int i = 0; i <= 1000; ++i) {
    const double theta = cam.MaxValidTheta() * i / 1000.0;
    CHECK(cam.ThetaDToTheta(cam.ThetaToThetaD(theta)).value() == Approx(theta).margin(1e-13));
  }
}

TEST_CASE("Fisheye round trip, checks and OpenCV conversions", "[fisheye]") {
  const FisheyeIntrinsics in = DistortedLens();
  const FisheyeCamera cam(in);
  for (double v = 0; v < in.height; v += 7.3) {
    for (double u = 0; u < in.width; u += 7.3) {
      const auto ray = cam.PixelToRay(Eigen::Vector2d(u, v));
      if (!ray) continue;
      const auto uv = cam.CamToPixel(*ray * 12.5);
      REQUIRE(uv);
      CHECK((*uv - Eigen::Vector2d(u, v)).norm() < 1e-9);
    }
  }
  const FisheyeIntrinsics back = FromCv(ToCvK(in), ToCvD(in), in.width, in.height, in.max_theta);
  CHECK(back.fx == in.fx);
  CHECK(back.skew == Approx(in.skew).epsilon(1e-15));
  CHECK(back.k == in.k);
  CHECK(back.cy == in.cy);
  cv::Matx33d bad_k = ToCvK(in);
  bad_k(2, 2) = 2.0;
  CHECK_THROWS_AS(FromCv(bad_k, ToCvD(in), 640, 480), std::invalid_argument);

  FisheyeIntrinsics bad = in;
  bad.fx = 0.0;
  CHECK_THROWS_WITH(FisheyeCamera(bad), Catch::Contains("FisheyeIntrinsics.fx"));
  bad = in;
  bad.max_theta = 100.0 * kDeg;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("FisheyeIntrinsics.max_theta"));
  bad = in;
  bad.k[2] = std::nan("");
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("FisheyeIntrinsics.k[2]"));
  bad = in;
  bad.width = 0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("FisheyeIntrinsics.width"));
}
