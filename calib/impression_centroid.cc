#include "calib/impression_centroid.h"

#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "capture/impression.h"

namespace gs360 {

void ImpressionCentroidOptions::Check() const {
  auto fail = [](const char* field, double value, const char* what) {
    throw std::invalid_argument(std::string("ImpressionCentroidOptions.") + field + " " + what +
                                ", got " + std::to_string(value));
  };
  if (!(blur_sigma_px >= 0.0)) fail("blur_sigma_px", blur_sigma_px, "must be >= 0");
  if (!(min_peak_dn > 0.0)) fail("min_peak_dn", min_peak_dn, "must be > 0");
  if (!(threshold_fraction > 0.0 && threshold_fraction < 1.0)) {
    fail("threshold_fraction", threshold_fraction, "must be in (0, 1)");
  }
  if (!(min_threshold_dn >= 0.0)) fail("min_threshold_dn", min_threshold_dn, "must be >= 0");
  if (!(window_px > 0.0)) fail("window_px", window_px, "must be > 0");
  if (!(max_area_fraction > 0.0 && max_area_fraction <= 1.0)) {
    fail("max_area_fraction", max_area_fraction, "must be in (0, 1]");
  }
}

std::optional<ImpressionRegion> FindImpressionRegion(const cv::Mat& press, const cv::Mat& reference,
                                                     const ImpressionCentroidOptions& options,
                                                     const cv::Mat& mask) {
  options.Check();
  const cv::Mat magnitude =
      DifferenceMagnitude(press, reference, mask, options.blur_sigma_px, "FindImpressionRegion");
  double peak = 0.0;
  cv::Point peak_at;
  cv::minMaxLoc(magnitude, nullptr, &peak, nullptr, &peak_at);
  if (peak < options.min_peak_dn) return std::nullopt;
  const float threshold =
      static_cast<float>(std::max(options.threshold_fraction * peak, options.min_threshold_dn));
  const int usable = mask.empty() ? press.rows * press.cols : cv::countNonZero(mask);
  if (cv::countNonZero(magnitude > threshold) > options.max_area_fraction * usable) {
    return std::nullopt;
  }
  const int w = static_cast<int>(std::ceil(options.window_px));
  const cv::Rect window = cv::Rect(peak_at.x - w, peak_at.y - w, 2 * w + 1, 2 * w + 1) &
                          cv::Rect(0, 0, press.cols, press.rows);
  const double w2 = options.window_px * options.window_px;
  std::vector<cv::Point> points;
  double sw = 0.0, su = 0.0, sv = 0.0;
  int u0 = press.cols, v0 = press.rows, u1 = -1, v1 = -1;
  for (int v = window.y; v < window.y + window.height; ++v) {
    const float* row = magnitude.ptr<float>(v);
    for (int u = window.x; u < window.x + window.width; ++u) {
      if (row[u] <= threshold) continue;
      const double du = u - peak_at.x, dv = v - peak_at.y;
      if (du * du + dv * dv > w2) continue;
      points.emplace_back(u, v);
      const double weight = row[u] - threshold;
      sw += weight;
      su += weight * u;
      sv += weight * v;
      u0 = std::min(u0, u);
      v0 = std::min(v0, v);
      u1 = std::max(u1, u);
      v1 = std::max(v1, v);
    }
  }
  if (points.empty() || sw <= 0.0) return std::nullopt;
  ImpressionRegion out;
  out.peak_dn = peak;
  out.pixels = static_cast<int>(points.size());
  out.box = cv::Rect(u0, v0, u1 - u0 + 1, v1 - v0 + 1);
  out.weighted_centroid = Eigen::Vector2d(su / sw, sv / sw);
  std::vector<cv::Point> hull;
  cv::convexHull(points, hull);
  const cv::Moments m = cv::moments(hull);
  if (hull.size() >= 3 && m.m00 > 0.0) {
    out.centroid = Eigen::Vector2d(m.m10 / m.m00, m.m01 / m.m00);
    out.area_px = m.m00;
  } else {
    out.centroid = out.weighted_centroid;
    out.area_px = static_cast<double>(points.size());
  }
  return out;
}

}  // namespace gs360
