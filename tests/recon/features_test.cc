#include <catch2/catch.hpp>

#include <opencv2/imgproc.hpp>

#include "recon/features.h"

using gs360::ContactDetectionOptions;
using gs360::DetectContactRegions;
using gs360::DifferenceOptions;
using gs360::NormalizedDifference;

namespace {
cv::Mat Reference() {
  cv::Mat ref(120, 160, CV_8UC3);
  for (int v = 0; v < ref.rows; ++v) {
    for (int u = 0; u < ref.cols; ++u) {
      ref.at<cv::Vec3b>(v, u) = cv::Vec3b(static_cast<std::uint8_t>(60 + u / 2),
                                          static_cast<std::uint8_t>(90 + v / 2), 150);
    }
  }
  return ref;
}
}  // namespace

TEST_CASE("normalised difference cancels a global LED gain and keeps a local change",
          "[recon][features]") {
  const cv::Mat ref = Reference();
  cv::Mat frame;
  ref.convertTo(frame, CV_8UC3, 1.04);  // all LEDs 4% brighter
  cv::circle(frame, cv::Point(80, 60), 6, cv::Scalar(40, 200, 250), cv::FILLED);
  cv::Vec3d gain;
  const cv::Mat f = NormalizedDifference(frame, ref, cv::Mat(), DifferenceOptions{}, &gain);
  CHECK(gain[0] == Approx(1.04).margin(0.01));
  CHECK(gain[2] == Approx(1.04).margin(0.01));
  // Far from the change: ~0 (8-bit rounding only).
  const cv::Vec3f far = f.at<cv::Vec3f>(10, 10);
  for (int c = 0; c < 3; ++c) CHECK(std::abs(far[c]) < 0.01f);
  // At the change: blue darker, green brighter.
  const cv::Vec3f at = f.at<cv::Vec3f>(60, 80);
  CHECK(at[0] < -0.3f);
  CHECK(at[1] > 0.4f);
  // Without compensation the gain shows everywhere.
  DifferenceOptions raw;
  raw.compensate_gain = false;
  const cv::Mat g = NormalizedDifference(frame, ref, cv::Mat(), raw);
  CHECK(g.at<cv::Vec3f>(10, 10)[2] > 0.025f);
}

TEST_CASE("normalised difference rejects mismatched inputs and masks pixels", "[recon][features]") {
  const cv::Mat ref = Reference();
  CHECK_THROWS_AS(NormalizedDifference(ref(cv::Rect(0, 0, 50, 50)), ref, cv::Mat()),
                  std::invalid_argument);
  cv::Mat grey;
  cv::cvtColor(ref, grey, cv::COLOR_BGR2GRAY);
  CHECK_THROWS_AS(NormalizedDifference(grey, ref, cv::Mat()), std::invalid_argument);
  cv::Mat frame = ref.clone();
  frame.setTo(cv::Scalar(255, 255, 255));
  cv::Mat mask(ref.size(), CV_8U, cv::Scalar(0));
  mask(cv::Rect(0, 0, 20, 20)).setTo(255);
  DifferenceOptions o;
  o.compensate_gain = false;
  const cv::Mat f = NormalizedDifference(frame, ref, mask, o);
  CHECK(f.at<cv::Vec3f>(5, 5)[0] > 0.5f);
  CHECK(f.at<cv::Vec3f>(100, 100)[0] == 0.0f);
  DifferenceOptions bad;
  bad.floor_dn = 0.0;
  CHECK_THROWS_WITH(NormalizedDifference(frame, ref, mask, bad), Catch::Contains("floor_dn"));
}

TEST_CASE("contact regions: blobs of change, largest first, grown rois", "[recon][features]") {
  cv::Mat diff(200, 300, CV_32FC3, cv::Scalar::all(0));
  cv::circle(diff, cv::Point(80, 100), 15, cv::Scalar(0.3, -0.2, 0.1), cv::FILLED);
  cv::circle(diff, cv::Point(230, 60), 6, cv::Scalar(0.0, 0.4, 0.0), cv::FILLED);
  diff.at<cv::Vec3f>(180, 280) = cv::Vec3f(0.5f, 0.5f, 0.5f);  // one hot pixel: noise
  const auto regions = DetectContactRegions(diff);
  REQUIRE(regions.size() == 2);
  CHECK(regions[0].blob.contains(cv::Point(80, 100)));
  CHECK(regions[1].blob.contains(cv::Point(230, 60)));
  CHECK(regions[0].area_px > regions[1].area_px);
  // The roi holds the blob with margin on every side.
  const cv::Rect& roi = regions[0].roi;
  const cv::Rect& blob = regions[0].blob;
  CHECK(roi.x < blob.x - 6);
  CHECK(roi.br().x > blob.br().x + 6);
  CHECK((roi & blob) == blob);
  CHECK(DetectContactRegions(cv::Mat(50, 50, CV_32FC3, cv::Scalar::all(0))).empty());
  ContactDetectionOptions bad;
  bad.threshold = -1;
  CHECK_THROWS_AS(DetectContactRegions(diff, bad), std::invalid_argument);
}

TEST_CASE("normalised difference smoothing lowers pixel noise and ignores masked pixels",
          "[recon][features]") {
  const cv::Mat ref(100, 100, CV_8UC3, cv::Scalar(100, 100, 100));
  cv::Mat noise(ref.size(), CV_16SC3);
  cv::theRNG().state = 5;
  cv::randn(noise, cv::Scalar::all(0), cv::Scalar::all(3.0));
  cv::Mat frame;
  cv::add(ref, noise, frame, cv::noArray(), CV_8UC3);
  cv::Mat valid(ref.size(), CV_8U, cv::Scalar(255));
  valid(cv::Rect(0, 0, 50, 100)).setTo(0);  // left half masked
  DifferenceOptions raw, smooth;
  raw.smooth_sigma_px = 0.0;
  raw.compensate_gain = smooth.compensate_gain = false;
  smooth.smooth_sigma_px = 1.5;
  auto stddev = [](const cv::Mat& m) {
    cv::Scalar mean, sd;
    cv::meanStdDev(m, mean, sd);
    return sd[0];
  };
  const cv::Rect right(55, 5, 40, 90);
  const cv::Mat a = NormalizedDifference(frame, ref, valid, raw)(right);
  const cv::Mat b = NormalizedDifference(frame, ref, valid, smooth)(right);
  CHECK(stddev(b) < 0.4 * stddev(a));
  // A uniform change next to the mask border keeps its value (normalised convolution).
  cv::Mat brighter;
  ref.convertTo(brighter, CV_8UC3, 1.0, 30.0);
  const cv::Mat c = NormalizedDifference(brighter, ref, valid, smooth);
  CHECK(c.at<cv::Vec3f>(50, 50)[0] == Approx(30.0 / 130.0).epsilon(1e-4));
  CHECK(c.at<cv::Vec3f>(50, 49)[0] == 0.0f);
}

TEST_CASE("context features: the smoothed change's gradient, per channel and scale",
          "[recon][features]") {
  // A linear ramp in R (stored channel 2) along u, in G along v, B constant: the gradient of
  // the smoothed change is the ramp's slope at every scale (a Gaussian keeps a linear function).
  cv::Mat diff(80, 100, CV_32FC3);
  for (int v = 0; v < diff.rows; ++v) {
    for (int u = 0; u < diff.cols; ++u) {
      diff.at<cv::Vec3f>(v, u) = cv::Vec3f(0.2f, 0.01f * v, 0.02f * u);
    }
  }
  const cv::Rect roi(30, 20, 40, 30);
  const cv::Mat c = gs360::ContextFeatures(diff, cv::Mat(), roi, {1.5, 4.0});
  REQUIRE(c.size() == roi.size());
  REQUIRE(c.channels() == 2 * gs360::kContextFeatureCount);
  for (const cv::Point p : {cv::Point(0, 0), cv::Point(20, 15), cv::Point(39, 29)}) {
    const float* f = c.ptr<float>(p.y) + p.x * c.channels();
    for (int scale = 0; scale < 2; ++scale) {
      const float* s = f + 6 * scale;
      CHECK(s[0] == Approx(0.02).margin(1e-5));  // dR/du
      CHECK(s[1] == Approx(0.0).margin(1e-5));   // dR/dv
      CHECK(s[2] == Approx(0.0).margin(1e-5));   // dG/du
      CHECK(s[3] == Approx(0.01).margin(1e-5));  // dG/dv
      CHECK(s[4] == Approx(0.0).margin(1e-5));   // dB/du
      CHECK(s[5] == Approx(0.0).margin(1e-5));   // dB/dv
    }
  }
  // PixelFeatures lays out u, v, R, G, B, then the context of the roi pixel.
  float x[5 + 12];
  gs360::PixelFeatures(diff, c, roi.tl(), 50, 35, x);
  CHECK(x[0] == 50.0f);
  CHECK(x[1] == 35.0f);
  CHECK(x[2] == Approx(1.0f));   // R = 0.02 * 50
  CHECK(x[3] == Approx(0.35f));  // G = 0.01 * 35
  CHECK(x[4] == Approx(0.2f));
  CHECK(x[5] == Approx(0.02).margin(1e-5));
  CHECK(x[8] == Approx(0.01).margin(1e-5));
  DifferenceOptions o;
  CHECK(gs360::FeatureCount(o) == 5 + 3 * 6);  // default: three scales
  o.context_sigmas_px.clear();
  CHECK(gs360::FeatureCount(o) == 5);
  o.context_sigmas_px = {1.5, 4.0};
  CHECK(gs360::FeatureCount(o) == 17);
  CHECK(gs360::ContextFeatures(diff, cv::Mat(), roi, {}).empty());
}

TEST_CASE("context features: a pixel's features do not depend on the roi around it",
          "[recon][features]") {
  // Noise with a masked band: the features of a small roi's pixels are those of a large roi
  // containing it (each blurs only where it reads, but from the whole image).
  cv::Mat diff(120, 160, CV_32FC3);
  cv::randu(diff, cv::Scalar::all(-1.0), cv::Scalar::all(1.0));
  cv::Mat valid(diff.size(), CV_8U, cv::Scalar(255));
  valid(cv::Rect(70, 0, 3, 120)).setTo(0);
  diff.setTo(cv::Scalar::all(0), valid == 0);
  const std::vector<double> sigmas = {1.5, 4.0, 10.0};
  const cv::Rect large(20, 15, 120, 90), small(60, 40, 30, 25);
  const cv::Mat a = gs360::ContextFeatures(diff, valid, large, sigmas);
  const cv::Mat b = gs360::ContextFeatures(diff, valid, small, sigmas);
  const cv::Mat a_small = a(small - large.tl());
  CHECK(cv::norm(a_small.reshape(1), b.reshape(1), cv::NORM_INF) < 1e-6);
  CHECK(cv::norm(b.reshape(1), cv::NORM_INF) > 0.01);  // not all zeros
}

TEST_CASE("context features: a masked fin reads as no change, bad input is refused",
          "[recon][features]") {
  // A uniform change with a masked band (diff is 0 there, as NormalizedDifference leaves it):
  // normalised convolution keeps the gradient 0 right next to the band instead of reading the
  // band's zeros as an edge.
  cv::Mat diff(60, 60, CV_32FC3, cv::Scalar::all(0.3));
  cv::Mat valid(diff.size(), CV_8U, cv::Scalar(255));
  valid(cv::Rect(28, 0, 4, 60)).setTo(0);
  diff.setTo(cv::Scalar::all(0), valid == 0);
  const cv::Rect roi(10, 10, 40, 40);
  const cv::Mat c = gs360::ContextFeatures(diff, valid, roi, {3.0});
  const cv::Mat unmasked = gs360::ContextFeatures(diff, cv::Mat(), roi, {3.0});
  CHECK(cv::norm(c.reshape(1), cv::NORM_INF) < 1e-4);
  CHECK(cv::norm(unmasked.reshape(1), cv::NORM_INF) >
        0.01);  // without the mask the band is an edge
  CHECK_THROWS_WITH(gs360::ContextFeatures(diff, valid, cv::Rect(50, 50, 20, 20), {3.0}),
                    Catch::Contains("not inside the image"));
  CHECK_THROWS_WITH(gs360::ContextFeatures(diff, valid, roi, {0.0}), Catch::Contains("sigma"));
  CHECK_THROWS_AS(gs360::ContextFeatures(cv::Mat(60, 60, CV_8UC3), valid, roi, {3.0}),
                  std::invalid_argument);
  DifferenceOptions o;
  o.context_sigmas_px = {25.0};
  CHECK_THROWS_WITH(o.Check(), Catch::Contains("context_sigmas_px"));
  o.context_sigmas_px = {1, 2, 3, 4, 5};
  CHECK_THROWS_WITH(o.Check(), Catch::Contains("at most 4"));
}
