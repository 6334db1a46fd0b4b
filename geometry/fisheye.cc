#include "geometry/fisheye.h"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <sstream>
#include <stdexcept>

#include "base/field_error.h"

namespace gs360 {
namespace {

constexpr double kHalfPi = 0.5 * std::numbers::pi;

[[noreturn]] void Bad(const char* field, double v, const char* rule) {
  ThrowFieldError(std::string("FisheyeIntrinsics.") + field, v, rule);
}

}  // namespace

void FisheyeIntrinsics::Check() const {
  if (width <= 0) Bad("width", width, "must be > 0");
  if (height <= 0) Bad("height", height, "must be > 0");
  if (!(fx > 0.0) || !std::isfinite(fx)) Bad("fx", fx, "must be finite and > 0");
  if (!(fy > 0.0) || !std::isfinite(fy)) Bad("fy", fy, "must be finite and > 0");
  if (!std::isfinite(cx)) Bad("cx", cx, "must be finite");
  if (!std::isfinite(cy)) Bad("cy", cy, "must be finite");
  if (!std::isfinite(skew)) Bad("skew", skew, "must be finite");
  static const char* const kNames[4] = {"k[0]", "k[1]", "k[2]", "k[3]"};
  for (int i = 0; i < 4; ++i)
    if (!std::isfinite(k[i])) Bad(kNames[i], k[i], "must be finite");
  if (!(max_theta > 0.0) || !(max_theta <= kHalfPi)) {
    Bad("max_theta", max_theta, "must be in (0, pi/2] rad");
  }
}

FisheyeIntrinsics FisheyeIntrinsics::Default160(int width, int height) {
  FisheyeIntrinsics in;
  in.width = width;
  in.height = height;
  in.max_theta = 80.0 * std::numbers::pi / 180.0;
  const double circle_radius = 0.5 * std::min(width, height) - 4.0;
  in.fx = in.fy = circle_radius / in.max_theta;
  in.cx = 0.5 * (width - 1);
  in.cy = 0.5 * (height - 1);
  in.Check();
  return in;
}

FisheyeCamera::FisheyeCamera(const FisheyeIntrinsics& intrinsics) : intrinsics_(intrinsics) {
  intrinsics_.Check();
  // theta_d'(theta) = 1 + 3 k1 t^2 + 5 k2 t^4 + 7 k3 t^6 + 9 k4 t^8: find its first zero.
  const auto& k = intrinsics_.k;
  auto slope = [&](double t) {
    const double t2 = t * t;
    return 1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])));
  };
  const double limit = std::min(intrinsics_.max_theta, kHalfPi);
  max_valid_theta_ = limit;
  const int steps = 20000;
  for (int i = 1; i <= steps; ++i) {
    const double t = limit * i / steps;
    if (slope(t) <= 0.0) {
      double lo = limit * (i - 1) / steps, hi = t;
      for (int it = 0; it < 200 && hi - lo > 0.0; ++it) {
        const double mid = 0.5 * (lo + hi);
        if (mid <= lo || mid >= hi) break;
        (slope(mid) > 0.0 ? lo : hi) = mid;
      }
      max_valid_theta_ = lo;
      break;
    }
  }
  max_valid_theta_d_ = ThetaToThetaD(max_valid_theta_);
}

double FisheyeCamera::ThetaToThetaD(double theta) const {
  const auto& k = intrinsics_.k;
  const double t2 = theta * theta;
  return theta * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))));
}

std::optional<double> FisheyeCamera::ThetaDToTheta(double theta_d) const {
  if (!(theta_d >= 0.0) || theta_d > max_valid_theta_d_) return std::nullopt;
  if (theta_d == 0.0) return 0.0;
  if (theta_d == max_valid_theta_d_) return max_valid_theta_;
  const auto& k = intrinsics_.k;
  // theta_d(theta) is increasing on [0, max_valid_theta_]: Newton kept inside a bisection
  // bracket.
  double lo = 0.0, hi = max_valid_theta_;
  double t = std::clamp(theta_d, lo, hi);
  for (int it = 0; it < 100; ++it) {
    const double f = ThetaToThetaD(t) - theta_d;
    if (f == 0.0) return t;
    (f > 0.0 ? hi : lo) = t;
    const double t2 = t * t;
    const double df =
        1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])));
    double next = df > 0.0 ? t - f / df : 0.5 * (lo + hi);
    if (!(next > lo && next < hi)) next = 0.5 * (lo + hi);
    if (std::abs(next - t) <= 1e-16 * std::max(1.0, t)) return next;
    t = next;
  }
  return t;
}

bool FisheyeCamera::InImage(const Eigen::Vector2d& uv) const {
  return uv.x() >= -0.5 && uv.x() <= intrinsics_.width - 0.5 && uv.y() >= -0.5 &&
         uv.y() <= intrinsics_.height - 0.5;
}

std::optional<double> FisheyeCamera::PixelTheta(const Eigen::Vector2d& uv) const {
  const double yd = (uv.y() - intrinsics_.cy) / intrinsics_.fy;
  const double xd = (uv.x() - intrinsics_.cx) / intrinsics_.fx - intrinsics_.skew * yd;
  return ThetaDToTheta(std::hypot(xd, yd));
}

std::optional<Eigen::Vector3d> FisheyeCamera::PixelToRay(const Eigen::Vector2d& uv) const {
  if (!uv.allFinite() || !InImage(uv)) return std::nullopt;
  const double yd = (uv.y() - intrinsics_.cy) / intrinsics_.fy;
  const double xd = (uv.x() - intrinsics_.cx) / intrinsics_.fx - intrinsics_.skew * yd;
  const double theta_d = std::hypot(xd, yd);
  const std::optional<double> theta = ThetaDToTheta(theta_d);
  if (!theta) return std::nullopt;
  if (theta_d == 0.0) return Eigen::Vector3d::UnitZ();
  const double s = std::sin(*theta) / theta_d;
  return Eigen::Vector3d(s * xd, s * yd, std::cos(*theta));
}

Eigen::Vector2d FisheyeCamera::ProjectUnchecked(const Eigen::Vector3d& x_cam) const {
  // Not std::hypot: its care for overflow costs a third of this function, and points in mm do
  // not come near it.
  const double r = std::sqrt(x_cam.x() * x_cam.x() + x_cam.y() * x_cam.y());
  const double theta = std::atan2(r, x_cam.z());
  const double theta_d = ThetaToThetaD(theta);
  double xd = 0.0, yd = 0.0;
  if (r > 0.0) {
    xd = theta_d * x_cam.x() / r;
    yd = theta_d * x_cam.y() / r;
  }
  return {intrinsics_.fx * (xd + intrinsics_.skew * yd) + intrinsics_.cx,
          intrinsics_.fy * yd + intrinsics_.cy};
}

std::optional<Eigen::Vector2d> FisheyeCamera::CamToPixel(const Eigen::Vector3d& x_cam) const {
  if (!x_cam.allFinite() || x_cam.squaredNorm() == 0.0) return std::nullopt;
  const double theta = std::atan2(std::hypot(x_cam.x(), x_cam.y()), x_cam.z());
  if (theta > max_valid_theta_) return std::nullopt;
  const Eigen::Vector2d uv = ProjectUnchecked(x_cam);
  if (!InImage(uv)) return std::nullopt;
  return uv;
}

}  // namespace gs360
