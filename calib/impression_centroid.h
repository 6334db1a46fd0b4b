#pragma once
// A less biased impression centre for pose estimation. capture/impression.h FindImpression
// weights the blob by the colour difference, which follows the LED directions: a spherical
// imprint lights up on one side and darkens on the other (and its centre, whose normal is
// unchanged, barely differs from the reference), so the weighted centroid is pulled toward the
// lit side by several pixels. Here the imprint's REGION is estimated instead: the pixels where the
// blurred difference magnitude exceeds a fraction of its peak, near the peak, closed by their
// convex hull (the imprint of a ball is a convex blob in the image of a smooth surface); the
// centre is the area centroid of that hull. It estimates the centroid of the deformed region,
// which calib/render.h's contact_centroid models (the elastic rim widens the region almost
// symmetrically).
//
// Pixels: (u right, v down), as geometry/fisheye.h.

#include <Eigen/Core>
#include <optional>

#include <opencv2/core/mat.hpp>

namespace gs360 {

struct ImpressionCentroidOptions {
  double blur_sigma_px = 1.5;       // Gaussian blur of the difference magnitude (>= 0)
  double min_peak_dn = 6.0;         // weaker peaks: no impression (> 0)
  double threshold_fraction = 0.2;  // region = pixels above this fraction of the peak, (0, 1)
  double min_threshold_dn = 3.0;    // ... and above this many DN (noise floor, >= 0)
  double window_px = 60.0;          // only pixels within this distance of the peak (> 0)
  // More than this fraction of the usable pixels above the threshold, anywhere: no press but a
  // frame unlike the reference everywhere (saturated, black, corrupt): no impression ((0, 1]).
  double max_area_fraction = 0.25;
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("blur_sigma_px", self.blur_sigma_px);
    visit("min_peak_dn", self.min_peak_dn);
    visit("threshold_fraction", self.threshold_fraction);
    visit("min_threshold_dn", self.min_threshold_dn);
    visit("window_px", self.window_px);
    visit("max_area_fraction", self.max_area_fraction);
  }
  void Check() const;  // throws std::invalid_argument naming the field and value
};

struct ImpressionRegion {
  Eigen::Vector2d centroid = Eigen::Vector2d::Zero();           // hull area centroid (px)
  Eigen::Vector2d weighted_centroid = Eigen::Vector2d::Zero();  // difference-weighted (px)
  double peak_dn = 0.0;
  double area_px = 0.0;  // hull area
  int pixels = 0;        // pixels above the threshold in the window
  cv::Rect box;          // bounding box of those pixels
};

// `press`, `reference`: CV_8UC3 of one size (std::invalid_argument otherwise); optional `mask`
// (CV_8U, non-zero = usable). nullopt when no peak reaches min_peak_dn, or when more than
// max_area_fraction of the usable pixels exceed the threshold.
std::optional<ImpressionRegion> FindImpressionRegion(const cv::Mat& press, const cv::Mat& reference,
                                                     const ImpressionCentroidOptions& options = {},
                                                     const cv::Mat& mask = cv::Mat());

}  // namespace gs360
