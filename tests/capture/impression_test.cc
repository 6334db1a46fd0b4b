#include <catch2/catch.hpp>

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
