#include <catch2/catch.hpp>

#include <cmath>
#include <random>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "capture/impression.h"
#include "capture/impression_regions.h"
#include "capture/press_check.h"

namespace {

using Catch::Matchers::Contains;
using gs360::PressVerdict;

constexpr int kWidth = 320;
constexpr int kHeight = 240;

// A scene lit brightly on its left half and dimly on its right; `bump_dn` adds an impression of
// that amplitude centred at `at`, a Gaussian of sigma size_px: a dimple's two-sided shading (one
// colour up, another down on one side, the other way on the other), or a shade over every colour.
cv::Mat Scene(double bump_dn, cv::Point2d at, double size_px, bool two_sided) {
  cv::Mat signal(kHeight, kWidth, CV_32FC3);
  for (int y = 0; y < kHeight; ++y) {
    for (int x = 0; x < kWidth; ++x) {
      const float level = x < kWidth / 2 ? 180.0f : 40.0f;
      signal.at<cv::Vec3f>(y, x) = cv::Vec3f(level * 0.8f, level, level * 0.6f);
    }
  }
  if (bump_dn != 0.0) {
    for (int y = 0; y < kHeight; ++y) {
      for (int x = 0; x < kWidth; ++x) {
        const double dx = x - at.x, dy = y - at.y;
        const double b = bump_dn * std::exp(-(dx * dx + dy * dy) / (2.0 * size_px * size_px));
        const double side = dx >= 0.0 ? 1.0 : -1.0;
        signal.at<cv::Vec3f>(y, x) +=
            two_sided ? cv::Vec3f(static_cast<float>(b * side), 0.0f, static_cast<float>(-b * side))
                      : cv::Vec3f::all(static_cast<float>(-b));
      }
    }
  }
  return signal;
}

// Scene() as a K-frame average the camera delivers (the shot noise follows the light: sigma 4 DN
// on the left, 1.5 on the right): `seed` draws the noise.
cv::Mat Capture(std::uint64_t seed, double bump_dn = 0.0, cv::Point2d at = {240, 120},
                double gain = 1.0, double size_px = 8.0, bool two_sided = true) {
  const cv::Mat signal = Scene(bump_dn, at, size_px, two_sided);
  std::mt19937 rng(static_cast<unsigned>(seed));
  std::normal_distribution<float> unit(0.0f, 1.0f);
  cv::Mat out(kHeight, kWidth, CV_8UC3);
  for (int y = 0; y < kHeight; ++y) {
    for (int x = 0; x < kWidth; ++x) {
      const float sigma = x < kWidth / 2 ? 4.0f : 1.5f;
      for (int c = 0; c < 3; ++c) {
        const float v =
            static_cast<float>(gain) * signal.at<cv::Vec3f>(y, x)[c] + sigma * unit(rng);
        out.at<cv::Vec3b>(y, x)[c] = cv::saturate_cast<std::uint8_t>(v);
      }
    }
  }
  return out;
}

// Where a plan's probes would project: a grid over the frame.
std::vector<Eigen::Vector2d> Grid() {
  std::vector<Eigen::Vector2d> px;
  for (int y = 15; y < kHeight; y += 15) {
    for (int x = 15; x < kWidth; x += 15) px.emplace_back(x, y);
  }
  return px;
}

}  // namespace

TEST_CASE("MeasureImpressionSnr: a faint impression in a dimly lit part stands out of its noise",
          "[capture][press_check]") {
  const cv::Mat reference = Capture(1), second = Capture(2);
  const gs360::DifferenceNoise noise(reference, second, 2.0);
  const Eigen::Vector2d at(240, 120);
  // 3 DN: twice the per-pixel noise there, and below the bright half's.
  const cv::Mat press = Capture(3, 3.0);
  const gs360::ImpressionSnr weak = gs360::MeasureImpressionSnr(press, reference, noise, at, 40);
  const gs360::ImpressionSnr none =
      gs360::MeasureImpressionSnr(Capture(4), reference, noise, at, 40);
  CHECK(weak.snr > 3.0 * none.snr);
  CHECK(none.snr < 6.0);
  CHECK((weak.peak_px - at).norm() < 12.0);
  // The noise as the two captures showed it: 1.5 DN per pixel in each capture here, 4 DN in the
  // bright half, over the 2 sqrt(2 pi) of the blur.
  CHECK(weak.noise_dn ==
        Approx(1.5 * std::sqrt(2.0) / (2.0 * std::sqrt(3.14159265) * 2.0)).epsilon(0.15));
  CHECK(noise.Sigma(1, 180.0) / noise.Sigma(1, 40.0) == Approx(4.0 / 1.5).epsilon(0.15));
  CHECK(weak.reference_dn == Approx(40.0 * 0.8).margin(1.0));
  // The frame-wide contrast the check used before sees nothing: the bright half's noise is
  // the 99th percentile it divides by.
  CHECK(gs360::ImpressionContrast(press, reference, at, 40) < 1.4);
}

TEST_CASE("MeasureImpressionSnr: an LED drift is not an impression, at a light's edge too",
          "[capture][press_check]") {
  const cv::Mat reference = Capture(1), second = Capture(2);
  const gs360::DifferenceNoise noise(reference, second, 2.0);
  // 3 % brighter: 1 DN more in the dim half, 4 DN in the bright one; the window straddles both.
  const cv::Mat drifted = Capture(5, 0.0, {}, 1.03);
  for (const Eigen::Vector2d& at : {Eigen::Vector2d(240, 120), Eigen::Vector2d(160, 120)}) {
    CHECK(gs360::MeasureImpressionSnr(drifted, reference, noise, at, 40).snr < 6.0);
  }
  CHECK(gs360::MeasureImpressionSnr(drifted, reference, noise, {-100, -100}, 40).snr == 0.0);
  CHECK_THROWS_AS(gs360::DifferenceNoise(reference, cv::Mat(10, 10, CV_8UC3), 2.0),
                  std::invalid_argument);
  CHECK_THROWS_AS(
      gs360::MeasureImpressionSnr(drifted, reference, gs360::DifferenceNoise(), {0, 0}, 40),
      std::invalid_argument);
}

TEST_CASE("GumbelQuantileAbove recovers a Gumbel distribution's tail from its bulk",
          "[capture][press_check]") {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(1e-12, 1.0);
  std::vector<double> samples;
  const double location = 4.2, scale = 0.3;
  for (int i = 0; i < 4000; ++i) samples.push_back(location - scale * std::log(-std::log(u(rng))));
  for (int i = 0; i < 40; ++i) samples.push_back(50.0);  // a few odd ones
  const double q = gs360::GumbelQuantileAbove(samples, 1e-6);
  CHECK(q == Approx(location - scale * std::log(-std::log1p(-1e-6))).epsilon(0.05));
  CHECK_THROWS_AS(gs360::GumbelQuantileAbove({}, 0.01), std::invalid_argument);
  CHECK_THROWS_AS(gs360::GumbelQuantileAbove({1.0}, 0.0), std::invalid_argument);
}

TEST_CASE("PressCheck: the threshold comes from the session's own null", "[capture][press_check]") {
  gs360::PressCheck check({}, Grid());
  REQUIRE_FALSE(check.HasReference());
  CHECK_THROWS_AS(check.Check(Capture(3), {240, 120}), std::logic_error);
  check.SetReference(Capture(1), Capture(2));
  CHECK(check.NullSamples() == 128);
  const double first = check.Threshold();
  CHECK(first > gs360::kMinImpressionSnr);
  CHECK(first < 12.0);

  SECTION("a weak but real impression counts; the same frame without it does not") {
    const auto weak = check.Check(Capture(3, 3.0), {240, 120});
    CHECK(weak.verdict == PressVerdict::kImpression);
    CHECK(weak.press.snr > weak.threshold);
    CHECK(weak.null_samples == 128);
    CHECK(weak.null_snr > 0.0);
    CHECK(check.NullSamples() == 130);  // two windows of the press frame, far from the press
    const auto missed = check.Check(Capture(4), {240, 120});
    CHECK(missed.verdict == PressVerdict::kNoImpression);
    // An impression 100 px from where the plan put it: the ball pressed elsewhere.
    const auto elsewhere = check.Check(Capture(6, 20.0, {120, 120}), {240, 120});
    CHECK(elsewhere.verdict == PressVerdict::kNoImpression);
  }
  SECTION("a frozen camera: the reference again, or the last press frame again") {
    const cv::Mat reference = Capture(1);
    const auto on_reference = check.Check(reference.clone(), {240, 120});
    CHECK(on_reference.verdict == PressVerdict::kFrozen);
    CHECK(on_reference.frozen_on_reference);
    const cv::Mat press = Capture(3, 20.0, {240, 120});
    CHECK(check.Check(press, {240, 120}).verdict == PressVerdict::kImpression);
    // The next probe, 20 px away: the old frame's impression lies within the window.
    const auto again = check.Check(press.clone(), {250, 130});
    CHECK(again.verdict == PressVerdict::kFrozen);
    CHECK_FALSE(again.frozen_on_reference);
  }
  SECTION("a frame unlike the reference everywhere is no press") {
    // Another picture: a pattern over it all (the camera knocked, a light gone or come).
    cv::Mat texture(kHeight, kWidth, CV_32FC3);
    cv::randu(texture, cv::Scalar::all(-1.0), cv::Scalar::all(1.0));
    cv::GaussianBlur(texture, texture, cv::Size(), 4.0);
    cv::Mat other;
    Capture(8).convertTo(other, CV_32FC3);
    other += 100.0 * texture;
    other.convertTo(other, CV_8UC3);
    const auto changed = check.Check(other, {240, 120});
    CHECK(changed.verdict == PressVerdict::kChangedEverywhere);
    CHECK(check.NullSamples() == 128);  // its windows are no sample of "nothing pressed"
  }
  SECTION("a user's fixed threshold") {
    gs360::PressCheckOptions fixed;
    fixed.min_snr = 1000.0;
    gs360::PressCheck strict(fixed, Grid());
    strict.SetReference(Capture(1), Capture(2));
    CHECK(strict.Threshold() == 1000.0);
    const auto r = strict.Check(Capture(3, 3.0), {240, 120});
    CHECK(r.verdict == PressVerdict::kNoImpression);
    CHECK(r.null_samples == 0);
  }
}

TEST_CASE("PressCheck: a camera without noise still needs a change to count",
          "[capture][press_check]") {
  cv::Mat flat(kHeight, kWidth, CV_8UC3, cv::Scalar(60, 90, 120));
  gs360::PressCheck check({}, Grid());
  check.SetReference(flat, flat.clone());
  CHECK(check.Threshold() == gs360::kMinImpressionSnr);
  cv::Mat press = flat.clone();
  cv::circle(press, cv::Point(240, 120), 6, cv::Scalar(62, 90, 118), cv::FILLED);
  CHECK(check.Check(press, {240, 120}).verdict == PressVerdict::kImpression);
  cv::Mat speck = flat.clone();
  speck.at<cv::Vec3b>(120, 240) = cv::Vec3b(61, 90, 120);  // one pixel rounded the other way
  CHECK(check.Check(speck, {240, 120}).verdict == PressVerdict::kNoImpression);
}

namespace {

// Scene() with Capture()'s noise drawn by OpenCV (faster, for many frames), spread over a
// Gaussian of sigma grain_px (0: white) at the same sigma per pixel: a camera whose demosaicing
// shares each pixel's noise with its neighbours.
cv::Mat FastCapture(std::uint64_t seed, double grain_px) {
  cv::Mat noise(kHeight, kWidth, CV_32FC3);
  cv::RNG rng(seed);
  rng.fill(noise, cv::RNG::NORMAL, 0.0, 1.0);
  if (grain_px > 0.0) {
    cv::GaussianBlur(noise, noise, cv::Size(), grain_px, grain_px, cv::BORDER_REFLECT);
    noise *= 2.0 * std::sqrt(3.14159265358979323846) * grain_px;
  }
  cv::Mat bright = noise.colRange(0, kWidth / 2), dim = noise.colRange(kWidth / 2, kWidth);
  bright *= 4.0;
  dim *= 1.5;
  cv::Mat out;
  cv::Mat(Scene(0.0, {}, 8.0, true) + noise).convertTo(out, CV_8UC3);
  return out;
}

}  // namespace

TEST_CASE("DifferenceNoise at a wide blur: the finer one's by level, scaled as the pair shows",
          "[capture][press_check]") {
  // White noise: a blur 4 times wider averages it 4 times down. Noise shared over neighbours
  // (sigma 2.5 px): less, sqrt((2.5^2 + 2^2) / (2.5^2 + 8^2)) = 0.38.
  const double grain = GENERATE(0.0, 2.5);
  const double expected = std::sqrt((grain * grain + 4.0) / (grain * grain + 64.0));
  const cv::Mat a = FastCapture(1, grain), b = FastCapture(2, grain);
  const gs360::DifferenceNoise fine(a, b, 2.0), wide(a, b, 8.0, fine);
  CHECK(wide.blur_sigma_px() == 8.0);
  // This frame holds some 100 independent spots of an 8 px blur: each channel's factor is good to
  // about 10 %, their mean to about 5 %.
  const double levels[3] = {144.0, 180.0, 108.0};
  double factor = 0.0;
  for (int c = 0; c < 3; ++c) factor += wide.Sigma(c, levels[c]) / fine.Sigma(c, levels[c]) / 3.0;
  CHECK(factor == Approx(expected).epsilon(0.1));
  CHECK(wide.Sigma(1, 180.0) / wide.Sigma(1, 40.0) == Approx(4.0 / 1.5).epsilon(0.15));
  CHECK_THROWS_AS(gs360::DifferenceNoise(a, b, 2.0, fine), std::invalid_argument);
  CHECK_THROWS_AS(gs360::DifferenceNoise(a, b, 8.0, gs360::DifferenceNoise()),
                  std::invalid_argument);
}

TEST_CASE("PressCheck: a large faint impression counts when measured at a wide blur too",
          "[capture][press_check]") {
  // At one in a million, where a single blur leaves this impression just under the threshold.
  gs360::PressCheckOptions narrow, every;
  narrow.blur_sigmas_px = {2.0};
  narrow.false_accept = every.false_accept = 1e-6;
  gs360::PressCheck single(narrow, Grid()), multi(every, Grid());
  const cv::Mat reference = Capture(1), second = Capture(2);
  single.SetReference(reference, second);
  multi.SetReference(reference, second);
  // A shade of 0.8 DN over a spot of sigma 10 px (an impression near the camera, in a dimly lit
  // part) where the noise is 1.5 DN per pixel: the 2 px blur leaves it in its noise, a wider one
  // does not.
  for (std::uint64_t seed = 10; seed < 15; ++seed) {
    const cv::Mat press = Capture(seed, 0.8, {240, 120}, 1.0, 10.0, /*two_sided=*/false);
    const gs360::PressCheckResult at_one = single.Check(press, {240, 120});
    const gs360::PressCheckResult at_every = multi.Check(press, {240, 120});
    CHECK(at_one.verdict == PressVerdict::kNoImpression);
    CHECK(at_every.verdict == PressVerdict::kImpression);
    CHECK(at_every.press.blur_sigma_px > 2.0);
    CHECK((at_every.press.peak_px - Eigen::Vector2d(240, 120)).norm() < 10.0);
  }
  // A small sharp one stands out most at the finest.
  const gs360::PressCheckResult small =
      multi.Check(Capture(20, 20.0, {240, 120}, 1.0, 2.0), {240, 120});
  CHECK(small.verdict == PressVerdict::kImpression);
  CHECK(small.press.blur_sigma_px == every.blur_sigmas_px.front());
}

TEST_CASE("PressCheck: frames without an impression pass at the false-accept rate",
          "[capture][press_check]") {
  // At false_accept 1 %, about 10 of 1,000 frames of noise alone pass (a Poisson count: 2 to 25
  // but once in a thousand draws), with white noise and with noise shared between neighbouring
  // pixels, which a wide blur averages away less.
  const double grain = GENERATE(0.0, 2.5);
  gs360::PressCheckOptions o;
  o.false_accept = 0.01;
  const std::vector<Eigen::Vector2d> grid = Grid();
  gs360::PressCheck check(o, grid);
  check.SetReference(FastCapture(1, grain), FastCapture(2, grain));
  constexpr int kFrames = 1000;
  int passed = 0;
  for (int i = 0; i < kFrames; ++i) {
    const gs360::PressCheckResult r =
        check.Check(FastCapture(100 + i, grain), grid[(7 * i) % grid.size()]);
    REQUIRE(r.verdict != PressVerdict::kFrozen);
    if (r.verdict == PressVerdict::kImpression) ++passed;
  }
  CHECK(passed >= 2);
  CHECK(passed <= 25);
}

TEST_CASE("PressCheckOptions::Check names the field", "[capture][press_check]") {
  gs360::PressCheckOptions o;
  o.false_accept = 0.5;
  CHECK_THROWS_WITH(o.Check(), Contains("false_accept"));
  o = {};
  o.min_snr = -1.0;
  CHECK_THROWS_WITH(o.Check(), Contains("min_snr"));
  o = {};
  o.press_null_windows = 0;
  CHECK_THROWS_WITH(gs360::PressCheck(o, Grid()), Contains("press_null_windows"));
  for (const std::vector<double>& bad : std::vector<std::vector<double>>{
           {}, {2.0, 2.0}, {4.0, 2.0}, {-1.0}, {2.0, 60.0}, {1.0, 2.0, 3.0, 4.0, 5.0}}) {
    o = {};
    o.blur_sigmas_px = bad;
    CHECK_THROWS_WITH(o.Check(), Contains("blur_sigmas_px"));
  }
  o = {};
  o.blur_sigmas_px = {0.0, 3.0};
  CHECK_NOTHROW(o.Check());
}

namespace {

// A press at height z (mm) and azimuth (deg) on a finger of radius 10.
Eigen::Vector3d At(double z, double azimuth_deg) {
  const double a = azimuth_deg * 3.14159265358979323846 / 180.0;
  return {10.0 * std::cos(a), 10.0 * std::sin(a), z};
}

}  // namespace

TEST_CASE("ImpressionRegionTally names a dim region by height and azimuth",
          "[capture][press_check]") {
  gs360::ImpressionRegionTally tally;
  // Strong impressions everywhere, in a well lit gel (reference level 120 DN)...
  for (double z = 1.0; z < 30.0; z += 1.0) {
    for (double a = -175.0; a < 180.0; a += 10.0) tally.Add(At(z, a), 80.0, 8.0, 120.0);
  }
  CHECK(tally.WeakRegions().empty());
  // ...but between 12 and 24 mm at azimuth 30-90 deg the LEDs light it at a third of that.
  for (double z = 12.5; z < 24.0; z += 1.0) {
    for (double a = 35.0; a < 90.0; a += 10.0) {
      for (int k = 0; k < 2; ++k) tally.Add(At(z, a), z < 14.0 ? 7.0 : 11.0, 8.0, 40.0);
    }
  }
  const auto regions = tally.WeakRegions();
  REQUIRE(regions.size() == 1);
  const gs360::WeakRegion& r = regions[0];
  CHECK(r.z_min_mm == Approx(12.0));
  CHECK(r.z_max_mm == Approx(23.5));
  CHECK(r.azimuth_min_deg == Approx(30.0));
  CHECK(r.azimuth_max_deg == Approx(90.0));
  CHECK_FALSE(r.all_around);
  CHECK(r.presses == 216);
  CHECK(r.weak == 144);
  CHECK(r.failed == 24);
  CHECK(r.dim);
  CHECK_THAT(r.Describe(),
             Contains("z 12.0-23.5 mm at azimuth 30 to 90 deg") && Contains("144 of 216") &&
                 Contains("24 of them too faint to count") && Contains("LEDs light it dimly"));
}

TEST_CASE("ImpressionRegionTally: a band weak all around, a range across 180 deg",
          "[capture][press_check]") {
  gs360::ImpressionRegionTally tally;
  for (double z = 0.5; z < 20.0; z += 1.0) {
    for (double a = -175.0; a < 180.0; a += 10.0) {
      const bool low = z < 6.0;
      const bool back = (a > 150.0 || a < -150.0) && z > 10.0;
      tally.Add(At(z, a), low || back ? 9.0 : 60.0, 6.0, back ? 110.0 : 100.0);
    }
  }
  const auto regions = tally.WeakRegions();
  REQUIRE(regions.size() == 2);
  CHECK_THAT(regions[0].Describe(), Contains("z 0.5-5.5 mm all around"));
  CHECK_THAT(regions[1].Describe(),
             Contains("z 9.5-19.5 mm at azimuth 150 to 180 and -180 to -150 deg") &&
                 Contains("It is not dim"));
  CHECK_FALSE(regions[1].dim);
  gs360::ImpressionRegionOptions o;
  o.weak_factor = 1.0;
  CHECK_THROWS_WITH(gs360::ImpressionRegionTally(o), Contains("weak_factor"));
}
