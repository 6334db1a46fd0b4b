#include "calib/impression_centroid.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numbers>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "capture/impression.h"

namespace gs360 {
namespace {

constexpr double kRayStepPx = 0.5;
constexpr int kJoinPx = 3;

// Bilinear sample of `magnitude` (CV_32F) at (x, y); false outside the image or next to a pixel
// that `mask` (optional) excludes.
bool Sample(const cv::Mat& magnitude, const cv::Mat& mask, double x, double y, double* value) {
  const int x0 = static_cast<int>(std::floor(x)), y0 = static_cast<int>(std::floor(y));
  if (x0 < 0 || y0 < 0 || x0 + 1 >= magnitude.cols || y0 + 1 >= magnitude.rows) return false;
  if (!mask.empty()) {
    for (int dy = 0; dy < 2; ++dy) {
      for (int dx = 0; dx < 2; ++dx) {
        if (mask.at<std::uint8_t>(y0 + dy, x0 + dx) == 0) return false;
      }
    }
  }
  const double fx = x - x0, fy = y - y0;
  const float* r0 = magnitude.ptr<float>(y0);
  const float* r1 = magnitude.ptr<float>(y0 + 1);
  *value = (1.0 - fy) * ((1.0 - fx) * r0[x0] + fx * r0[x0 + 1]) +
           fy * ((1.0 - fx) * r1[x0] + fx * r1[x0 + 1]);
  return true;
}

// Distance from `centre` along direction `angle` to the imprint's edge: past the ray's maximum,
// where the magnitude falls below threshold_fraction of that maximum (linear between samples).
// Negative when the ray has no edge of its own: too weak, or it leaves the image or the mask, or
// `reach`, first.
double EdgeAlongRay(const cv::Mat& magnitude, const cv::Mat& mask, const Eigen::Vector2d& centre,
                    double angle, double reach, double min_max,
                    const ImpressionCentroidOptions& options) {
  const Eigen::Vector2d step = kRayStepPx * Eigen::Vector2d(std::cos(angle), std::sin(angle));
  std::vector<double> profile;
  double value = 0.0, best = 0.0;
  std::size_t best_at = 0;
  for (int i = 0; i * kRayStepPx <= reach; ++i) {
    const Eigen::Vector2d p = centre + i * step;
    if (!Sample(magnitude, mask, p.x(), p.y(), &value)) break;
    profile.push_back(value);
    if (value > best) {
      best = value;
      best_at = profile.size() - 1;
    }
  }
  if (best < min_max) return -1.0;
  const double threshold = options.threshold_fraction * best;
  for (std::size_t i = best_at; i + 1 < profile.size(); ++i) {
    if (profile[i + 1] >= threshold) continue;
    const double f = (profile[i] - threshold) / (profile[i] - profile[i + 1]);
    return (static_cast<double>(i) + f) * kRayStepPx;
  }
  return -1.0;
}

// One round of the per-direction edge from `centre`: the area centroid of the edge polygon (rays
// without an edge take the radius interpolated between their neighbours'), or nullopt when too
// few rays have an edge.
std::optional<Eigen::Vector2d> DirectionalCentre(const cv::Mat& magnitude, const cv::Mat& mask,
                                                 double peak, const Eigen::Vector2d& centre,
                                                 double reach,
                                                 const ImpressionCentroidOptions& options) {
  const int n = options.directions;
  const double min_max = std::max(options.min_direction_fraction * peak, options.min_threshold_dn);
  std::vector<double> radius(static_cast<std::size_t>(n));
  std::vector<int> with_edge;
  for (int k = 0; k < n; ++k) {
    const double angle = 2.0 * std::numbers::pi * k / n;
    radius[static_cast<std::size_t>(k)] =
        EdgeAlongRay(magnitude, mask, centre, angle, reach, min_max, options);
    if (radius[static_cast<std::size_t>(k)] >= 0.0) with_edge.push_back(k);
  }
  if (with_edge.empty() ||
      static_cast<double>(with_edge.size()) < options.min_direction_share * n) {
    return std::nullopt;
  }
  std::vector<cv::Point2f> polygon;
  for (int k = 0; k < n; ++k) {
    double r = radius[static_cast<std::size_t>(k)];
    if (r < 0.0) {  // between the nearest rays with an edge on either side (circularly)
      int before = k, after = k;
      while (radius[static_cast<std::size_t>((before + n) % n)] < 0.0) --before;
      while (radius[static_cast<std::size_t>(after % n)] < 0.0) ++after;
      const double t = static_cast<double>(k - before) / (after - before);
      r = (1.0 - t) * radius[static_cast<std::size_t>((before + n) % n)] +
          t * radius[static_cast<std::size_t>(after % n)];
    }
    const double angle = 2.0 * std::numbers::pi * k / n;
    polygon.emplace_back(static_cast<float>(centre.x() + r * std::cos(angle)),
                         static_cast<float>(centre.y() + r * std::sin(angle)));
  }
  const cv::Moments m = cv::moments(polygon);
  if (!(m.m00 > 0.0)) return std::nullopt;
  return Eigen::Vector2d(m.m10 / m.m00, m.m01 / m.m00);
}

// The region in `window` (CV_8U of its size, non-zero = in): pixels above `threshold` within
// `radius` of the peak and connected to it across gaps of up to 2 * kJoinPx, so that a change
// elsewhere in the window (LED drift at the gel's edge, a fin) does not pull the centre while the
// weak side of a one-sided imprint stays joined to it.
cv::Mat RegionAroundPeak(const cv::Mat& magnitude, const cv::Rect& window, const cv::Point& peak_at,
                         float threshold, double radius) {
  cv::Mat above = magnitude(window) > threshold;
  cv::Mat disc = cv::Mat::zeros(window.size(), CV_8U);
  cv::circle(disc, peak_at - window.tl(), static_cast<int>(std::floor(radius)), cv::Scalar(255),
             cv::FILLED);
  above &= disc;
  cv::Mat joined, labels;
  cv::dilate(
      above, joined,
      cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * kJoinPx + 1, 2 * kJoinPx + 1)));
  cv::connectedComponents(joined, labels, 8, CV_32S);
  const int label = labels.at<std::int32_t>(peak_at - window.tl());
  return above & (labels == label);
}

// The frame's strongest change is kept when it lies within search_radius_px of the expected pixel,
// or when nothing near it reaches min_peak_dn (a nominal pose far off must not lose every press);
// otherwise the strongest change near the expected pixel is the impression. True when the peak
// kept lies near the expected pixel.
bool NearExpected(const cv::Mat& magnitude, const cv::Mat& mask, const Eigen::Vector2d& expected,
                  const ImpressionCentroidOptions& options, double& peak, cv::Point& peak_at) {
  const double du = peak_at.x - expected.x(), dv = peak_at.y - expected.y();
  if (du * du + dv * dv <= options.search_radius_px * options.search_radius_px) return true;
  // A pixel farther off the image than the radius has no neighbourhood in it (and would not fit
  // the int that cv::circle takes).
  const double r = options.search_radius_px;
  if (expected.x() < -r || expected.y() < -r || expected.x() > magnitude.cols + r ||
      expected.y() > magnitude.rows + r) {
    return false;
  }
  cv::Mat near = cv::Mat::zeros(magnitude.size(), CV_8U);
  cv::circle(near,
             cv::Point(static_cast<int>(std::lround(expected.x())),
                       static_cast<int>(std::lround(expected.y()))),
             static_cast<int>(std::ceil(options.search_radius_px)), cv::Scalar(255), cv::FILLED);
  if (!mask.empty()) near &= mask;
  if (cv::countNonZero(near) == 0) return false;
  double near_peak = 0.0;
  cv::Point near_at;
  cv::minMaxLoc(magnitude, nullptr, &near_peak, nullptr, &near_at, near);
  if (near_peak < options.min_peak_dn) return false;
  peak = near_peak;
  peak_at = near_at;
  return true;
}

}  // namespace

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
  if (!(search_radius_px > 0.0)) fail("search_radius_px", search_radius_px, "must be > 0");
  if (!(max_area_fraction > 0.0 && max_area_fraction <= 1.0)) {
    fail("max_area_fraction", max_area_fraction, "must be in (0, 1]");
  }
  if (directions != 0 && (directions < 8 || directions > 3600)) {
    fail("directions", directions, "must be 0 or in [8, 3600]");
  }
  if (direction_rounds < 1 || direction_rounds > 20) {
    fail("direction_rounds", direction_rounds, "must be in [1, 20]");
  }
  if (!(min_direction_fraction >= 0.0 && min_direction_fraction < 1.0)) {
    fail("min_direction_fraction", min_direction_fraction, "must be in [0, 1)");
  }
  if (!(min_direction_share > 0.0 && min_direction_share <= 1.0)) {
    fail("min_direction_share", min_direction_share, "must be in (0, 1]");
  }
}

std::optional<ImpressionRegion> FindImpressionRegion(
    const cv::Mat& press, const cv::Mat& reference, const ImpressionCentroidOptions& options,
    const cv::Mat& mask, const std::optional<Eigen::Vector2d>& expected_px) {
  options.Check();
  const cv::Mat magnitude =
      DifferenceMagnitude(press, reference, mask, options.blur_sigma_px, "FindImpressionRegion");
  return FindImpressionRegionInMagnitude(magnitude, options, mask, expected_px);
}

std::optional<ImpressionRegion> FindImpressionRegionInMagnitude(
    const cv::Mat& magnitude, const ImpressionCentroidOptions& options, const cv::Mat& mask,
    const std::optional<Eigen::Vector2d>& expected_px) {
  options.Check();
  if (magnitude.empty() || magnitude.type() != CV_32F) {
    throw std::invalid_argument("FindImpressionRegionInMagnitude: magnitude must be CV_32F");
  }
  if (!mask.empty() && (mask.type() != CV_8U || mask.size() != magnitude.size())) {
    throw std::invalid_argument(
        "FindImpressionRegionInMagnitude: mask must be CV_8U of the magnitude's size");
  }
  double peak = 0.0;
  cv::Point peak_at;
  cv::minMaxLoc(magnitude, nullptr, &peak, nullptr, &peak_at);
  const bool near = expected_px && expected_px->allFinite() &&
                    NearExpected(magnitude, mask, *expected_px, options, peak, peak_at);
  if (peak < options.min_peak_dn) return std::nullopt;
  const float threshold =
      static_cast<float>(std::max(options.threshold_fraction * peak, options.min_threshold_dn));
  const int usable = mask.empty() ? magnitude.rows * magnitude.cols : cv::countNonZero(mask);
  if (cv::countNonZero(magnitude > threshold) > options.max_area_fraction * usable) {
    return std::nullopt;
  }
  const int w = static_cast<int>(std::ceil(options.window_px));
  const cv::Rect window = cv::Rect(peak_at.x - w, peak_at.y - w, 2 * w + 1, 2 * w + 1) &
                          cv::Rect(0, 0, magnitude.cols, magnitude.rows);
  const cv::Mat region = RegionAroundPeak(magnitude, window, peak_at, threshold, options.window_px);
  std::vector<cv::Point> points;
  double sw = 0.0, su = 0.0, sv = 0.0;
  int u0 = magnitude.cols, v0 = magnitude.rows, u1 = -1, v1 = -1;
  for (int v = window.y; v < window.y + window.height; ++v) {
    const float* row = magnitude.ptr<float>(v);
    const std::uint8_t* in = region.ptr<std::uint8_t>(v - window.y);
    for (int u = window.x; u < window.x + window.width; ++u) {
      if (in[u - window.x] == 0) continue;
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
  out.near_expected = near;
  out.pixels = static_cast<int>(points.size());
  out.box = cv::Rect(u0, v0, u1 - u0 + 1, v1 - v0 + 1);
  out.weighted_centroid = Eigen::Vector2d(su / sw, sv / sw);
  std::vector<cv::Point> hull;
  cv::convexHull(points, hull);
  const cv::Moments m = cv::moments(hull);
  if (hull.size() >= 3 && m.m00 > 0.0) {
    out.hull_centroid = Eigen::Vector2d(m.m10 / m.m00, m.m01 / m.m00);
    out.area_px = m.m00;
  } else {
    out.hull_centroid = out.weighted_centroid;
    out.area_px = static_cast<double>(points.size());
  }
  out.centroid = out.hull_centroid;
  if (options.directions == 0) return out;
  // The per-direction edge (header comment), out to twice the region's radius.
  const double reach =
      std::min(options.window_px, 2.0 * std::sqrt(out.area_px / std::numbers::pi) + 4.0);
  Eigen::Vector2d centre = out.hull_centroid;
  for (int round = 0; round < options.direction_rounds; ++round) {
    const auto next = DirectionalCentre(magnitude, mask, peak, centre, reach, options);
    if (!next) return out;  // the hull centroid
    centre = *next;
  }
  out.centroid = centre;
  out.directional = true;
  return out;
}

bool NominalPoseHolds(int found, int near) {
  return 2 * near >= found;
}

}  // namespace gs360
