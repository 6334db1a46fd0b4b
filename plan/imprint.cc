#include "plan/imprint.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace gs360 {

double ExpectedImprintPixels(const FisheyeCamera& camera, const Rigid3d& cam_from_sensor,
                             const Eigen::Vector3d& point_sensor,
                             const Eigen::Vector3d& normal_sensor, double ball_radius,
                             double press_depth) {
  const Eigen::Vector3d x = cam_from_sensor * point_sensor;
  const Eigen::Vector3d n = cam_from_sensor.RotateDirection(normal_sensor).normalized();
  // The camera looks at the gel from inside: the outward normal points away from the lens.
  if (!(n.dot(x) > 0.0)) return 0.0;
  const double a =
      std::sqrt(std::max(0.0, 2.0 * ball_radius * press_depth - press_depth * press_depth));
  // Two tangent directions; the ellipse's area is pi |du x dv| for its two half-axes' images
  // (central differences: the disc is small against its distance from the lens).
  const Eigen::Vector3d helper =
      std::abs(n.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  const Eigen::Vector3d t1 = n.cross(helper).normalized(), t2 = n.cross(t1);
  const auto c = camera.CamToPixel(x);
  if (!c) return 0.0;
  Eigen::Vector2d half[2];
  const Eigen::Vector3d t[2] = {t1, t2};
  for (int k = 0; k < 2; ++k) {
    half[k] = 0.5 * (camera.ProjectUnchecked(x + a * t[k]) - camera.ProjectUnchecked(x - a * t[k]));
  }
  const double area =
      3.14159265358979323846 * std::abs(half[0].x() * half[1].y() - half[0].y() * half[1].x());
  return std::isfinite(area) ? area : 0.0;
}

SmallImprints FindSmallImprints(const FisheyeCamera& camera, const Rigid3d& cam_from_sensor,
                                const std::vector<Eigen::Vector3d>& points_sensor,
                                const std::vector<Eigen::Vector3d>& normals_sensor,
                                double ball_radius, double press_depth) {
  if (points_sensor.size() != normals_sensor.size()) {
    throw std::invalid_argument("FindSmallImprints: " + std::to_string(points_sensor.size()) +
                                " points but " + std::to_string(normals_sensor.size()) +
                                " normals");
  }
  if (!(press_depth > 0.0 && press_depth < ball_radius)) {
    throw std::invalid_argument("FindSmallImprints: press_depth " + std::to_string(press_depth) +
                                " must be in (0, ball_radius " + std::to_string(ball_radius) + ")");
  }
  SmallImprints out;
  std::vector<double> small;
  for (std::size_t i = 0; i < points_sensor.size(); ++i) {
    const double px = ExpectedImprintPixels(camera, cam_from_sensor, points_sensor[i],
                                            normals_sensor[i], ball_radius, press_depth);
    if (!(px > 0.0)) continue;
    ++out.seen;
    if (px >= kMinImprintPixels) continue;
    const double z = points_sensor[i].z();
    out.z_min_mm = small.empty() ? z : std::min(out.z_min_mm, z);
    out.z_max_mm = small.empty() ? z : std::max(out.z_max_mm, z);
    small.push_back(px);
  }
  out.probes = static_cast<int>(small.size());
  if (!small.empty()) {
    std::nth_element(small.begin(), small.begin() + static_cast<std::ptrdiff_t>(small.size() / 2),
                     small.end());
    out.median_px = small[small.size() / 2];
  }
  return out;
}

}  // namespace gs360
