#pragma once
// Shared helpers of the tactile camera tests (tests/sim/camera_*_test.cc).

#include <Eigen/Core>
#include <cmath>
#include <memory>
#include <numbers>
#include <optional>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "sim/ground_truth.h"
#include "sim/rig_model.h"
#include "sim/tactile_camera.h"

namespace gs360::camera_test {

inline double Deg(double d) {
  return d * std::numbers::pi / 180.0;
}

// Ball centre pressing `depth` mm into the rig's surface of revolution at profile parameter t and
// azimuth phi_deg (sensor frame).
inline Eigen::Vector3d BallAt(const SimRig& rig, double t, double phi_deg, double depth) {
  return rig.profile().SurfacePoint(t, Deg(phi_deg)) +
         (rig.ball_radius() - depth) * rig.profile().SurfaceNormal(t, Deg(phi_deg));
}

// Sum over channels of |a - b| (CV_32S).
inline cv::Mat AbsDiffSum(const cv::Mat& a, const cv::Mat& b) {
  cv::Mat d;
  cv::absdiff(a, b, d);
  std::vector<cv::Mat> ch;
  cv::split(d, ch);
  cv::Mat sum;
  cv::Mat c0, c1, c2;
  ch[0].convertTo(c0, CV_32S);
  ch[1].convertTo(c1, CV_32S);
  ch[2].convertTo(c2, CV_32S);
  sum = c0 + c1 + c2;
  return sum;
}

struct Blob {
  double u = 0.0, v = 0.0;  // centroid (px)
  int pixels = 0;
};

// Largest 8-connected component of AbsDiffSum(press, reference) > threshold, if any.
inline std::optional<Blob> DifferenceBlob(const cv::Mat& press, const cv::Mat& reference,
                                          int threshold) {
  const cv::Mat mask = AbsDiffSum(press, reference) > threshold;
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(mask, labels, stats, centroids, 8);
  int best = -1;
  for (int k = 1; k < n; ++k) {
    if (best < 0 || stats.at<int>(k, cv::CC_STAT_AREA) > stats.at<int>(best, cv::CC_STAT_AREA))
      best = k;
  }
  if (best < 0) return std::nullopt;
  Blob blob;
  blob.u = centroids.at<double>(best, 0);
  blob.v = centroids.at<double>(best, 1);
  blob.pixels = stats.at<int>(best, cv::CC_STAT_AREA);
  return blob;
}

// Pearson correlation of two equally long samples (0 if either is constant).
inline double Correlation(const std::vector<double>& a, const std::vector<double>& b) {
  const std::size_t n = a.size();
  if (n < 2 || b.size() != n) return 0.0;
  double ma = 0.0, mb = 0.0;
  for (std::size_t i = 0; i < n; ++i) {
    ma += a[i] / n;
    mb += b[i] / n;
  }
  double sab = 0.0, saa = 0.0, sbb = 0.0;
  for (std::size_t i = 0; i < n; ++i) {
    sab += (a[i] - ma) * (b[i] - mb);
    saa += (a[i] - ma) * (a[i] - ma);
    sbb += (b[i] - mb) * (b[i] - mb);
  }
  if (saa <= 0.0 || sbb <= 0.0) return 0.0;
  return sab / std::sqrt(saa * sbb);
}

}  // namespace gs360::camera_test
