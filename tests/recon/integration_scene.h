#pragma once
// Synthetic scenes with known answers for the log-distance integration (tests/recon and
// bench/bench_integration.cc): a rigid ball pressed into a surface seen through a surface map.
// Header-only, test and bench code only.
//
// The truth is the rigid imprint (docs/design.md, "Render"): for a visible pixel with ray d, the
// ball (centre c, radius r, camera frame) entered at t_b < rho0 means contact: x = t_b d and the
// gel's outward normal is n = (c - x) / r; elsewhere x = rho0 d and n = n0.

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <vector>

#include <opencv2/core.hpp>

#include "geometry/bvh.h"
#include "geometry/fisheye.h"
#include "geometry/mesh.h"
#include "recon/integration.h"
#include "recon/surface_map.h"

namespace gs360::testing {

struct PressScene {
  cv::Rect roi;
  cv::Mat normals;  // CV_64FC3 exact normals (NaN where not visible)
  cv::Mat rho;      // CV_64F true distance along the ray (NaN where not visible)
  cv::Mat contact;  // CV_8U 255 = contact
  int contact_pixels = 0;
};

// Ball entry distance along the unit ray d from the camera centre, or +inf.
inline double BallEntry(const Eigen::Vector3d& d, const Eigen::Vector3d& c, double r) {
  const double b = d.dot(c);
  const double disc = b * b - c.squaredNorm() + r * r;
  if (disc <= 0.0) return std::numeric_limits<double>::infinity();
  const double t = b - std::sqrt(disc);
  return t > 0.0 ? t : std::numeric_limits<double>::infinity();
}

// Renders the press of a ball (camera-frame centre c, radius r) into the map's surface. The roi
// is the bounding box of the contact pixels grown by `margin` px (clipped to the image); empty
// when there is no contact.
inline PressScene RenderPress(const SurfaceMap& map, const FisheyeCamera& camera,
                              const Eigen::Vector3d& c, double r, int margin = 4) {
  PressScene s;
  // The ball's image: project points of its surface.
  double u_lo = 1e9, u_hi = -1e9, v_lo = 1e9, v_hi = -1e9;
  for (int i = 0; i < 24; ++i) {
    for (int j = 0; j < 48; ++j) {
      const double th = std::numbers::pi * (i + 0.5) / 24, ph = 2 * std::numbers::pi * j / 48;
      const Eigen::Vector3d p = c + r * Eigen::Vector3d(std::sin(th) * std::cos(ph),
                                                        std::sin(th) * std::sin(ph), std::cos(th));
      if (const auto uv = camera.CamToPixel(p)) {
        u_lo = std::min(u_lo, uv->x()), u_hi = std::max(u_hi, uv->x());
        v_lo = std::min(v_lo, uv->y()), v_hi = std::max(v_hi, uv->y());
      }
    }
  }
  if (u_lo > u_hi) return s;
  const int x0 = std::max(0, static_cast<int>(std::floor(u_lo)) - 2);
  const int x1 = std::min(map.width() - 1, static_cast<int>(std::ceil(u_hi)) + 2);
  const int y0 = std::max(0, static_cast<int>(std::floor(v_lo)) - 2);
  const int y1 = std::min(map.height() - 1, static_cast<int>(std::ceil(v_hi)) + 2);
  int cx0 = 1 << 30, cx1 = -1, cy0 = 1 << 30, cy1 = -1;
  for (int v = y0; v <= y1; ++v) {
    for (int u = x0; u <= x1; ++u) {
      if (!map.visible(u, v)) continue;
      if (BallEntry(map.ray(u, v).normalized(), c, r) < map.rho0(u, v)) {
        cx0 = std::min(cx0, u), cx1 = std::max(cx1, u);
        cy0 = std::min(cy0, v), cy1 = std::max(cy1, v);
      }
    }
  }
  if (cx1 < 0) return s;
  const int rx0 = std::max(0, cx0 - margin), ry0 = std::max(0, cy0 - margin);
  const int rx1 = std::min(map.width() - 1, cx1 + margin);
  const int ry1 = std::min(map.height() - 1, cy1 + margin);
  s.roi = cv::Rect(rx0, ry0, rx1 - rx0 + 1, ry1 - ry0 + 1);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  s.normals = cv::Mat(s.roi.size(), CV_64FC3, cv::Scalar(nan, nan, nan));
  s.rho = cv::Mat(s.roi.size(), CV_64F, cv::Scalar(nan));
  s.contact = cv::Mat::zeros(s.roi.size(), CV_8U);
  for (int y = 0; y < s.roi.height; ++y) {
    for (int x = 0; x < s.roi.width; ++x) {
      const int u = s.roi.x + x, v = s.roi.y + y;
      if (!map.visible(u, v)) continue;
      const Eigen::Vector3d d = map.ray(u, v).normalized();
      const double tb = BallEntry(d, c, r);
      Eigen::Vector3d n = map.normal0(u, v);
      double rho = map.rho0(u, v);
      if (tb < rho) {
        rho = tb;
        n = (c - tb * d) / r;
        s.contact.at<std::uint8_t>(y, x) = 255;
        ++s.contact_pixels;
      }
      s.rho.at<double>(y, x) = rho;
      s.normals.at<cv::Vec3d>(y, x) = cv::Vec3d(n.x(), n.y(), n.z());
    }
  }
  return s;
}

// A vertical open cylinder of `radius` around the sensor z axis, from z = 0 to `height`, with
// exact outward normals; fine in azimuth (its chord sag is radius (1 - cos(pi / segments))).
// UV sphere with exact outward vertex normals.
inline TriangleMesh Sphere(const Eigen::Vector3d& c, double radius, int segments, int rings) {
  TriangleMesh m;
  for (int i = 0; i <= rings; ++i) {
    const double th = std::numbers::pi * i / rings;
    for (int j = 0; j < segments; ++j) {
      const double ph = 2.0 * std::numbers::pi * j / segments;
      const Eigen::Vector3d n(std::sin(th) * std::cos(ph), std::sin(th) * std::sin(ph),
                              std::cos(th));
      m.vertices.push_back(c + radius * n);
      m.normals.push_back(n);
    }
  }
  for (int i = 0; i < rings; ++i) {
    for (int j = 0; j < segments; ++j) {
      const int a = i * segments + j, b = i * segments + (j + 1) % segments;
      if (i > 0) m.triangles.emplace_back(a, a + segments, b);
      if (i + 1 < rings) m.triangles.emplace_back(b, a + segments, b + segments);
    }
  }
  return m;
}

inline TriangleMesh DenseCylinder(double radius, double height, int segments, int rings) {
  TriangleMesh m;
  for (int i = 0; i <= rings; ++i) {
    for (int j = 0; j < segments; ++j) {
      const double ph = 2.0 * std::numbers::pi * j / segments;
      m.vertices.emplace_back(radius * std::cos(ph), radius * std::sin(ph), height * i / rings);
      m.normals.emplace_back(std::cos(ph), std::sin(ph), 0.0);
    }
  }
  for (int i = 0; i < rings; ++i) {
    for (int j = 0; j < segments; ++j) {
      const int a = i * segments + j, b = i * segments + (j + 1) % segments;
      m.triangles.emplace_back(a, b, b + segments);
      m.triangles.emplace_back(a, b + segments, a + segments);
    }
  }
  return m;
}

// The deformed wall of the cylinder scene: a cylinder of radius R around the camera-frame axis
// through `axis_point` along +z (the camera looks along the axis), minus the ball (c, r). Exact
// point-to-surface distance: the nearest of the wall outside the ball, the ball inside the
// cylinder and the rim where they meet (sampled densely).
class DeformedWall {
 public:
  DeformedWall(double radius, const Eigen::Vector3d& axis_point, const Eigen::Vector3d& c, double r)
      : radius_(radius), axis_(axis_point), c_(c), r_(r) {
    const Eigen::Vector3d cr = c - axis_;
    const Eigen::Vector3d n = Eigen::Vector3d(cr.x(), cr.y(), 0.0).normalized();  // outward
    const Eigen::Vector3d e1 = Eigen::Vector3d::UnitZ();
    const Eigen::Vector3d e2 = n.cross(e1);
    constexpr int kSamples = 2048;
    for (int k = 0; k < kSamples; ++k) {
      const double ph = 2.0 * std::numbers::pi * k / kSamples;
      const Eigen::Vector3d side = std::cos(ph) * e1 + std::sin(ph) * e2;
      auto point = [&](double beta) {
        return Eigen::Vector3d(c_ + r_ * (-std::cos(beta) * n + std::sin(beta) * side));
      };
      double lo = 0.0, hi = std::numbers::pi;      // inside the cylinder at lo, outside at hi
      if (Radial(point(lo)) >= radius_) continue;  // the ball does not reach into the gel
      for (int it = 0; it < 60; ++it) {
        const double mid = 0.5 * (lo + hi);
        (Radial(point(mid)) < radius_ ? lo : hi) = mid;
      }
      rim_.push_back(point(0.5 * (lo + hi)));
    }
  }

  double Distance(const Eigen::Vector3d& q) const {
    double best = std::numeric_limits<double>::infinity();
    const double rq = Radial(q);
    if (rq > 0.0) {
      Eigen::Vector3d pw = q - axis_;
      pw.x() *= radius_ / rq;
      pw.y() *= radius_ / rq;
      pw += axis_;
      if ((pw - c_).norm() >= r_) best = std::min(best, std::abs(rq - radius_));
    }
    const double qc = (q - c_).norm();
    if (qc > 0.0) {
      const Eigen::Vector3d pb = c_ + r_ * (q - c_) / qc;
      if (Radial(pb) <= radius_) best = std::min(best, std::abs(qc - r_));
    }
    for (const Eigen::Vector3d& p : rim_) best = std::min(best, (q - p).norm());
    return best;
  }

 private:
  double Radial(const Eigen::Vector3d& p) const {
    return std::hypot(p.x() - axis_.x(), p.y() - axis_.y());
  }
  double radius_;
  Eigen::Vector3d axis_, c_;
  double r_;
  std::vector<Eigen::Vector3d> rim_;
};

struct PressErrors {
  double contact_rho = 0.0;     // mean |rho - rho_true| over contact pixels (mm)
  double roi_rho = 0.0;         // over all visible roi pixels (mm)
  double contact_p2s = 0.0;     // mean point-to-surface distance over contact pixels (mm)
  double roi_p2s = 0.0;         // over all visible roi pixels (mm)
  double max_roi_rho = 0.0;     // max |rho - rho_true| over the roi (mm)
  double view_angle_deg = 0.0;  // mean view angle of the contact pixels' undeformed surface
};

// Errors of a reconstructed rho against the scene; `wall` may be null (then p2s = rho error).
inline PressErrors MeasurePress(const SurfaceMap& map, const PressScene& s, const cv::Mat& rho,
                                const DeformedWall* wall) {
  PressErrors e;
  int n_contact = 0, n_roi = 0;
  for (int y = 0; y < s.roi.height; ++y) {
    for (int x = 0; x < s.roi.width; ++x) {
      const double truth = s.rho.at<double>(y, x);
      if (!std::isfinite(truth)) continue;
      const int u = s.roi.x + x, v = s.roi.y + y;
      const double err = std::abs(rho.at<double>(y, x) - truth);
      const Eigen::Vector3d q = rho.at<double>(y, x) * map.ray(u, v).normalized();
      const double p2s = wall ? wall->Distance(q) : err;
      e.roi_rho += err;
      e.roi_p2s += p2s;
      e.max_roi_rho = std::max(e.max_roi_rho, err);
      ++n_roi;
      if (s.contact.at<std::uint8_t>(y, x)) {
        e.contact_rho += err;
        e.contact_p2s += p2s;
        e.view_angle_deg += map.view_angle(u, v) * 180.0 / std::numbers::pi;
        ++n_contact;
      }
    }
  }
  if (n_roi > 0) e.roi_rho /= n_roi, e.roi_p2s /= n_roi;
  if (n_contact > 0) {
    e.contact_rho /= n_contact, e.contact_p2s /= n_contact, e.view_angle_deg /= n_contact;
  }
  return e;
}

}  // namespace gs360::testing
