#include <catch2/catch.hpp>

#include <cmath>
#include <opencv2/imgproc.hpp>
#include <random>

#include "capture/impression.h"

namespace {
cv::Mat Noisy(int seed) {
  cv::Mat img(120, 160, CV_8UC3, cv::Scalar(80, 120, 160));
  cv::Mat noise(img.size(), CV_16SC3);
  cv::theRNG().state = static_cast<std::uint64_t>(seed);
  cv::randn(noise, cv::Scalar::all(0), cv::Scalar::all(1.5));
  cv::Mat out;
  cv::add(img, noise, out, cv::noArray(), CV_8UC3);
  return out;
}
}  // namespace

TEST_CASE("FindImpression locates a blob at its centroid", "[capture][impression]") {
  const cv::Mat reference = Noisy(1);
  cv::Mat press = reference.clone();
  cv::circle(press, cv::Point(100, 40), 8, cv::Scalar(110, 150, 120), cv::FILLED, cv::LINE_AA);
  // An unrelated weaker change elsewhere must not pull the centroid.
  cv::circle(press, cv::Point(20, 100), 3, cv::Scalar(95, 120, 160), cv::FILLED);
  const auto imp = gs360::FindImpression(press, reference);
  REQUIRE(imp);
  CHECK(imp->centroid.x() == Approx(100.0).margin(0.3));
  CHECK(imp->centroid.y() == Approx(40.0).margin(0.3));
  CHECK(imp->box.contains(cv::Point(100, 40)));
  CHECK_FALSE(imp->box.contains(cv::Point(20, 100)));
}

TEST_CASE("FindImpression: no contact and masked pixels", "[capture][impression]") {
  const cv::Mat reference = Noisy(2);
  CHECK_FALSE(gs360::FindImpression(reference.clone(), reference));
  cv::Mat press = reference.clone();
  cv::circle(press, cv::Point(60, 60), 6, cv::Scalar(140, 140, 140), cv::FILLED);
  cv::Mat mask(press.size(), CV_8U, cv::Scalar(255));
  cv::circle(mask, cv::Point(60, 60), 20, cv::Scalar(0), cv::FILLED);
  CHECK_FALSE(gs360::FindImpression(press, reference, {}, mask));
  CHECK_THROWS_AS(gs360::FindImpression(press, cv::Mat(10, 10, CV_8UC3)), std::invalid_argument);
}

TEST_CASE("DifferenceMagnitude is the per-pixel colour distance, zero under the mask",
          "[capture][impression]") {
  cv::Mat reference = Noisy(3);
  cv::Mat press = Noisy(4);
  press.at<cv::Vec3b>(5, 7) = cv::Vec3b(0, 255, 30);
  reference.at<cv::Vec3b>(5, 7) = cv::Vec3b(255, 0, 30);
  cv::Mat mask(press.size(), CV_8U, cv::Scalar(1));
  mask.at<std::uint8_t>(9, 11) = 0;
  const cv::Mat m = gs360::DifferenceMagnitude(press, reference, mask, 0.0, "test");
  REQUIRE(m.type() == CV_32F);
  REQUIRE(m.size() == press.size());
  for (int y = 0; y < press.rows; ++y) {
    for (int x = 0; x < press.cols; ++x) {
      const cv::Vec3b a = press.at<cv::Vec3b>(y, x), b = reference.at<cv::Vec3b>(y, x);
      double sum = 0.0;
      for (int c = 0; c < 3; ++c) sum += (a[c] - b[c]) * (a[c] - b[c]);
      const double want = (y == 9 && x == 11) ? 0.0 : std::sqrt(sum);
      if (std::abs(m.at<float>(y, x) - want) > 1e-4) FAIL("pixel " << x << ", " << y);
    }
  }
  CHECK(m.at<float>(5, 7) == Approx(std::sqrt(2.0 * 255 * 255)));
  CHECK_THROWS_WITH(
      gs360::DifferenceMagnitude(press, reference(cv::Rect(0, 0, 10, 10)), {}, 0.0, "caller"),
      Catch::Contains("caller"));
}
