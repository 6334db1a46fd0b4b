#include "recon/features.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include <opencv2/imgproc.hpp>

#include "base/field_error.h"

namespace gs360 {
namespace {

[[noreturn]] void Bad(const std::string& field, double value, const std::string& rule) {
  ThrowFieldError(field, value, "must be " + rule);
}

// One context scale's bound, shared by DifferenceOptions::Check and ContextFeatures.
void CheckContextSigma(const std::string& field, double sigma_px) {
  if (!(sigma_px > 0.0 && sigma_px <= 20.0)) Bad(field, sigma_px, "in (0, 20]");
}

}  // namespace

void DifferenceOptions::Check() const {
  if (!(floor_dn > 0.0 && std::isfinite(floor_dn)))
    Bad("DifferenceOptions.floor_dn", floor_dn, "> 0");
  if (!(gain_min_reference_dn >= 0.0 && gain_min_reference_dn < 255.0)) {
    Bad("DifferenceOptions.gain_min_reference_dn", gain_min_reference_dn, "in [0, 255)");
  }
  if (gain_stride < 1 || gain_stride > 64) {
    Bad("DifferenceOptions.gain_stride", gain_stride, "in [1, 64]");
  }
  if (!(smooth_sigma_px >= 0.0 && smooth_sigma_px <= 10.0)) {
    Bad("DifferenceOptions.smooth_sigma_px", smooth_sigma_px, "in [0, 10]");
  }
  if (context_sigmas_px.size() > 4) {
    Bad("DifferenceOptions.context_sigmas_px's size", static_cast<double>(context_sigmas_px.size()),
        "at most 4");
  }
  for (double sigma : context_sigmas_px)
    CheckContextSigma("DifferenceOptions.context_sigmas_px", sigma);
}

int FeatureCount(const DifferenceOptions& options) {
  return kFeatureCount + kContextFeatureCount * static_cast<int>(options.context_sigmas_px.size());
}

namespace {

// One scale of ContextFeatures, into channels [offset, offset + 6) of `out`.
void ContextFeaturesAtScale(const cv::Mat& diff, const cv::Mat& valid, const cv::Rect& roi,
                            double sigma_px, int offset, cv::Mat* out_mat) {
  const cv::Rect image(0, 0, diff.cols, diff.rows);
  // The weights of a margin around the roi, so the roi's border sees the same filter as its
  // inside.
  const int margin = static_cast<int>(std::ceil(3.0 * sigma_px)) + 1;
  const cv::Rect big =
      cv::Rect(roi.x - margin, roi.y - margin, roi.width + 2 * margin, roi.height + 2 * margin) &
      image;
  cv::Mat weight;
  if (valid.empty()) {
    weight = cv::Mat(big.size(), CV_32F, cv::Scalar::all(1.0));
  } else {
    valid(big).convertTo(weight, CV_32F, 1.0 / 255.0);
    cv::threshold(weight, weight, 0.0, 1.0, cv::THRESH_BINARY);
  }
  // Smoothed only where read: the roi and one pixel around it (the central differences). A
  // filter on a view reads its parent's pixels beyond it (no BORDER_ISOLATED), so these are the
  // values a blur of all of `big` would give there, at a fraction of its cost.
  const cv::Rect need = cv::Rect(roi.x - 1, roi.y - 1, roi.width + 2, roi.height + 2) & image;
  cv::Mat smooth, wsum;
  // diff is already 0 outside `valid`, so blurring it is the numerator of the normalised
  // convolution.
  cv::GaussianBlur(diff(need), smooth, cv::Size(), sigma_px, sigma_px, cv::BORDER_REPLICATE);
  cv::GaussianBlur(weight(need - big.tl()), wsum, cv::Size(), sigma_px, sigma_px,
                   cv::BORDER_REPLICATE);
  for (int v = 0; v < smooth.rows; ++v) {
    const float* ws = wsum.ptr<float>(v);
    auto* s = smooth.ptr<cv::Vec3f>(v);
    for (int u = 0; u < smooth.cols; ++u) s[u] = ws[u] > 1e-3f ? s[u] / ws[u] : cv::Vec3f(0, 0, 0);
  }
  const int ox = roi.x - need.x, oy = roi.y - need.y;
  const int channels = out_mat->channels();
  for (int y = 0; y < roi.height; ++y) {
    const int sy = y + oy;
    const int y0 = std::max(sy - 1, 0), y1 = std::min(sy + 1, smooth.rows - 1);
    float* o = out_mat->ptr<float>(y);
    for (int x = 0; x < roi.width; ++x) {
      const int sx = x + ox;
      const int x0 = std::max(sx - 1, 0), x1 = std::min(sx + 1, smooth.cols - 1);
      const cv::Vec3f du = (smooth.at<cv::Vec3f>(sy, x1) - smooth.at<cv::Vec3f>(sy, x0)) /
                           static_cast<float>(std::max(x1 - x0, 1));
      const cv::Vec3f dv = (smooth.at<cv::Vec3f>(y1, sx) - smooth.at<cv::Vec3f>(y0, sx)) /
                           static_cast<float>(std::max(y1 - y0, 1));
      float* px = o + static_cast<std::ptrdiff_t>(x) * channels + offset;
      for (int c = 0; c < 3; ++c) {  // R, G, B: stored channels 2, 1, 0
        px[2 * c] = du[2 - c];
        px[2 * c + 1] = dv[2 - c];
      }
    }
  }
}

}  // namespace

cv::Mat ContextFeatures(const cv::Mat& diff, const cv::Mat& valid, const cv::Rect& roi,
                        const std::vector<double>& sigmas_px) {
  if (diff.type() != CV_32FC3)
    throw std::invalid_argument("ContextFeatures: diff must be CV_32FC3");
  if (!valid.empty() && (valid.type() != CV_8U || valid.size() != diff.size())) {
    throw std::invalid_argument("ContextFeatures: valid mask must be CV_8U of the image size");
  }
  const cv::Rect image(0, 0, diff.cols, diff.rows);
  if ((roi & image) != roi || roi.empty()) {
    throw std::invalid_argument("ContextFeatures: roi " + std::to_string(roi.x) + "," +
                                std::to_string(roi.y) + " " + std::to_string(roi.width) + "x" +
                                std::to_string(roi.height) + " is not inside the image");
  }
  for (double sigma : sigmas_px) CheckContextSigma("ContextFeatures sigma_px", sigma);
  if (sigmas_px.empty()) return cv::Mat();
  const int channels = kContextFeatureCount * static_cast<int>(sigmas_px.size());
  cv::Mat out(roi.size(), CV_32FC(channels), cv::Scalar::all(0));
  for (std::size_t k = 0; k < sigmas_px.size(); ++k) {
    ContextFeaturesAtScale(diff, valid, roi, sigmas_px[k],
                           kContextFeatureCount * static_cast<int>(k), &out);
  }
  return out;
}

void PixelFeatures(const cv::Mat& diff, const cv::Mat& context, cv::Point roi_origin, int u, int v,
                   float* out) {
  const cv::Vec3f f = diff.at<cv::Vec3f>(v, u);
  out[0] = static_cast<float>(u);
  out[1] = static_cast<float>(v);
  out[2] = f[2];  // R
  out[3] = f[1];  // G
  out[4] = f[0];  // B
  if (context.empty()) return;
  const float* c = context.ptr<float>(v - roi_origin.y) +
                   static_cast<std::ptrdiff_t>(u - roi_origin.x) * context.channels();
  for (int k = 0; k < context.channels(); ++k) out[kFeatureCount + k] = c[k];
}

void ContactDetectionOptions::Check() const {
  if (!(blur_sigma_px >= 0.0 && blur_sigma_px <= 20.0)) {
    Bad("ContactDetectionOptions.blur_sigma_px", blur_sigma_px, "in [0, 20]");
  }
  if (!(threshold > 0.0 && std::isfinite(threshold))) {
    Bad("ContactDetectionOptions.threshold", threshold, "> 0");
  }
  if (min_area_px < 1) Bad("ContactDetectionOptions.min_area_px", min_area_px, ">= 1");
  if (!(grow_fraction >= 0.0 && grow_fraction <= 5.0)) {
    Bad("ContactDetectionOptions.grow_fraction", grow_fraction, "in [0, 5]");
  }
  if (grow_px < 0) Bad("ContactDetectionOptions.grow_px", grow_px, ">= 0");
  if (max_regions < 1) Bad("ContactDetectionOptions.max_regions", max_regions, ">= 1");
}

cv::Vec3d EstimateGain(const cv::Mat& frame, const cv::Mat& reference, const cv::Mat& valid,
                       const DifferenceOptions& options) {
  if (frame.type() != CV_8UC3 || reference.type() != CV_8UC3 || frame.size() != reference.size() ||
      (!valid.empty() && valid.size() != frame.size())) {
    throw std::invalid_argument("EstimateGain: frame, reference (CV_8UC3) and mask of one size");
  }
  cv::Vec3d gain(1.0, 1.0, 1.0);
  if (!options.compensate_gain) return gain;
  std::vector<float> ratios[3];
  for (int v = 0; v < frame.rows; v += options.gain_stride) {
    const auto* f = frame.ptr<cv::Vec3b>(v);
    const auto* r = reference.ptr<cv::Vec3b>(v);
    const auto* m = valid.empty() ? nullptr : valid.ptr<std::uint8_t>(v);
    for (int u = 0; u < frame.cols; u += options.gain_stride) {
      if (m != nullptr && m[u] == 0) continue;
      for (int c = 0; c < 3; ++c) {
        if (r[u][c] >= options.gain_min_reference_dn) {
          ratios[c].push_back(static_cast<float>(f[u][c]) / static_cast<float>(r[u][c]));
        }
      }
    }
  }
  for (int c = 0; c < 3; ++c) {
    // Too few bright pixels in a channel (e.g. a sensor lit by one colour): keep g = 1.
    if (ratios[c].size() < 64) continue;
    auto mid = ratios[c].begin() + static_cast<std::ptrdiff_t>(ratios[c].size() / 2);
    std::nth_element(ratios[c].begin(), mid, ratios[c].end());
    gain[c] = *mid;
  }
  return gain;
}

cv::Mat NormalizedDifference(const cv::Mat& frame, const cv::Mat& reference, const cv::Mat& valid,
                             const DifferenceOptions& options, cv::Vec3d* gain_out,
                             const cv::Vec3d* gain_in) {
  options.Check();
  if (frame.type() != CV_8UC3 || reference.type() != CV_8UC3 || frame.size() != reference.size()) {
    throw std::invalid_argument(
        "NormalizedDifference: frame and reference must be CV_8UC3 images of one size (got " +
        std::to_string(frame.cols) + "x" + std::to_string(frame.rows) + " type " +
        std::to_string(frame.type()) + " and " + std::to_string(reference.cols) + "x" +
        std::to_string(reference.rows) + " type " + std::to_string(reference.type()) + ")");
  }
  if (!valid.empty() && (valid.type() != CV_8U || valid.size() != frame.size())) {
    throw std::invalid_argument("NormalizedDifference: valid mask must be CV_8U of the image size");
  }
  const cv::Vec3d gain =
      gain_in != nullptr ? *gain_in : EstimateGain(frame, reference, valid, options);
  if (gain_out != nullptr) *gain_out = gain;
  cv::Mat out(frame.size(), CV_32FC3, cv::Scalar::all(0));
  const float floor = static_cast<float>(options.floor_dn);
  const float g[3] = {static_cast<float>(gain[0]), static_cast<float>(gain[1]),
                      static_cast<float>(gain[2])};
  for (int v = 0; v < frame.rows; ++v) {
    const auto* f = frame.ptr<cv::Vec3b>(v);
    const auto* r = reference.ptr<cv::Vec3b>(v);
    const auto* m = valid.empty() ? nullptr : valid.ptr<std::uint8_t>(v);
    auto* o = out.ptr<cv::Vec3f>(v);
    for (int u = 0; u < frame.cols; ++u) {
      if (m != nullptr && m[u] == 0) continue;
      for (int c = 0; c < 3; ++c) {
        const float ref = g[c] * static_cast<float>(r[u][c]);
        o[u][c] = (static_cast<float>(f[u][c]) - ref) / (ref + floor);
      }
    }
  }
  if (options.smooth_sigma_px > 0.0) {
    cv::Mat weight;
    if (valid.empty()) {
      weight = cv::Mat(out.size(), CV_32F, cv::Scalar::all(1.0));
    } else {
      valid.convertTo(weight, CV_32F, 1.0 / 255.0);
      cv::threshold(weight, weight, 0.0, 1.0, cv::THRESH_BINARY);
    }
    cv::Mat blurred, wsum;
    cv::GaussianBlur(out, blurred, cv::Size(), options.smooth_sigma_px);
    cv::GaussianBlur(weight, wsum, cv::Size(), options.smooth_sigma_px);
    for (int v = 0; v < out.rows; ++v) {
      const float* w = weight.ptr<float>(v);
      const float* ws = wsum.ptr<float>(v);
      const auto* b = blurred.ptr<cv::Vec3f>(v);
      auto* o = out.ptr<cv::Vec3f>(v);
      for (int u = 0; u < out.cols; ++u) {
        o[u] = (w[u] > 0.0f && ws[u] > 1e-6f) ? b[u] / ws[u] : cv::Vec3f(0, 0, 0);
      }
    }
  }
  return out;
}

std::vector<ContactRegion> DetectContactRegions(const cv::Mat& normalized_difference,
                                                const ContactDetectionOptions& options) {
  options.Check();
  if (normalized_difference.type() != CV_32FC3) {
    throw std::invalid_argument("DetectContactRegions: expected a CV_32FC3 normalised difference");
  }
  cv::Mat sq;
  cv::multiply(normalized_difference, normalized_difference, sq);
  cv::Mat magnitude(normalized_difference.size(), CV_32F);
  for (int v = 0; v < sq.rows; ++v) {
    const auto* s = sq.ptr<cv::Vec3f>(v);
    auto* m = magnitude.ptr<float>(v);
    for (int u = 0; u < sq.cols; ++u) m[u] = std::sqrt(s[u][0] + s[u][1] + s[u][2]);
  }
  if (options.blur_sigma_px > 0.0) {
    cv::GaussianBlur(magnitude, magnitude, cv::Size(), options.blur_sigma_px);
  }
  cv::Mat above = magnitude > static_cast<float>(options.threshold);
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(above, labels, stats, centroids, 8, CV_32S);
  std::vector<ContactRegion> regions;
  for (int label = 1; label < n; ++label) {
    const int area = stats.at<int>(label, cv::CC_STAT_AREA);
    if (area < options.min_area_px) continue;
    ContactRegion region;
    region.area_px = area;
    region.blob =
        cv::Rect(stats.at<int>(label, cv::CC_STAT_LEFT), stats.at<int>(label, cv::CC_STAT_TOP),
                 stats.at<int>(label, cv::CC_STAT_WIDTH), stats.at<int>(label, cv::CC_STAT_HEIGHT));
    double peak = 0.0;
    cv::minMaxLoc(magnitude(region.blob), nullptr, &peak, nullptr, nullptr,
                  labels(region.blob) == label);
    region.peak = peak;
    const int gx =
        options.grow_px + static_cast<int>(std::ceil(options.grow_fraction * region.blob.width));
    const int gy =
        options.grow_px + static_cast<int>(std::ceil(options.grow_fraction * region.blob.height));
    cv::Rect grown(region.blob.x - gx, region.blob.y - gy, region.blob.width + 2 * gx,
                   region.blob.height + 2 * gy);
    region.roi = grown & cv::Rect(0, 0, magnitude.cols, magnitude.rows);
    regions.push_back(region);
  }
  std::sort(regions.begin(), regions.end(),
            [](const ContactRegion& a, const ContactRegion& b) { return a.area_px > b.area_px; });
  if (static_cast<int>(regions.size()) > options.max_regions) regions.resize(options.max_regions);
  return regions;
}

}  // namespace gs360
