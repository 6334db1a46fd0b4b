#include "calib/render.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numbers>
#include <stdexcept>
#include <string>

namespace gs360 {
namespace {

constexpr double kDegToRad = std::numbers::pi / 180.0;

// Signed penetration of a ball of `radius` along the normal line of a surface point x0 with unit
// normal n0, q = x0 - ball centre: see NormalPenetration in render.h.
double PenetrationAlongNormal(const Eigen::Vector3d& q, const Eigen::Vector3d& n0, double radius) {
  // x0 - s n0 is inside the ball for s^2 - 2 s (q.n0) + |q|^2 - r^2 < 0; x0 + g n0 reaches its
  // surface at g^2 + 2 g (q.n0) + |q|^2 - r^2 = 0. Same discriminant.
  const double r2 = radius * radius;
  const double b = q.dot(n0), disc = b * b - q.squaredNorm() + r2;
  if (disc < 0.0) return -(q.norm() - radius);            // the line misses the ball
  if (q.squaredNorm() <= r2) return b + std::sqrt(disc);  // inside: past the far root along -n0
  const double s_near = -b - std::sqrt(disc);             // outside: first root along +n0
  return s_near >= 0.0 ? -s_near : -(q.norm() - radius);
}
// Points on the tangent cone's circle used for the projected bounding box. With 96 samples the
// chord between neighbours stays within 0.06% of the projected radius of the circle.
constexpr int kConeSamples = 96;

// Bounding box (u0, v0, u1, v1) in pixels of the ball's projection, restricted to the lens's
// valid field; false when no part of the ball is inside the field.
bool ProjectedBallBox(const FisheyeCamera& camera, const Eigen::Vector3d& c, double r, double* u0,
                      double* v0, double* u1, double* v1) {
  const double dist = c.norm();
  const double max_theta = camera.MaxValidTheta();
  const Eigen::Vector3d axis = c / dist;
  const double alpha = std::asin(std::min(1.0, r / dist));  // half-angle of the tangent cone
  const double axis_theta = std::atan2(axis.head<2>().norm(), axis.z());
  if (axis_theta - alpha > max_theta) return false;  // the whole cone is beyond the field

  // Orthonormal basis around the cone's axis.
  const Eigen::Vector3d helper =
      std::abs(axis.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  const Eigen::Vector3d e1 = axis.cross(helper).normalized();
  const Eigen::Vector3d e2 = axis.cross(e1);

  *u0 = *v0 = std::numeric_limits<double>::infinity();
  *u1 = *v1 = -std::numeric_limits<double>::infinity();
  auto add = [&](Eigen::Vector3d w) {
    // A direction beyond the field is moved radially (same azimuth) onto the field's border:
    // the projection is monotone in theta, so the clipped cap's image stays inside the box.
    const double rho_xy = w.head<2>().norm();
    const double theta = std::atan2(rho_xy, w.z());
    if (theta > max_theta) {
      const double phi = std::atan2(w.y(), w.x());
      w = Eigen::Vector3d(std::sin(max_theta) * std::cos(phi), std::sin(max_theta) * std::sin(phi),
                          std::cos(max_theta));
    }
    const Eigen::Vector2d uv = camera.ProjectUnchecked(w);
    *u0 = std::min(*u0, uv.x());
    *v0 = std::min(*v0, uv.y());
    *u1 = std::max(*u1, uv.x());
    *v1 = std::max(*v1, uv.y());
  };
  add(axis);
  const double ca = std::cos(alpha), sa = std::sin(alpha);
  for (int k = 0; k < kConeSamples; ++k) {
    const double phi = 2.0 * std::numbers::pi * k / kConeSamples;
    add(ca * axis + sa * (std::cos(phi) * e1 + std::sin(phi) * e2));
  }
  // The optical axis inside the cap: its image (the principal point) is inside the box already
  // unless the clipped cap wraps around it, in which case the border samples surround it.
  if (axis_theta < alpha) add(Eigen::Vector3d::UnitZ());
  return true;
}

}  // namespace

void ProbeRenderOptions::Check() const {
  if (!(margin_px >= 0.0) || !std::isfinite(margin_px)) {
    throw std::invalid_argument("ProbeRenderOptions.margin_px must be finite and >= 0, got " +
                                std::to_string(margin_px));
  }
  if (!(max_slope_deg > 0.0 && max_slope_deg < 90.0)) {
    throw std::invalid_argument("ProbeRenderOptions.max_slope_deg must be in (0, 90), got " +
                                std::to_string(max_slope_deg));
  }
}

ProbeRender RenderProbe(const SurfaceMap& map, const FisheyeCamera& camera,
                        const Eigen::Vector3d& ball_center_cam, double ball_radius,
                        const ProbeRenderOptions& options) {
  options.Check();
  if (!(ball_radius > 0.0) || !std::isfinite(ball_radius)) {
    throw std::invalid_argument("RenderProbe: ball_radius must be finite and > 0, got " +
                                std::to_string(ball_radius));
  }
  if (!ball_center_cam.allFinite()) {
    throw std::invalid_argument("RenderProbe: the ball centre is not finite");
  }
  if (map.width() != camera.width() || map.height() != camera.height()) {
    throw std::invalid_argument("RenderProbe: surface map is " + std::to_string(map.width()) + "x" +
                                std::to_string(map.height()) + " but the camera is " +
                                std::to_string(camera.width()) + "x" +
                                std::to_string(camera.height()));
  }
  ProbeRender out;
  const Eigen::Vector3d& c = ball_center_cam;
  const double r = ball_radius;
  const double c2 = c.squaredNorm();

  cv::Rect roi;
  const cv::Rect image(0, 0, map.width(), map.height());
  if (c2 <= r * r) {
    roi = image;  // the camera centre is inside the ball: every ray meets it
  } else {
    double u0, v0, u1, v1;
    if (!ProjectedBallBox(camera, c, r, &u0, &v0, &u1, &v1)) return out;
    const double m = options.margin_px;
    const double lo_u = std::max(-1.0, std::floor(u0 - m));
    const double lo_v = std::max(-1.0, std::floor(v0 - m));
    const double hi_u = std::min(static_cast<double>(map.width()), std::ceil(u1 + m));
    const double hi_v = std::min(static_cast<double>(map.height()), std::ceil(v1 + m));
    if (hi_u < lo_u || hi_v < lo_v) return out;
    const int iu0 = static_cast<int>(lo_u), iv0 = static_cast<int>(lo_v);
    const int iu1 = static_cast<int>(hi_u), iv1 = static_cast<int>(hi_v);
    roi = cv::Rect(iu0, iv0, iu1 - iu0 + 1, iv1 - iv0 + 1) & image;
  }
  if (roi.empty()) return out;

  out.roi = roi;
  out.contact = cv::Mat::zeros(roi.size(), CV_8U);
  out.steep = cv::Mat::zeros(roi.size(), CV_8U);
  out.gx = cv::Mat::zeros(roi.size(), CV_32F);
  out.gy = cv::Mat::zeros(roi.size(), CV_32F);
  out.rho = cv::Mat(roi.size(), CV_64F, cv::Scalar(std::numeric_limits<double>::quiet_NaN()));

  const double cos_max = std::cos(options.max_slope_deg * kDegToRad);
  const double tan_max = std::tan(options.max_slope_deg * kDegToRad);
  const double rest = c2 - r * r;
  double sum_u = 0.0, sum_v = 0.0;
  for (int y = 0; y < roi.height; ++y) {
    const int v = roi.y + y;
    std::uint8_t* contact_row = out.contact.ptr<std::uint8_t>(y);
    std::uint8_t* steep_row = out.steep.ptr<std::uint8_t>(y);
    float* gx_row = out.gx.ptr<float>(y);
    float* gy_row = out.gy.ptr<float>(y);
    double* rho_row = out.rho.ptr<double>(y);
    for (int x = 0; x < roi.width; ++x) {
      const int u = roi.x + x;
      if (!map.visible(u, v)) continue;
      const double rho0 = map.rho0(u, v);
      rho_row[x] = rho0;
      const Eigen::Vector3d d = map.ray(u, v).normalized();
      const double b = d.dot(c);
      const double disc = b * b - rest;
      if (disc < 0.0) continue;
      const double t_b = b - std::sqrt(disc);
      if (!(t_b < rho0) || t_b <= 0.0) continue;
      const Eigen::Vector3d xp = t_b * d;
      const Eigen::Vector3d n = (c - xp) / r;
      const Eigen::Vector3d n0 = map.normal0(u, v);
      const double a1 = n.dot(map.t1(u, v));
      const double a2 = n.dot(map.t2(u, v));
      const double nn0 = n.dot(n0);
      double gx = 0.0, gy = 0.0;
      if (nn0 > cos_max) {
        gx = a1 / nn0;
        gy = a2 / nn0;
      } else {
        steep_row[x] = 255;
        const double tangential = std::hypot(a1, a2);
        if (tangential > 0.0) {
          gx = tan_max * a1 / tangential;
          gy = tan_max * a2 / tangential;
        }
      }
      contact_row[x] = 255;
      gx_row[x] = static_cast<float>(gx);
      gy_row[x] = static_cast<float>(gy);
      rho_row[x] = t_b;
      ++out.contact_pixels;
      sum_u += u;
      sum_v += v;
      // The imprint's depth along the gel's own normal at this pixel's surface point (> 0 where
      // x0 is inside the ball). Its maximum is the press depth on any surface shape;
      // (rho0 - t_b) |d.n0| is that only on a flat one.
      out.max_indentation_mm =
          std::max(out.max_indentation_mm, PenetrationAlongNormal(map.point0(u, v) - c, n0, r));
    }
  }
  if (out.contact_pixels > 0) {
    out.contact_centroid = Eigen::Vector2d(sum_u, sum_v) / out.contact_pixels;
  }
  return out;
}

cv::Mat NormalPenetration(const SurfaceMap& map, const cv::Rect& roi,
                          const Eigen::Vector3d& ball_center_cam, double ball_radius) {
  if (!(ball_radius > 0.0) || !std::isfinite(ball_radius)) {
    throw std::invalid_argument("NormalPenetration: ball_radius must be finite and > 0, got " +
                                std::to_string(ball_radius));
  }
  const cv::Rect r = roi & cv::Rect(0, 0, map.width(), map.height());
  cv::Mat out(r.size(), CV_32F, cv::Scalar::all(std::numeric_limits<float>::quiet_NaN()));
  for (int y = 0; y < r.height; ++y) {
    for (int x = 0; x < r.width; ++x) {
      const int u = r.x + x, v = r.y + y;
      if (!map.visible(u, v)) continue;
      const double p = PenetrationAlongNormal(map.point0(u, v) - ball_center_cam, map.normal0(u, v),
                                              ball_radius);
      out.at<float>(y, x) = static_cast<float>(p);
    }
  }
  return out;
}

}  // namespace gs360
