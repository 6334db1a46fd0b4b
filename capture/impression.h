#pragma once
// Where a press shows in the image: the blob of the difference between a press frame and a
// no-contact reference frame. Used by resume (has the sensor moved?) and by calibration (the
// impression centres that pose estimation fits).

#include <Eigen/Core>
#include <optional>

#include <opencv2/core/mat.hpp>

namespace gs360 {

struct ImpressionOptions {
  double blur_sigma_px = 2.0;        // Gaussian blur of the difference magnitude (noise)
  double min_peak_dn = 6.0;          // weaker peaks are "no impression" (DN, 8-bit scale)
  double threshold_fraction = 0.35;  // blob = connected pixels above this fraction of the peak
  // A blob over more than this fraction of the usable pixels is no press but a frame unlike the
  // reference everywhere (saturated, black, corrupt, the lighting changed): no impression.
  double max_area_fraction = 0.25;
  void Check() const;  // throws std::invalid_argument naming the field and value
};

struct Impression {
  Eigen::Vector2d centroid = Eigen::Vector2d::Zero();  // pixels (u right, v down), weighted
  double peak_dn = 0.0;  // peak of the blurred colour-difference magnitude
  int pixels = 0;        // blob area
  cv::Rect box;          // blob bounding box
};

// The blurred colour-difference magnitude both impression finders start from: per pixel
// |press - reference| over the three channels (DN), 0 where `mask` is 0, then a Gaussian blur of
// blur_sigma_px (none if 0). CV_32F. Throws std::invalid_argument, naming `caller`, for inputs
// that are not CV_8UC3 of one size or a mask that is not CV_8U of that size.
cv::Mat DifferenceMagnitude(const cv::Mat& press, const cv::Mat& reference, const cv::Mat& mask,
                            double blur_sigma_px, const char* caller);

// `press` and `reference`: CV_8UC3 of equal size (std::invalid_argument otherwise). Optional
// `mask` (CV_8U, non-zero = usable pixel, e.g. not behind a fin). Returns nullopt when no blob
// reaches min_peak_dn (no contact visible) or the blob covers more than max_area_fraction of the
// usable pixels (not a press).
std::optional<Impression> FindImpression(const cv::Mat& press, const cv::Mat& reference,
                                         const ImpressionOptions& options = {},
                                         const cv::Mat& mask = cv::Mat());

// An impression whose centre can be trusted to a pixel (what the resume re-check compares):
// FindImpression with default options, a peak of at least `min_peak_dn` and a blob smaller than a
// quarter of the frame each way. Noise or LED drift alone gives a faint peak spread over much of
// the frame, whose centre moves by tens of pixels. nullopt otherwise; throws as FindImpression.
std::optional<Impression> FindClearImpression(const cv::Mat& press, const cv::Mat& reference,
                                              double min_peak_dn);

// Below this correlation (ImpressionShift::score) the impression has changed shape, not only
// place: the same press captured twice on the virtual rig scores at least 0.996, the sensor
// moved 0.6 mm sideways down to 0.64.
inline constexpr double kMinImpressionMatch = 0.9;

// How far a press's impression lies from where an earlier capture of the same press put it.
struct ImpressionShift {
  Eigen::Vector2d px = Eigen::Vector2d::Zero();  // now minus then (u right, v down), pixels
  double score = 0.0;  // normalised cross-correlation at the best alignment, in [-1, 1]
  // The best alignment lies at the edge of the search window: the shift is at least that far.
  bool at_search_limit = false;
};

// The displacement that best aligns the blurred colour-difference magnitude (DifferenceMagnitude,
// ImpressionOptions' blur) of (press, reference) with that of (stored_press, stored_reference)
// over `stored`'s blob box padded by 6 px, searched up to `search_px` each way, to a fraction of a
// pixel by a parabola through the correlation peak. Unlike the distance between two
// FindImpression centroids it does not depend on where each capture's threshold cuts the blob:
// noise that joins a side lobe to the blob or moves the peak to another lobe moves a centroid by
// 1 to 40 px on the virtual rig, and this by a few hundredths (docs/running.md has the figures).
// Throws std::invalid_argument for frames that are not CV_8UC3 of one size.
ImpressionShift MeasureImpressionShift(const cv::Mat& stored_press, const cv::Mat& stored_reference,
                                       const Impression& stored, const cv::Mat& press,
                                       const cv::Mat& reference, int search_px = 32);

// The resume re-check's distance (px) between a stored impression and its re-press: |shift.px|
// when the correlation is trusted (score >= kMinImpressionMatch, not at the search limit), else
// the larger of that and the distance between the two centroids (a changed or far-moved
// impression must not look still).
double ImpressionDistance(const ImpressionShift& shift, const Impression& stored,
                          const Impression& now);

// How much the change near `expected_px` stands out of the whole frame's: the largest blurred
// colour difference (DifferenceMagnitude, blur_sigma_px) within `radius_px` of it, over the 99th
// percentile of the difference over the frame's pixels (where `mask` allows). A press near
// there gives a local bump well above 1; a frame whose change is only noise and slow
// illumination drift gives about 1 (docs/running.md has the figures on the virtual rig). Returns 0
// when the window lies outside the image. Throws as DifferenceMagnitude.
double ImpressionContrast(const cv::Mat& press, const cv::Mat& reference,
                          const Eigen::Vector2d& expected_px, double radius_px,
                          double blur_sigma_px = 2.0, const cv::Mat& mask = cv::Mat());

}  // namespace gs360
