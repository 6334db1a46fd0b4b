#include "calib/intrinsics.h"

#include <algorithm>
#include <catch2/catch.hpp>
#include <cmath>
#include <numbers>
#include <opencv2/imgcodecs.hpp>
#include <stdexcept>
#include <vector>

#include "sim/checkerboard.h"
#include "tests/angles.h"

namespace gs360 {
namespace {

using gs360::test::kRadToDeg;

std::vector<cv::Mat> RenderBoards(const FisheyeIntrinsics& truth, int count, std::uint64_t seed) {
  CheckerboardPoseOptions pose_options;
  pose_options.count = count;
  return RenderCheckerboardSet(CheckerboardOptions{}, truth, pose_options, seed);
}

TEST_CASE("CalibrateIntrinsics recovers a perturbed fisheye lens", "[intrinsics]") {
  const FisheyeIntrinsics truth = PerturbedLens160();
  const std::vector<cv::Mat> images = RenderBoards(truth, 20, 7);
  const IntrinsicsResult result =
      CalibrateIntrinsics(images, FisheyeIntrinsics::Default160(), IntrinsicsOptions{});
  const FisheyeIntrinsics& got = result.intrinsics;
  INFO("fx " << got.fx << " vs " << truth.fx << ", fy " << got.fy << " vs " << truth.fy << ", cx "
             << got.cx << " vs " << truth.cx << ", cy " << got.cy << " vs " << truth.cy << ", k "
             << got.k[0] << " " << got.k[1] << " " << got.k[2] << " " << got.k[3] << ", rms "
             << result.rms_px);
  CHECK(result.used.size() + result.rejected.size() == images.size());
  CHECK(result.used.size() >= 15);
  CHECK(result.rms_px < 0.3);
  CHECK(result.radial_coverage > 0.6);
  CHECK(std::abs(got.fx - truth.fx) < 0.5);
  CHECK(std::abs(got.fy - truth.fy) < 0.5);
  CHECK(std::abs(got.cx - truth.cx) < 0.5);
  CHECK(std::abs(got.cy - truth.cy) < 0.5);
  CHECK(got.skew == 0.0);
  CHECK(got.max_theta == FisheyeIntrinsics::Default160().max_theta);
  CHECK(result.cam_from_board.size() == result.used.size());
  for (const IntrinsicsImageReport& report : result.images) {
    if (report.used) CHECK(report.rms_px < 0.5);
  }
  // Rays over the whole field agree with the truth; the nominal lens is far off.
  const double err_deg = MaxRayAngleDifference(got, truth, 4) * kRadToDeg;
  const double nominal_deg =
      MaxRayAngleDifference(FisheyeIntrinsics::Default160(), truth, 4) * kRadToDeg;
  INFO("max ray error " << err_deg << " deg (nominal lens: " << nominal_deg << " deg)");
  CHECK(err_deg < 0.05);
  CHECK(nominal_deg > 0.5);
}

TEST_CASE("CalibrateIntrinsics rejects too few images", "[intrinsics]") {
  const FisheyeIntrinsics truth = PerturbedLens160();
  const std::vector<cv::Mat> images = RenderBoards(truth, 5, 3);
  try {
    CalibrateIntrinsics(images, FisheyeIntrinsics::Default160(), IntrinsicsOptions{});
    FAIL("expected an error");
  } catch (const std::runtime_error& e) {
    CHECK_THAT(e.what(), Catch::Contains("detected in 5 of 5 images, need at least 8"));
  }
}

TEST_CASE("CalibrateIntrinsics rejects blank images", "[intrinsics]") {
  std::vector<cv::Mat> images(10, cv::Mat(480, 640, CV_8UC1, cv::Scalar(120)));
  try {
    CalibrateIntrinsics(images, FisheyeIntrinsics::Default160(), IntrinsicsOptions{});
    FAIL("expected an error");
  } catch (const std::runtime_error& e) {
    CHECK_THAT(e.what(), Catch::Contains("detected in 0 of 10"));
  }
}

TEST_CASE("CalibrateIntrinsics rejects boards only at the centre of the field", "[intrinsics]") {
  const FisheyeIntrinsics truth = PerturbedLens160();
  CheckerboardOptions board;
  CheckerboardPoseOptions pose_options;
  pose_options.count = 10;
  pose_options.max_field_deg = 4.0;  // board centres near the axis
  pose_options.min_distance_mm = 60.0;
  pose_options.max_distance_mm = 70.0;
  pose_options.max_tilt_deg = 30.0;
  std::vector<cv::Mat> images;
  std::uint64_t k = 0;
  for (const Rigid3d& pose : CheckerboardPoses(board, truth, pose_options, 11)) {
    images.push_back(RenderCheckerboard(board, pose, truth, 500 + k++));
  }
  try {
    CalibrateIntrinsics(images, FisheyeIntrinsics::Default160(), IntrinsicsOptions{});
    FAIL("expected an error");
  } catch (const std::runtime_error& e) {
    CHECK_THAT(e.what(), Catch::Contains("of the image circle's radius"));
  }
}

TEST_CASE("CalibrateIntrinsics checks its inputs", "[intrinsics]") {
  IntrinsicsOptions bad;
  bad.square_mm = 0.0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("square_mm"));
  bad = {};
  bad.min_images = 2;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("min_images"));
  std::vector<cv::Mat> wrong_size(8, cv::Mat(100, 100, CV_8UC1, cv::Scalar(0)));
  CHECK_THROWS_AS(CalibrateIntrinsics(wrong_size, FisheyeIntrinsics::Default160()),
                  std::invalid_argument);
}

}  // namespace
}  // namespace gs360

namespace gs360 {
namespace {

std::vector<std::uint8_t> Encoded(const cv::Mat& image, const std::string& ext) {
  std::vector<std::uint8_t> bytes;
  REQUIRE(cv::imencode(ext, image, bytes));
  return bytes;
}

}  // namespace

TEST_CASE("ImageFileProblem: truncated PNG and JPEG files are caught alike", "[intrinsics]") {
  const cv::Mat board = RenderBoards(PerturbedLens160(), 1, 5)[0];
  for (const std::string ext : {".png", ".jpg"}) {
    INFO(ext);
    std::vector<std::uint8_t> bytes = Encoded(board, ext);
    CHECK_FALSE(ImageFileProblem(bytes));
    bytes.resize(bytes.size() * 2 / 3);
    const auto problem = ImageFileProblem(bytes);
    REQUIRE(problem);
    CHECK_THAT(*problem,
               Catch::Contains("truncated") && Catch::Contains(ext == ".png" ? "PNG" : "JPEG"));
  }
  CHECK_THAT(*ImageFileProblem(std::vector<std::uint8_t>(5, 0)), Catch::Contains("too short"));
}

TEST_CASE("CalibrateIntrinsics rejects an undecodable image and goes on", "[intrinsics]") {
  std::vector<cv::Mat> images = RenderBoards(PerturbedLens160(), 14, 7);
  images[3] = cv::Mat();
  const IntrinsicsResult result =
      CalibrateIntrinsics(images, FisheyeIntrinsics::Default160(), IntrinsicsOptions{});
  CHECK_FALSE(result.images[3].used);
  CHECK(result.images[3].reason == "not a decodable image");
  CHECK(std::count(result.rejected.begin(), result.rejected.end(), 3) == 1);
  CHECK(result.rms_px < 0.3);
}

}  // namespace gs360

namespace gs360 {

TEST_CASE("CalibrateIntrinsics says when the nominal lens is far off, not what the images lack",
          "[intrinsics]") {
  const FisheyeIntrinsics truth = PerturbedLens160();
  const std::vector<cv::Mat> images = RenderBoards(truth, 12, 7);
  for (const double factor : {0.5, 2.0, 3.0}) {
    INFO("nominal focal length x" << factor);
    FisheyeIntrinsics nominal = FisheyeIntrinsics::Default160();
    nominal.fx *= factor;
    nominal.fy *= factor;
    try {
      CalibrateIntrinsics(images, nominal, IntrinsicsOptions{});
      FAIL("expected an error");
    } catch (const std::runtime_error& e) {
      const std::string what = e.what();
      CHECK_THAT(what, Catch::Contains("nominal lens looks far from the real one"));
      // The focal length it names is the true one.
      const auto at = what.find("px at fx ");
      REQUIRE(at != std::string::npos);
      CHECK(std::abs(std::stod(what.substr(at + 9)) - truth.fx) < 2.0);
    }
  }
}

}  // namespace gs360
