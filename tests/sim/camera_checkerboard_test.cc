// Checkerboard images through the true fisheye model: OpenCV finds the corners where the model
// projects them, and cv::fisheye::calibrate recovers the true intrinsics from a generated set.
#include <catch2/catch.hpp>

#include <cmath>
#include <memory>
#include <numbers>
#include <vector>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

#include "geometry/fisheye.h"
#include "geometry/fisheye_cv.h"
#include "sim/checkerboard.h"
#include "sim/ground_truth.h"
#include "sim/rig_model.h"

using namespace gs360;

namespace {

const FisheyeIntrinsics& TrueIntrinsics() {
  static const SimRigOptions options;
  static const SimRig rig(options);
  return SimGroundTruth::TrueIntrinsics(rig);
}

// Detected, sub-pixel refined corners, or empty.
std::vector<cv::Point2f> Detect(const cv::Mat& image, const CheckerboardOptions& board) {
  std::vector<cv::Point2f> corners;
  if (!cv::findChessboardCorners(image, cv::Size(board.cols, board.rows), corners,
                                 cv::CALIB_CB_ADAPTIVE_THRESH | cv::CALIB_CB_NORMALIZE_IMAGE)) {
    return {};
  }
  cv::cornerSubPix(image, corners, cv::Size(5, 5), cv::Size(-1, -1),
                   cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 50, 1e-3));
  return corners;
}

}  // namespace

TEST_CASE("checkerboard: generated poses cover the field and keep every corner visible",
          "[sim][camera]") {
  const FisheyeIntrinsics& intrinsics = TrueIntrinsics();
  const FisheyeCamera camera(intrinsics);
  const CheckerboardOptions board;
  CheckerboardPoseOptions options;
  options.count = 20;
  const std::vector<Rigid3d> poses = CheckerboardPoses(board, intrinsics, options, 11);
  REQUIRE(poses.size() == 20);
  double widest = 0.0;
  for (const Rigid3d& pose : poses) {
    for (const Eigen::Vector3d& x : CheckerboardCorners(board)) {
      const Eigen::Vector3d xc = pose * x;
      const auto uv = camera.CamToPixel(xc);
      REQUIRE(uv);
      widest = std::max(widest, std::atan2(xc.head<2>().norm(), xc.z()));
    }
  }
  CHECK(widest > 60.0 * std::numbers::pi / 180.0);  // corners reach toward the rim
  // Deterministic.
  const auto again = CheckerboardPoses(board, intrinsics, options, 11);
  CHECK((again[7].translation - poses[7].translation).norm() == 0.0);
}

TEST_CASE("checkerboard: OpenCV finds the corners where the true model projects them",
          "[sim][camera]") {
  const FisheyeIntrinsics& intrinsics = TrueIntrinsics();
  const FisheyeCamera camera(intrinsics);
  const CheckerboardOptions board;
  CheckerboardPoseOptions options;
  options.count = 6;
  const std::vector<Rigid3d> poses = CheckerboardPoses(board, intrinsics, options, 5);
  const std::vector<Eigen::Vector3d> corners = CheckerboardCorners(board);
  int found = 0;
  for (std::size_t k = 0; k < poses.size(); ++k) {
    const cv::Mat image = RenderCheckerboard(board, poses[k], intrinsics, k);
    REQUIRE(image.type() == CV_8UC1);
    const std::vector<cv::Point2f> detected = Detect(image, board);
    if (detected.empty()) continue;
    ++found;
    REQUIRE(detected.size() == corners.size());
    double worst = 0.0;
    for (const cv::Point2f& d : detected) {
      // Nearest true projection (OpenCV may order the corners from either end).
      double best = 1e9;
      for (const Eigen::Vector3d& x : corners) {
        const auto uv = camera.CamToPixel(poses[k] * x);
        REQUIRE(uv);
        best = std::min(best, (Eigen::Vector2d(d.x, d.y) - *uv).norm());
      }
      worst = std::max(worst, best);
    }
    CAPTURE(k, worst);
    CHECK(worst < 0.3);
  }
  CHECK(found >= 4);
}

TEST_CASE("checkerboard: cv::fisheye::calibrate recovers the true intrinsics", "[sim][camera]") {
  const FisheyeIntrinsics& intrinsics = TrueIntrinsics();
  const CheckerboardOptions board;
  CheckerboardPoseOptions options;
  options.count = 18;
  const std::vector<Rigid3d> poses = CheckerboardPoses(board, intrinsics, options, 21);
  std::vector<cv::Point3f> object;
  for (const Eigen::Vector3d& x : CheckerboardCorners(board)) {
    object.emplace_back(float(x.x()), float(x.y()), float(x.z()));
  }
  std::vector<std::vector<cv::Point3f>> objects;
  std::vector<std::vector<cv::Point2f>> images;
  for (std::size_t k = 0; k < poses.size(); ++k) {
    const std::vector<cv::Point2f> detected =
        Detect(RenderCheckerboard(board, poses[k], intrinsics, 100 + k), board);
    if (detected.empty()) continue;
    objects.push_back(object);
    images.push_back(detected);
  }
  REQUIRE(images.size() >= 12);
  // Start from the nominal lens, as the intrinsics stage would.
  const FisheyeIntrinsics nominal = FisheyeIntrinsics::Default160();
  cv::Matx33d K = ToCvK(nominal);
  cv::Vec4d D = ToCvD(nominal);
  std::vector<cv::Vec3d> rvecs, tvecs;
  const double rms = cv::fisheye::calibrate(
      objects, images, cv::Size(intrinsics.width, intrinsics.height), K, D, rvecs, tvecs,
      cv::fisheye::CALIB_RECOMPUTE_EXTRINSIC | cv::fisheye::CALIB_FIX_SKEW |
          cv::fisheye::CALIB_USE_INTRINSIC_GUESS,
      cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 100, 1e-9));
  CAPTURE(rms, K(0, 0), K(1, 1), K(0, 2), K(1, 2), D[0], D[1]);
  CHECK(rms < 0.3);
  CHECK(K(0, 0) == Approx(intrinsics.fx).epsilon(0.005));
  CHECK(K(1, 1) == Approx(intrinsics.fy).epsilon(0.005));
  CHECK(K(0, 2) == Approx(intrinsics.cx).margin(1.0));
  CHECK(K(1, 2) == Approx(intrinsics.cy).margin(1.0));
  // The recovered lens maps rays like the true one across the field (the k's trade off).
  const FisheyeCamera truth(intrinsics);
  const FisheyeCamera fitted(
      FromCv(K, D, intrinsics.width, intrinsics.height, intrinsics.max_theta));
  double worst = 0.0;
  for (double theta = 0.0; theta < 1.2; theta += 0.05) {
    const Eigen::Vector3d ray(std::sin(theta) * 0.6, std::sin(theta) * 0.8, std::cos(theta));
    worst = std::max(worst, (truth.ProjectUnchecked(ray) - fitted.ProjectUnchecked(ray)).norm());
  }
  CHECK(worst < 1.0);
}

TEST_CASE("checkerboard: options are checked and a board too large for the field is reported",
          "[sim][camera]") {
  CheckerboardOptions bad;
  bad.cols = 1;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("cols"));
  bad = CheckerboardOptions{};
  bad.square_mm = -1.0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("square_mm"));
  CheckerboardOptions huge;
  huge.square_mm = 40.0;
  CheckerboardPoseOptions options;
  options.count = 2;
  CHECK_THROWS_AS(CheckerboardPoses(huge, TrueIntrinsics(), options, 1), std::runtime_error);
}
