#pragma once
// Fisheye camera model: Kannala-Brandt in the cv::fisheye convention.
//
// Camera frame: OpenCV (x right, y down, z forward), mm or any length unit (only directions
// matter). For a point X = (x, y, z) with theta = atan2(sqrt(x^2 + y^2), z) (angle off the optical
// axis, rad):
//   theta_d = theta * (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
//   (xd, yd) = (theta_d / r) * (x, y),   r = sqrt(x^2 + y^2)   ((0, 0) on the axis)
//   u = fx * (xd + skew * yd) + cx,      v = fy * yd + cy
// which is exactly cv::fisheye::projectPoints with K = [fx, fx*skew, cx; 0, fy, cy; 0, 0, 1]
// (skew is OpenCV's `alpha`) and D = (k1, k2, k3, k4). Unlike OpenCV, theta is computed with
// atan2, so points at or behind 90 degrees are classified (invalid) rather than mirrored.
//
// Pixels: (0, 0) is the centre of the top-left pixel; the image covers
// [-0.5, width - 0.5] x [-0.5, height - 0.5]. Images are raw fisheye pixels, never resampled.
//
// Validity ("invalid" = std::nullopt): theta > MaxValidTheta(), where MaxValidTheta() is the
// smallest of max_theta, pi/2 and the first theta where theta_d(theta) stops increasing; or the
// pixel outside the image. Inside that image circle the model is a bijection between pixels and
// rays. OpenCV headers stay out of this file: see geometry/fisheye_cv.h for K/D conversions.

#include <Eigen/Core>
#include <array>
#include <optional>

namespace gs360 {

struct FisheyeIntrinsics {
  int width = 640;            // px
  int height = 480;           // px
  double fx = 0.0, fy = 0.0;  // px per rad of theta_d
  double cx = 0.0, cy = 0.0;  // px, principal point
  double skew = 0.0;          // OpenCV alpha
  std::array<double, 4> k{};  // k1..k4
  // Field limit (rad), half the lens's field of view; at most pi/2.
  double max_theta = 1.5707963267948966;

  // Throws std::invalid_argument naming the field and value: width/height <= 0, fx/fy <= 0 or
  // non-finite, non-finite cx/cy/skew/k, max_theta not in (0, pi/2].
  void Check() const;

  // The nominal 160-degree lens for a 640x480 sensor: equidistant (k = 0), max_theta = 80 deg,
  // fx = fy = 236 / (80 deg in rad) = 169.0 px/rad so that the image circle (radius 236 px) fits
  // inside the image height with a 4 px margin, principal point at the image centre
  // (319.5, 239.5), no skew.
  static FisheyeIntrinsics Default160(int width = 640, int height = 480);
};

class FisheyeCamera {
 public:
  // Throws std::invalid_argument (via Check()).
  explicit FisheyeCamera(const FisheyeIntrinsics& intrinsics);
  FisheyeCamera() : FisheyeCamera(FisheyeIntrinsics::Default160()) {}

  const FisheyeIntrinsics& intrinsics() const { return intrinsics_; }
  int width() const { return intrinsics_.width; }
  int height() const { return intrinsics_.height; }

  // Unit ray (camera frame) of pixel uv, or nullopt if uv is outside the image or its theta is
  // beyond MaxValidTheta(). Round trip CamToPixel(PixelToRay(uv)) == uv to ~1e-9 px.
  std::optional<Eigen::Vector3d> PixelToRay(const Eigen::Vector2d& uv) const;
  // Pixel of a camera-frame point, or nullopt if it is at the origin, beyond MaxValidTheta()
  // (behind the camera included), or projects outside the image.
  std::optional<Eigen::Vector2d> CamToPixel(const Eigen::Vector3d& x_cam) const;
  // The formula above with no validity check (theta from atan2; the origin maps to (cx, cy)).
  // For optimisers that must stay differentiable across the border.
  Eigen::Vector2d ProjectUnchecked(const Eigen::Vector3d& x_cam) const;

  // theta_d(theta) and its inverse on [0, MaxValidTheta()] (nullopt beyond it or for < 0).
  double ThetaToThetaD(double theta) const;
  std::optional<double> ThetaDToTheta(double theta_d) const;
  double MaxValidTheta() const { return max_valid_theta_; }
  // theta (rad) of a pixel from the model alone (no image-bounds check); nullopt beyond the
  // valid field.
  std::optional<double> PixelTheta(const Eigen::Vector2d& uv) const;

  bool InImage(const Eigen::Vector2d& uv) const;

 private:
  FisheyeIntrinsics intrinsics_;
  double max_valid_theta_ = 0.0;
  double max_valid_theta_d_ = 0.0;
};

}  // namespace gs360
