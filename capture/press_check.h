#pragma once
// Whether a press frame shows its press: a change near where the plan puts the probe that the
// session's own noise cannot explain. The change is measured at a few blur scales, each a matched
// filter for an impression of about its size (a small sharp one, or a large faint one near the
// camera that a narrow blur would leave buried in its noise), and the largest standardized change
// over them is the statistic. What the decision compares with is measured in the session, not set
// on a rig: the camera's noise at each scale, from two no-contact captures taken back to back at
// each reference (DifferenceNoise); and the statistic's distribution where nothing was pressed
// (windows of that pair, and windows of each press frame far from its press, measured with the same
// scales), to which the threshold is fitted. The fixed numbers are a probability (how often a frame
// with no impression may pass) and a floor for a camera without noise, whose null distribution is
// zero.
//
// Images: CV_8UC3 of one size (std::invalid_argument otherwise), pixels (u right, v down).

#include <Eigen/Core>
#include <cstdint>
#include <deque>
#include <random>
#include <vector>

#include <opencv2/core/mat.hpp>

namespace gs360 {

// The camera's noise as a difference of two captures shows it: per channel, the spread of the
// blurred difference between two no-contact captures taken back to back, as a function of the
// blurred level (shot noise grows with the light; a fin, a dim patch and the lens's dark border
// each get their own), at least what rounding to 8 bits gives.
class DifferenceNoise {
 public:
  DifferenceNoise() = default;
  // Measured level by level at blur_sigma_px (in [0, 50]), from pixels at least 2 blur sigmas
  // from the image's edge (nearer, the blur took mirrored pixels: the same noise twice). Throws
  // std::invalid_argument for images that are not CV_8UC3 of one size or a blur out of range.
  DifferenceNoise(const cv::Mat& reference, const cv::Mat& second, double blur_sigma_px);
  // At a wider blur: `finer`'s spread level by level, times one factor per channel, the spread of
  // the pair's difference at this blur over `finer`'s, pooled over the image's pixels lit alike
  // across this blur (a wide blur leaves too few independent pixels at each level to measure each
  // on its own; how much a blur divides the noise depends on how far the noise is shared between
  // neighbours, not on the light). With too few such pixels (a camera without noise), the factor
  // a white noise would show. Throws std::invalid_argument as above, for an empty `finer`, or a
  // blur_sigma_px not above finer's.
  DifferenceNoise(const cv::Mat& reference, const cv::Mat& second, double blur_sigma_px,
                  const DifferenceNoise& finer);
  bool empty() const { return blur_sigma_px_ < 0.0; }
  double blur_sigma_px() const { return blur_sigma_px_; }
  // Sigma (DN) of a blurred difference of two captures in `channel` (0..2) at `level` (DN).
  double Sigma(int channel, double level) const;

 private:
  // Of 2 DN each: near black, where a capture clips at 0, the noise changes within a few DN.
  static constexpr int kBins = 128;
  double blur_sigma_px_ = -1.0;
  double sigma_[3][kBins] = {};
};

// The change near an expected pixel, in units of the camera's noise there.
struct ImpressionSnr {
  double snr = 0.0;                                   // largest standardized change (no unit)
  Eigen::Vector2d peak_px = Eigen::Vector2d::Zero();  // where it is
  double blur_sigma_px = 0.0;                         // the blur it was measured at (px)
  double peak_dn = 0.0;       // the change there, DN (8-bit scale, blurred, drift removed)
  double noise_dn = 0.0;      // the noise there (root mean square of the three channels), DN
  double reference_dn = 0.0;  // the reference's mean level over the window (DN): how lit it is
};

// D: press minus reference per channel, blurred by the noise's blur with its sign (the noise
// averages out, unlike in DifferenceMagnitude's magnitude), less the part proportional to the
// blurred reference level L that fits the window best (median of D / L per channel: LED drift
// scales all the light); s: noise.Sigma at L. snr: the largest sqrt(sum_c (D_c / s_c)^2) within
// radius_px of expected_px and at least 2 blur sigmas from the image's edge; 0 when there is no
// such pixel. Throws std::invalid_argument for images that are not CV_8UC3 of one size or an empty
// noise.
ImpressionSnr MeasureImpressionSnr(const cv::Mat& press, const cv::Mat& reference,
                                   const DifferenceNoise& noise, const Eigen::Vector2d& expected_px,
                                   double radius_px);

// The value that one more draw of what `samples` are draws of (maxima: a Gumbel distribution,
// fitted to their median and median absolute deviation, so a few odd ones do not move it)
// exceeds with probability `chance` in (0, 1). Throws std::invalid_argument for no samples.
double GumbelQuantileAbove(std::vector<double> samples, double chance);

// Under the session's threshold: a camera without noise (a noise-free virtual rig) measures
// nothing where nothing was pressed, and a threshold fitted to that would be zero.
inline constexpr double kMinImpressionSnr = 5.0;

struct PressCheckOptions {
  double radius_px = 40.0;  // how far from the expected pixel the impression may lie, > 0
  // The blurs (Gaussian sigma, px) the change is measured at: 1 to 4 of them, increasing, in
  // [0, 50].
  std::vector<double> blur_sigmas_px = {1.0, 2.0, 4.0, 8.0};
  // The chance that a press frame without an impression near the expected pixel passes, under
  // the session's measured null distribution: in (0, 0.01]. One in 10,000: were not one press of
  // the largest run (10,000 probes) to touch the gel, about one would be counted. A lower chance
  // only raises the threshold and loses real presses where the light is weakest, the data the
  // model has least of.
  double false_accept = 1e-4;
  double min_snr = 0.0;  // > 0: a fixed threshold instead of the session's (a user's override)
  int reference_null_windows = 128;  // null samples from each reference pair, >= 1
  int press_null_windows = 2;        // null samples from each press frame, >= 1
  int max_null_samples = 4096;       // the newest are kept, >= 1
  std::uint64_t seed = 1;            // which planned pixels the null windows sit on
  void Check() const;                // throws std::invalid_argument naming the field and value
};

enum class PressVerdict {
  kImpression,         // the press shows near the expected pixel: it counts
  kNoImpression,       // nothing there stands out of the session's noise
  kChangedEverywhere,  // the frame differs from the reference where nothing was pressed too
  kFrozen,             // the frame is identical to the reference or to the previous press frame
};

struct PressCheckResult {
  PressVerdict verdict = PressVerdict::kNoImpression;
  ImpressionSnr press;               // at the expected pixel
  double threshold = 0.0;            // the snr the press had to reach
  int null_samples = 0;              // the threshold's sample (0: min_snr or the floor alone)
  double null_snr = 0.0;             // the smallest snr of this frame's own null windows (0: none)
  bool frozen_on_reference = false;  // kFrozen: the same as the reference (else: the last press)
};

// One session's check: a reference pair, then press frames.
class PressCheck {
 public:
  // `plan_px`: where the plan's probes project (the null windows sit on them: places on the
  // gel). Throws std::invalid_argument for invalid options.
  PressCheck(const PressCheckOptions& options, std::vector<Eigen::Vector2d> plan_px);

  // A new no-contact reference and a second capture of it: the noise, and null samples.
  void SetReference(const cv::Mat& reference, const cv::Mat& second);
  bool HasReference() const { return !reference_.empty(); }
  // Throws std::logic_error without a reference.
  PressCheckResult Check(const cv::Mat& press, const Eigen::Vector2d& expected_px);
  // The snr a press must reach now: min_snr if set, else the session's null quantile at
  // false_accept, at least kMinImpressionSnr.
  double Threshold() const;
  int NullSamples() const { return static_cast<int>(null_.size()); }
  // The q-quantile (q in [0, 1]) of the null samples kept; 0 without any.
  double NullQuantile(double q) const;

 private:
  // MeasureImpressionSnr at every blur, the largest; `blurred`: `press` blurred at each (the whole
  // image, as level_), or null to blur its window here.
  ImpressionSnr Measure(const cv::Mat& press, const Eigen::Vector2d& at,
                        const std::vector<cv::Mat>* blurred = nullptr) const;
  // Up to `count` planned pixels farther than `away_px` from `from` (all when away_px is 0).
  std::vector<Eigen::Vector2d> NullPlaces(const Eigen::Vector2d& from, double away_px, int count);
  void AddNull(double snr);

  PressCheckOptions options_;
  std::vector<Eigen::Vector2d> plan_px_;
  std::mt19937_64 rng_;
  cv::Mat reference_, second_, last_press_;
  std::vector<DifferenceNoise> noise_;  // one per blur, finest first
  std::vector<cv::Mat> level_;          // the reference at each blur (CV_32FC3, whole image)
  std::deque<double> null_;
};

}  // namespace gs360
