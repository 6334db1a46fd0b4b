#include "capture/impression.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

#include <opencv2/imgproc.hpp>

namespace gs360 {

void ImpressionOptions::Check() const {
  if (!(blur_sigma_px >= 0.0)) {
    throw std::invalid_argument("ImpressionOptions.blur_sigma_px must be >= 0, got " +
                                std::to_string(blur_sigma_px));
  }
  if (!(min_peak_dn > 0.0)) {
    throw std::invalid_argument("ImpressionOptions.min_peak_dn must be > 0, got " +
                                std::to_string(min_peak_dn));
  }
  if (!(max_area_fraction > 0.0 && max_area_fraction <= 1.0)) {
    throw std::invalid_argument("ImpressionOptions.max_area_fraction must be in (0, 1], got " +
                                std::to_string(max_area_fraction));
  }
  if (!(threshold_fraction > 0.0 && threshold_fraction < 1.0)) {
    throw std::invalid_argument("ImpressionOptions.threshold_fraction must be in (0, 1), got " +
                                std::to_string(threshold_fraction));
  }
}

cv::Mat DifferenceMagnitude(const cv::Mat& press, const cv::Mat& reference, const cv::Mat& mask,
                            double blur_sigma_px, const char* caller) {
  if (press.type() != CV_8UC3 || reference.type() != CV_8UC3 || press.size() != reference.size()) {
    throw std::invalid_argument(std::string(caller) +
                                ": press and reference must be CV_8UC3 of one size");
  }
  if (!mask.empty() && (mask.type() != CV_8U || mask.size() != press.size())) {
    throw std::invalid_argument(std::string(caller) + ": mask must be CV_8U of the image size");
  }
  // One pass from the 8-bit pixels to the sum of squared channel differences (exact in float:
  // at most 3 * 255^2 < 2^24), then OpenCV's vectorised square root: no 3-channel float
  // temporaries, which made this several times slower (each a fresh 3.7 MB allocation).
  cv::Mat magnitude(press.size(), CV_32F);
  for (int y = 0; y < press.rows; ++y) {
    const std::uint8_t* a = press.ptr<std::uint8_t>(y);
    const std::uint8_t* b = reference.ptr<std::uint8_t>(y);
    const std::uint8_t* m = mask.empty() ? nullptr : mask.ptr<std::uint8_t>(y);
    float* out = magnitude.ptr<float>(y);
    for (int x = 0; x < press.cols; ++x) {
      const int d0 = a[3 * x] - b[3 * x];
      const int d1 = a[3 * x + 1] - b[3 * x + 1];
      const int d2 = a[3 * x + 2] - b[3 * x + 2];
      const int sum = d0 * d0 + d1 * d1 + d2 * d2;
      out[x] = m && m[x] == 0 ? 0.0f : static_cast<float>(sum);
    }
  }
  cv::sqrt(magnitude, magnitude);
  if (blur_sigma_px > 0.0) cv::GaussianBlur(magnitude, magnitude, cv::Size(), blur_sigma_px);
  return magnitude;
}

double ImpressionContrast(const cv::Mat& press, const cv::Mat& reference,
                          const Eigen::Vector2d& expected_px, double radius_px,
                          double blur_sigma_px, const cv::Mat& mask) {
  const cv::Mat magnitude =
      DifferenceMagnitude(press, reference, mask, blur_sigma_px, "ImpressionContrast");
  const int r = static_cast<int>(std::ceil(radius_px));
  cv::Rect window(static_cast<int>(std::lround(expected_px.x())) - r,
                  static_cast<int>(std::lround(expected_px.y())) - r, 2 * r + 1, 2 * r + 1);
  window &= cv::Rect(0, 0, magnitude.cols, magnitude.rows);
  if (window.empty()) return 0.0;
  double local = 0.0;
  cv::minMaxLoc(magnitude(window), nullptr, &local);
  // The frame's level of change: every other pixel is enough for a percentile.
  std::vector<float> values;
  values.reserve(magnitude.total() / 4 + 1);
  for (int y = 0; y < magnitude.rows; y += 2) {
    const float* row = magnitude.ptr<float>(y);
    for (int x = 0; x < magnitude.cols; x += 2) {
      if (mask.empty() || mask.at<std::uint8_t>(y, x) != 0) values.push_back(row[x]);
    }
  }
  if (values.empty()) return 0.0;
  const auto p99 = values.begin() + static_cast<std::ptrdiff_t>(values.size() * 99 / 100);
  std::nth_element(values.begin(), p99, values.end());
  return local / std::max(1e-3, static_cast<double>(*p99));
}

std::optional<Impression> FindImpression(const cv::Mat& press, const cv::Mat& reference,
                                         const ImpressionOptions& options, const cv::Mat& mask) {
  options.Check();
  const cv::Mat magnitude =
      DifferenceMagnitude(press, reference, mask, options.blur_sigma_px, "FindImpression");
  double peak = 0.0;
  cv::Point peak_at;
  cv::minMaxLoc(magnitude, nullptr, &peak, nullptr, &peak_at);
  if (peak < options.min_peak_dn) return std::nullopt;

  // The blob is the connected region above the threshold that contains the peak: a second,
  // unrelated change elsewhere (LED drift, a speck) does not pull the centroid.
  const float threshold = static_cast<float>(options.threshold_fraction * peak);
  cv::Mat above = magnitude > threshold;
  cv::Mat labels;
  cv::connectedComponents(above, labels, 8, CV_32S);
  const int label = labels.at<int>(peak_at);
  double sw = 0.0, su = 0.0, sv = 0.0;
  int count = 0;
  int u0 = press.cols, v0 = press.rows, u1 = -1, v1 = -1;
  for (int v = 0; v < labels.rows; ++v) {
    const int* lrow = labels.ptr<int>(v);
    const float* mrow = magnitude.ptr<float>(v);
    for (int u = 0; u < labels.cols; ++u) {
      if (lrow[u] != label) continue;
      const double w = mrow[u] - threshold;
      sw += w;
      su += w * u;
      sv += w * v;
      ++count;
      u0 = std::min(u0, u);
      v0 = std::min(v0, v);
      u1 = std::max(u1, u);
      v1 = std::max(v1, v);
    }
  }
  if (sw <= 0.0) return std::nullopt;
  const int usable = mask.empty() ? press.rows * press.cols : cv::countNonZero(mask);
  if (count > options.max_area_fraction * usable) return std::nullopt;
  Impression out;
  out.centroid = Eigen::Vector2d(su / sw, sv / sw);
  out.peak_dn = peak;
  out.pixels = count;
  out.box = cv::Rect(u0, v0, u1 - u0 + 1, v1 - v0 + 1);
  return out;
}

ImpressionShift MeasureImpressionShift(const cv::Mat& stored_press, const cv::Mat& stored_reference,
                                       const Impression& stored, const cv::Mat& press,
                                       const cv::Mat& reference, int search_px) {
  constexpr int kPad = 6;
  const double blur = ImpressionOptions{}.blur_sigma_px;
  const char* caller = "MeasureImpressionShift";
  const cv::Mat then = DifferenceMagnitude(stored_press, stored_reference, cv::Mat(), blur, caller);
  const cv::Mat now = DifferenceMagnitude(press, reference, cv::Mat(), blur, caller);
  if (then.size() != now.size()) {
    throw std::invalid_argument(std::string(caller) + ": the two captures differ in size");
  }
  const cv::Rect bounds(0, 0, now.cols, now.rows);
  const cv::Rect templ = cv::Rect(stored.box.x - kPad, stored.box.y - kPad,
                                  stored.box.width + 2 * kPad, stored.box.height + 2 * kPad) &
                         bounds;
  const cv::Rect search = cv::Rect(templ.x - search_px, templ.y - search_px,
                                   templ.width + 2 * search_px, templ.height + 2 * search_px) &
                          bounds;
  ImpressionShift out;
  if (templ.width < 3 || templ.height < 3) return out;
  cv::Mat score;
  cv::matchTemplate(now(search), then(templ), score, cv::TM_CCOEFF_NORMED);
  double best = 0.0;
  cv::Point at;
  cv::minMaxLoc(score, nullptr, &best, nullptr, &at);
  // The vertex of the parabola through the peak and its two neighbours along one axis.
  const auto vertex = [](double left, double centre, double right) {
    const double curvature = left - 2.0 * centre + right;
    return curvature < 0.0 ? 0.5 * (left - right) / curvature : 0.0;
  };
  double du = 0.0, dv = 0.0;
  if (at.x > 0 && at.x < score.cols - 1) {
    du = vertex(score.at<float>(at.y, at.x - 1), best, score.at<float>(at.y, at.x + 1));
  }
  if (at.y > 0 && at.y < score.rows - 1) {
    dv = vertex(score.at<float>(at.y - 1, at.x), best, score.at<float>(at.y + 1, at.x));
  }
  out.px = Eigen::Vector2d(search.x + at.x + du - templ.x, search.y + at.y + dv - templ.y);
  out.score = best;
  out.at_search_limit = at.x == 0 || at.y == 0 || at.x == score.cols - 1 || at.y == score.rows - 1;
  return out;
}

double ImpressionDistance(const ImpressionShift& shift, const Impression& stored,
                          const Impression& now) {
  const double measured = shift.px.norm();
  if (shift.score >= kMinImpressionMatch && !shift.at_search_limit) return measured;
  return std::max(measured, (stored.centroid - now.centroid).norm());
}

std::optional<Impression> FindClearImpression(const cv::Mat& press, const cv::Mat& reference,
                                              double min_peak_dn) {
  std::optional<Impression> found = FindImpression(press, reference);
  if (!found || found->peak_dn < min_peak_dn) return std::nullopt;
  if (found->box.width > press.cols / 4 || found->box.height > press.rows / 4) return std::nullopt;
  return found;
}

}  // namespace gs360
