#include "capture/press_check.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

namespace gs360 {
namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kMadToSigma = 1.4826;  // a normal distribution's sigma over its MAD
// The standard Gumbel distribution's median and median absolute deviation.
constexpr double kGumbelMedian = 0.36651292058166435;
constexpr double kGumbelMad = 0.7670492513257081;

void CheckImages(const cv::Mat& a, const cv::Mat& b, const char* caller) {
  if (a.type() != CV_8UC3 || b.type() != CV_8UC3 || a.size() != b.size()) {
    throw std::invalid_argument(std::string(caller) +
                                ": the images must be CV_8UC3 of the reference's size");
  }
}

// `image` over `roi` as CV_32FC3, blurred (none if blur is 0) over the ROI padded by the kernel's
// reach (4 sigma), so that its border is no different from its middle, and the ROI is the same as
// the whole image blurred.
cv::Mat Blurred(const cv::Mat& image, const cv::Rect& roi, double blur) {
  const int pad = blur > 0.0 ? static_cast<int>(std::ceil(4.0 * blur)) : 0;
  const cv::Rect outer =
      cv::Rect(roi.x - pad, roi.y - pad, roi.width + 2 * pad, roi.height + 2 * pad) &
      cv::Rect(0, 0, image.cols, image.rows);
  cv::Mat f;
  image(outer).convertTo(f, CV_32FC3);
  if (blur > 0.0) {
    cv::GaussianBlur(f, f, cv::Size(2 * pad + 1, 2 * pad + 1), blur, blur, cv::BORDER_REFLECT);
  }
  return f(cv::Rect(roi.x - outer.x, roi.y - outer.y, roi.width, roi.height)).clone();
}

// How far from the image's edge a pixel's blur stays a fair measure: nearer, the blur reached past
// the edge and took mirrored pixels, the same noise twice (up to twice its variance at the edge).
int EdgeMargin(double blur) {
  return static_cast<int>(std::ceil(2.0 * blur));
}

// The square of radius_px around `at` within an image of `size` (empty when outside it).
cv::Rect Window(const Eigen::Vector2d& at, double radius_px, const cv::Size& size) {
  const int r = static_cast<int>(std::ceil(radius_px));
  return cv::Rect(static_cast<int>(std::lround(at.x())) - r,
                  static_cast<int>(std::lround(at.y())) - r, 2 * r + 1, 2 * r + 1) &
         cv::Rect(0, 0, size.width, size.height);
}

double Median(std::vector<float>& v) {
  if (v.empty()) return 0.0;
  const auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

// A normal distribution's sigma that fits v's median absolute deviation (v is reordered).
double RobustSigma(std::vector<float>& v) {
  const double median = Median(v);
  for (float& e : v) e = static_cast<float>(std::abs(e - median));
  return kMadToSigma * Median(v);
}

// Over the whole image, blurred by `blur`: the pair's difference `n` and their mean level.
void PairDifference(const cv::Mat& reference, const cv::Mat& second, double blur, cv::Mat* n,
                    cv::Mat* level) {
  const cv::Rect all(0, 0, reference.cols, reference.rows);
  const cv::Mat first = Blurred(reference, all, blur);
  const cv::Mat then = Blurred(second, all, blur);
  *n = then - first;
  // Binned by the pair's mean, whose noise is independent of their difference's (binned by one
  // capture's level, a bin's edge would sort its pixels by that capture's noise).
  *level = 0.5 * (first + then);
}

void CheckBlur(double blur_sigma_px) {
  if (!(blur_sigma_px >= 0.0 && blur_sigma_px <= 50.0)) {
    throw std::invalid_argument("DifferenceNoise: blur_sigma_px must be in [0, 50], got " +
                                std::to_string(blur_sigma_px));
  }
}

// The noise that rounding each capture to 8 bits leaves in a blurred difference of two: uniform
// +-0.5 DN each (variance 1/12), and a Gaussian blur of sigma b divides a white noise's sigma by
// 2 sqrt(pi) b.
double QuantisationSigma(double blur) {
  const double raw = std::sqrt(2.0 / 12.0);
  return blur >= 0.5 ? raw / (2.0 * std::sqrt(kPi) * blur) : raw;
}

// Per channel, the gain change (D / L) that fits the window: the median over its pixels lit
// enough for the ratio to mean something.
void DriftGain(const cv::Mat& d, const cv::Mat& level, double gain[3]) {
  constexpr float kMinLevel = 8.0f;  // DN: below, the ratio is noise over next to nothing
  std::vector<float> ratio[3];
  for (int y = 0; y < d.rows; ++y) {
    const cv::Vec3f* dr = d.ptr<cv::Vec3f>(y);
    const cv::Vec3f* lr = level.ptr<cv::Vec3f>(y);
    for (int x = 0; x < d.cols; ++x) {
      for (int c = 0; c < 3; ++c) {
        if (lr[x][c] >= kMinLevel) ratio[c].push_back(dr[x][c] / lr[x][c]);
      }
    }
  }
  for (int c = 0; c < 3; ++c) {
    gain[c] = ratio[c].size() * 4 >= d.total() ? Median(ratio[c]) : 0.0;
  }
}

}  // namespace

DifferenceNoise::DifferenceNoise(const cv::Mat& reference, const cv::Mat& second,
                                 double blur_sigma_px) {
  CheckImages(second, reference, "DifferenceNoise");
  CheckBlur(blur_sigma_px);
  cv::Mat n, level;
  PairDifference(reference, second, blur_sigma_px, &n, &level);
  std::vector<float> bins[3][kBins];
  const int m = EdgeMargin(blur_sigma_px);
  for (int y = m; y < n.rows - m; ++y) {
    const cv::Vec3f* nr = n.ptr<cv::Vec3f>(y);
    const cv::Vec3f* lr = level.ptr<cv::Vec3f>(y);
    for (int x = m; x < n.cols - m; ++x) {
      for (int c = 0; c < 3; ++c) {
        // Exactly equal over the blur's reach: clipped to black (outside the lens's image
        // circle), or a camera without noise. Such pixels say nothing of the noise elsewhere at
        // their level (the edge of that circle), and a press changes nothing there either.
        if (nr[x][c] == 0.0f) continue;
        const int b = std::clamp(static_cast<int>(lr[x][c] / (256.0f / kBins)), 0, kBins - 1);
        bins[c][b].push_back(nr[x][c]);
      }
    }
  }
  // A level with too few pixels to say takes the figure of the nearest level that has enough.
  constexpr std::size_t kMinPixels = 200;
  for (int c = 0; c < 3; ++c) {
    double measured[kBins];
    for (int b = 0; b < kBins; ++b) {
      measured[b] = bins[c][b].size() < kMinPixels ? -1.0 : RobustSigma(bins[c][b]);
    }
    for (int b = 0; b < kBins; ++b) {
      sigma_[c][b] = 0.0;
      for (int k = 0; k < kBins; ++k) {
        if (b - k >= 0 && measured[b - k] >= 0.0) {
          sigma_[c][b] = measured[b - k];
          break;
        }
        if (b + k < kBins && measured[b + k] >= 0.0) {
          sigma_[c][b] = measured[b + k];
          break;
        }
      }
    }
  }
  const double floor = QuantisationSigma(blur_sigma_px);
  for (auto& channel : sigma_) {
    for (double& s : channel) s = std::max(s, floor);
  }
  blur_sigma_px_ = blur_sigma_px;
}

DifferenceNoise::DifferenceNoise(const cv::Mat& reference, const cv::Mat& second,
                                 double blur_sigma_px, const DifferenceNoise& finer) {
  CheckImages(second, reference, "DifferenceNoise");
  CheckBlur(blur_sigma_px);
  if (finer.empty()) throw std::invalid_argument("DifferenceNoise: no finer noise measured");
  if (!(blur_sigma_px > finer.blur_sigma_px_)) {
    throw std::invalid_argument("DifferenceNoise: blur_sigma_px must be above the finer noise's " +
                                std::to_string(finer.blur_sigma_px_) + ", got " +
                                std::to_string(blur_sigma_px));
  }
  cv::Mat n, level, unused, fine_level;
  PairDifference(reference, second, blur_sigma_px, &n, &level);
  PairDifference(reference, second, finer.blur_sigma_px_, &unused, &fine_level);
  // Pooled over pixels whose surroundings are lit alike (their level at this blur and at the
  // finer one within 1 DN + 5 %): across a light's edge, the blur averages the noise of both
  // sides, which the noise at no one level describes.
  std::vector<float> ratio[3];
  const int m = EdgeMargin(blur_sigma_px);
  for (int y = m; y < n.rows - m; ++y) {
    const cv::Vec3f* nr = n.ptr<cv::Vec3f>(y);
    const cv::Vec3f* lr = level.ptr<cv::Vec3f>(y);
    const cv::Vec3f* fr = fine_level.ptr<cv::Vec3f>(y);
    for (int x = m; x < n.cols - m; ++x) {
      for (int c = 0; c < 3; ++c) {
        if (nr[x][c] == 0.0f || std::abs(lr[x][c] - fr[x][c]) > 1.0f + 0.05f * fr[x][c]) continue;
        ratio[c].push_back(static_cast<float>(nr[x][c] / finer.Sigma(c, lr[x][c])));
      }
    }
  }
  // Pixels a wide blur averages share most of their noise: the factor needs some 50 blurs'
  // worth of them. Without (a camera without noise), what a blur does to white noise.
  const double min_pixels = std::max(200.0, 50.0 * 4.0 * kPi * blur_sigma_px * blur_sigma_px);
  const double white = QuantisationSigma(blur_sigma_px) / QuantisationSigma(finer.blur_sigma_px_);
  const double floor = QuantisationSigma(blur_sigma_px);
  for (int c = 0; c < 3; ++c) {
    const double factor = ratio[c].size() >= min_pixels ? RobustSigma(ratio[c]) : white;
    for (int b = 0; b < kBins; ++b) sigma_[c][b] = std::max(factor * finer.sigma_[c][b], floor);
  }
  blur_sigma_px_ = blur_sigma_px;
}

double DifferenceNoise::Sigma(int channel, double level) const {
  const int b = std::clamp(static_cast<int>(level / (256.0 / kBins)), 0, kBins - 1);
  return sigma_[std::clamp(channel, 0, 2)][b];
}

namespace {

ImpressionSnr Unmeasured(const Eigen::Vector2d& at, const DifferenceNoise& noise) {
  ImpressionSnr out;
  out.peak_px = at;
  out.blur_sigma_px = noise.blur_sigma_px();
  return out;
}

// The largest standardized change within radius_px of expected_px: `shown` (the press) less
// `level` (the reference), both blurred at the noise's blur over `window`, less the drift.
ImpressionSnr PeakSnr(const cv::Mat& shown, const cv::Mat& level, const cv::Mat& reference,
                      const cv::Rect& window, const DifferenceNoise& noise,
                      const Eigen::Vector2d& expected_px, double radius_px) {
  ImpressionSnr out = Unmeasured(expected_px, noise);
  const cv::Mat d = shown - level;
  double gain[3];
  DriftGain(d, level, gain);
  const cv::Scalar mean = cv::mean(reference(window));
  out.reference_dn = (mean[0] + mean[1] + mean[2]) / 3.0;

  const double r2 = radius_px * radius_px;
  const int m = EdgeMargin(noise.blur_sigma_px());
  const cv::Rect fair =
      cv::Rect(m - window.x, m - window.y, reference.cols - 2 * m, reference.rows - 2 * m) &
      cv::Rect(0, 0, d.cols, d.rows);
  double best = -1.0;
  for (int y = fair.y; y < fair.y + fair.height; ++y) {
    const cv::Vec3f* dr = d.ptr<cv::Vec3f>(y);
    const cv::Vec3f* lr = level.ptr<cv::Vec3f>(y);
    const double dv = window.y + y - expected_px.y();
    for (int x = fair.x; x < fair.x + fair.width; ++x) {
      const double du = window.x + x - expected_px.x();
      if (du * du + dv * dv > r2) continue;
      double z2 = 0.0, m2 = 0.0, s2 = 0.0;
      for (int c = 0; c < 3; ++c) {
        const double v = dr[x][c] - gain[c] * lr[x][c];
        const double s = noise.Sigma(c, lr[x][c]);
        z2 += v * v / (s * s);
        m2 += v * v;
        s2 += s * s;
      }
      if (z2 > best) {
        best = z2;
        out.peak_px = Eigen::Vector2d(window.x + x, window.y + y);
        out.peak_dn = std::sqrt(m2);
        out.noise_dn = std::sqrt(s2 / 3.0);
      }
    }
  }
  out.snr = std::sqrt(std::max(0.0, best));
  return out;
}

}  // namespace

ImpressionSnr MeasureImpressionSnr(const cv::Mat& press, const cv::Mat& reference,
                                   const DifferenceNoise& noise, const Eigen::Vector2d& expected_px,
                                   double radius_px) {
  CheckImages(press, reference, "MeasureImpressionSnr");
  if (noise.empty()) throw std::invalid_argument("MeasureImpressionSnr: no noise measured");
  const cv::Rect window = Window(expected_px, radius_px, press.size());
  if (window.empty()) return Unmeasured(expected_px, noise);
  const cv::Mat level = Blurred(reference, window, noise.blur_sigma_px());
  return PeakSnr(Blurred(press, window, noise.blur_sigma_px()), level, reference, window, noise,
                 expected_px, radius_px);
}

double GumbelQuantileAbove(std::vector<double> samples, double chance) {
  if (samples.empty()) throw std::invalid_argument("GumbelQuantileAbove: no samples");
  if (!(chance > 0.0 && chance < 1.0)) {
    throw std::invalid_argument("GumbelQuantileAbove: chance must be in (0, 1), got " +
                                std::to_string(chance));
  }
  const auto mid = samples.begin() + static_cast<std::ptrdiff_t>(samples.size() / 2);
  std::nth_element(samples.begin(), mid, samples.end());
  const double median = *mid;
  for (double& s : samples) s = std::abs(s - median);
  std::nth_element(samples.begin(), mid, samples.end());
  const double scale = *mid / kGumbelMad;
  const double location = median - kGumbelMedian * scale;
  return location - scale * std::log(-std::log1p(-chance));
}

void PressCheckOptions::Check() const {
  const auto bad = [](const std::string& field, double value, const char* rule) {
    throw std::invalid_argument("PressCheckOptions." + field + " must be " + rule + ", got " +
                                std::to_string(value));
  };
  if (!(radius_px > 0.0 && std::isfinite(radius_px))) bad("radius_px", radius_px, "> 0");
  const std::size_t scales = blur_sigmas_px.size();
  if (scales < 1 || scales > 4) bad("blur_sigmas_px's size", static_cast<double>(scales), "1..4");
  for (std::size_t i = 0; i < scales; ++i) {
    const double b = blur_sigmas_px[i];
    const double above = i == 0 ? -1.0 : blur_sigmas_px[i - 1];
    if (!(b > above && b >= 0.0 && b <= 50.0)) {
      bad("blur_sigmas_px[" + std::to_string(i) + "]", b, "in [0, 50] and above the one before");
    }
  }
  if (!(false_accept > 0.0 && false_accept <= 0.01)) {
    bad("false_accept", false_accept, "in (0, 0.01]");
  }
  if (!(min_snr >= 0.0 && std::isfinite(min_snr))) bad("min_snr", min_snr, ">= 0");
  if (reference_null_windows < 1) bad("reference_null_windows", reference_null_windows, ">= 1");
  if (press_null_windows < 1) bad("press_null_windows", press_null_windows, ">= 1");
  if (max_null_samples < 1) bad("max_null_samples", max_null_samples, ">= 1");
}

PressCheck::PressCheck(const PressCheckOptions& options, std::vector<Eigen::Vector2d> plan_px)
    : options_(options), plan_px_(std::move(plan_px)), rng_(options.seed) {
  options_.Check();
}

ImpressionSnr PressCheck::Measure(const cv::Mat& press, const Eigen::Vector2d& at,
                                  const std::vector<cv::Mat>* blurred) const {
  const cv::Rect window = Window(at, options_.radius_px, press.size());
  ImpressionSnr best = Unmeasured(at, noise_.front());
  if (window.empty()) return best;
  for (std::size_t i = 0; i < noise_.size(); ++i) {
    const cv::Mat shown =
        blurred ? (*blurred)[i](window) : Blurred(press, window, noise_[i].blur_sigma_px());
    const ImpressionSnr s =
        PeakSnr(shown, level_[i](window), reference_, window, noise_[i], at, options_.radius_px);
    if (i == 0 || s.snr > best.snr) best = s;
  }
  return best;
}

std::vector<Eigen::Vector2d> PressCheck::NullPlaces(const Eigen::Vector2d& from, double away_px,
                                                    int count) {
  std::vector<Eigen::Vector2d> far;
  for (const Eigen::Vector2d& p : plan_px_) {
    if ((p - from).norm() > away_px) far.push_back(p);
  }
  std::vector<Eigen::Vector2d> out;
  for (int k = 0; k < count && !far.empty(); ++k) {
    std::uniform_int_distribution<std::size_t> pick(0, far.size() - 1);
    const std::size_t i = pick(rng_);
    out.push_back(far[i]);
    far[i] = far.back();
    far.pop_back();
  }
  return out;
}

void PressCheck::AddNull(double snr) {
  null_.push_back(snr);
  while (static_cast<int>(null_.size()) > options_.max_null_samples) null_.pop_front();
}

void PressCheck::SetReference(const cv::Mat& reference, const cv::Mat& second) {
  if (reference.type() != CV_8UC3 || second.type() != CV_8UC3 ||
      reference.size() != second.size()) {
    throw std::invalid_argument(
        "PressCheck::SetReference: the two captures must be CV_8UC3 of one size");
  }
  // The reference at every blur once (each press's windows take theirs), and the second capture
  // too (many windows of it are measured here).
  const cv::Rect all(0, 0, reference.cols, reference.rows);
  const DifferenceNoise finest(reference, second, options_.blur_sigmas_px.front());
  noise_.assign(1, finest);
  level_.clear();
  std::vector<cv::Mat> second_blurred;
  for (std::size_t i = 0; i < options_.blur_sigmas_px.size(); ++i) {
    const double blur = options_.blur_sigmas_px[i];
    if (i > 0) noise_.emplace_back(reference, second, blur, finest);
    level_.push_back(Blurred(reference, all, blur));
    second_blurred.push_back(Blurred(second, all, blur));
  }
  reference_ = reference;
  second_ = second;
  last_press_.release();
  // The pair's own difference where nothing was pressed, measured against its own noise.
  for (const Eigen::Vector2d& at :
       NullPlaces(Eigen::Vector2d::Zero(), -1.0, options_.reference_null_windows)) {
    AddNull(Measure(second_, at, &second_blurred).snr);
  }
}

double PressCheck::Threshold() const {
  if (options_.min_snr > 0.0) return options_.min_snr;
  if (null_.empty()) return kMinImpressionSnr;
  return std::max(
      kMinImpressionSnr,
      GumbelQuantileAbove(std::vector<double>(null_.begin(), null_.end()), options_.false_accept));
}

double PressCheck::NullQuantile(double q) const {
  if (null_.empty()) return 0.0;
  std::vector<double> v(null_.begin(), null_.end());
  const auto at =
      v.begin() + static_cast<std::ptrdiff_t>(
                      std::clamp(q, 0.0, 1.0) * static_cast<double>(v.size() - 1) + 0.5);
  std::nth_element(v.begin(), at, v.end());
  return *at;
}

PressCheckResult PressCheck::Check(const cv::Mat& press, const Eigen::Vector2d& expected_px) {
  if (!HasReference()) throw std::logic_error("PressCheck::Check: no reference frame yet");
  PressCheckResult out;
  out.threshold = Threshold();
  out.null_samples = options_.min_snr > 0.0 ? 0 : NullSamples();
  out.press = Measure(press, expected_px);
  // A camera that stopped delivering new pictures: no two real captures are equal to the bit.
  const auto same = [&](const cv::Mat& other) {
    return !other.empty() && cv::norm(press, other, cv::NORM_INF) == 0.0;
  };
  if (same(reference_) || same(second_) || same(last_press_)) {
    out.verdict = PressVerdict::kFrozen;
    out.frozen_on_reference = same(reference_) || same(second_);
    return out;
  }
  last_press_ = press;
  // This frame where nothing was pressed: far enough that no part of its impression (the
  // window's radius from the expected pixel, plus the impression's own size) reaches them.
  std::vector<double> nulls;
  for (const Eigen::Vector2d& at :
       NullPlaces(expected_px, 4.0 * options_.radius_px, options_.press_null_windows)) {
    nulls.push_back(Measure(press, at).snr);
  }
  if (!nulls.empty()) out.null_snr = *std::min_element(nulls.begin(), nulls.end());
  if (!nulls.empty() && out.null_snr >= out.threshold) {
    out.verdict = PressVerdict::kChangedEverywhere;
    return out;
  }
  for (double s : nulls) AddNull(s);
  out.verdict =
      out.press.snr >= out.threshold ? PressVerdict::kImpression : PressVerdict::kNoImpression;
  return out;
}

}  // namespace gs360
