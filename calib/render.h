#pragma once
// Rendering a probe's rigid imprint against the surface map (calibration stage 4, "render"):
// what the calibration assumes the camera sees when the ball (centre c, radius r) is pressed into
// the gel -- a rigid, sharp imprint. Only the pixels of the projected ball's bounding box are
// touched.
//
// For each visible pixel of the box (SurfaceMap status kVisible), intersect its ray d with the
// ball: entry distance t_b. If t_b < rho0 (the ball is in front of the undeformed surface) the
// pixel is in CONTACT: the deformed point is x = t_b d, the gel's outward normal there is
// n = (c - x)/r, the targets are the tangent-frame slopes gx = (n.t1)/(n.n0), gy = (n.t2)/(n.n0)
// and rho = t_b. Elsewhere rho = rho0 and gx = gy = 0. A contact pixel whose n.n0 <= cos(max
// slope angle) is still contact but flagged in `steep` (its slopes are clamped to the bound).
//
// Frames: ball centre in the CAMERA frame (mm). Pixels as in recon/surface_map.h.

#include <Eigen/Core>
#include <limits>

#include <opencv2/core/mat.hpp>

#include "geometry/fisheye.h"
#include "recon/surface_map.h"

namespace gs360 {

struct ProbeRenderOptions {
  double margin_px = 2.0;  // grow the projected ball's bounding box by this much (>= 0)
  // Slopes are clamped to tan(max_slope_deg) in magnitude (the normal turned at most this far
  // from n0); (0, 90).
  double max_slope_deg = 80.0;
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("margin_px", self.margin_px);
    visit("max_slope_deg", self.max_slope_deg);
  }
  void Check() const;  // throws std::invalid_argument naming the field and value
};

struct ProbeRender {
  cv::Rect roi;     // image pixels rendered (the projected ball's box, clipped); empty = none
  cv::Mat contact;  // CV_8U, roi-sized: 255 = contact
  cv::Mat steep;    // CV_8U, roi-sized: 255 = contact with a clamped slope
  cv::Mat gx, gy;   // CV_32F, roi-sized: slopes (0 outside contact)
  cv::Mat rho;      // CV_64F, roi-sized: mm along the ray; NaN where not visible
  int contact_pixels = 0;
  // Max over contact pixels of the rigid imprint's depth along the gel's normal at the pixel's
  // undeformed point (NormalPenetration there): the press depth, sampled at the pixels.
  double max_indentation_mm = 0.0;
  // Centroid (u, v) of the contact pixels, or of nothing (NaN) when there is no contact.
  Eigen::Vector2d contact_centroid =
      Eigen::Vector2d::Constant(std::numeric_limits<double>::quiet_NaN());
};

// `camera` must be the one the map was built with (same size). Ball centre in the camera frame.
// Never throws for a ball out of view (empty roi, no contact); std::invalid_argument for invalid
// options or a radius <= 0.
ProbeRender RenderProbe(const SurfaceMap& map, const FisheyeCamera& camera,
                        const Eigen::Vector3d& ball_center_cam, double ball_radius,
                        const ProbeRenderOptions& options = {});

// Signed penetration of the ball along each pixel's surface normal line (mm), over `roi`
// (CV_32F, roi-sized): for the undeformed point x0 with normal n0, the distance x0 must move
// along -n0 to leave the ball (> 0: the rigid imprint's depth there), or minus the gap along +n0
// to the ball (< 0; |x0 - c| - r where the normal line misses the ball). NaN where the map has no
// visible surface. It says how far a pixel is from the rigid imprint's edge, where a real gel
// rounds the imprint off (the dataset stage leaves that band out). Ball centre in the camera
// frame; roi is clipped to the map; std::invalid_argument for a radius <= 0.
cv::Mat NormalPenetration(const SurfaceMap& map, const cv::Rect& roi,
                          const Eigen::Vector3d& ball_center_cam, double ball_radius);

}  // namespace gs360
