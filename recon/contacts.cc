#include "recon/contacts.h"

#include <cmath>
#include <stdexcept>
#include <string>

namespace gs360 {
namespace {

constexpr double kPartialFraction = 0.25;

// Undeformed gel area seen by one pixel: rho0^2 times the pixel's solid angle, over the cosine
// of the view angle (the footprint of the pixel's cone on the surface).
double PixelArea(const SurfaceMap& map, int u, int v) {
  const Eigen::Vector3d d = map.ray(u, v);
  const double solid_angle = std::abs(d.dot(map.ray_du(u, v).cross(map.ray_dv(u, v))));
  const double cosine = std::max(0.05, std::abs(map.normal0(u, v).dot(d)));
  const double rho0 = map.rho0(u, v);
  return rho0 * rho0 * solid_angle / cosine;
}

// A pixel of the contact next to one the camera does not see.
bool AtEdgeOfView(const SurfaceMap& map, int u, int v) {
  for (int dv = -1; dv <= 1; ++dv) {
    for (int du = -1; du <= 1; ++du) {
      const int x = u + du, y = v + dv;
      if (x < 0 || y < 0 || x >= map.width() || y >= map.height() || !map.visible(x, y)) {
        return true;
      }
    }
  }
  return false;
}

}  // namespace

std::vector<ContactSummary> SummarizeContacts(const Reconstructor& reconstructor,
                                              const FrameReconstruction& frame,
                                              double min_indentation_mm) {
  if (!(min_indentation_mm >= 0.0)) {
    throw std::invalid_argument("SummarizeContacts: min_indentation_mm must be >= 0, got " +
                                std::to_string(min_indentation_mm));
  }
  const SurfaceMap& map = reconstructor.map();
  const Rigid3d sensor_from_cam = map.cam_from_sensor().Inverse();
  std::vector<ContactSummary> out;
  for (const RegionReconstruction& r : frame.regions) {
    ContactSummary c;
    c.roi = r.region.roi;
    Eigen::Vector3d weighted = Eigen::Vector3d::Zero();
    double weight = 0.0;
    double deepest_at_edge = 0.0;  // of the pixels next to one the camera does not see
    for (int y = 0; y < c.roi.height; ++y) {
      for (int x = 0; x < c.roi.width; ++x) {
        const double depth = r.indentation.at<double>(y, x);
        if (!(depth > min_indentation_mm)) continue;
        const int u = c.roi.x + x, v = c.roi.y + y;
        const Eigen::Vector3d p = sensor_from_cam * (r.rho.at<double>(y, x) * map.ray(u, v));
        weighted += depth * p;
        weight += depth;
        c.area_mm2 += PixelArea(map, u, v);
        ++c.pixels;
        if (depth > c.peak_indentation_mm) {
          c.peak_indentation_mm = depth;
          c.peak_sensor = p;
        }
        if (depth > deepest_at_edge && AtEdgeOfView(map, u, v)) deepest_at_edge = depth;
      }
    }
    if (c.pixels == 0) continue;
    c.centre_sensor = weighted / weight;
    // Cut where the gel is still well pressed, not where the faint rim of the contact fades.
    c.partial = deepest_at_edge > kPartialFraction * c.peak_indentation_mm;
    out.push_back(c);
  }
  return out;
}

cv::Mat IndentationImage(const Reconstructor& reconstructor, const FrameReconstruction& frame) {
  cv::Mat image(reconstructor.map().height(), reconstructor.map().width(), CV_32F,
                cv::Scalar(0.0f));
  for (const RegionReconstruction& r : frame.regions) {
    const cv::Rect& roi = r.region.roi;
    for (int y = 0; y < roi.height; ++y) {
      const double* src = r.indentation.ptr<double>(y);
      float* dst = image.ptr<float>(roi.y + y) + roi.x;
      for (int x = 0; x < roi.width; ++x) {
        // Regions may overlap: the deeper value wins; NaN (not visible) stays 0.
        if (std::isfinite(src[x]) && src[x] > dst[x]) dst[x] = static_cast<float>(src[x]);
      }
    }
  }
  return image;
}

}  // namespace gs360
