#pragma once
// How large a press's imprint will look in the camera, decided before the run: the reconstruction
// measures an imprint's depth from the slopes of its pixels, and an imprint that covers few
// pixels (far from the camera, or seen at a steep angle) is measured coarsely, whatever the
// model. The plan names the probes that will be seen that small, so that a rig whose gel is
// largely seen so is told before it runs (PlanAdvice, plan/plan.h).
//
// Frames: sensor frame (mm) for points and normals, the camera frame by the NOMINAL
// cam_from_sensor (the plan's; the calibrated pose differs by a fraction of a millimetre).

#include <vector>

#include <Eigen/Core>

#include "geometry/fisheye.h"
#include "geometry/rigid3.h"

namespace gs360 {

// Imprints smaller than this (camera pixels) are measured coarsely: on held-out rigs their peak
// depth was off by 0.17-0.31 mm even from the rendered imprint's exact slopes, against
// 0.04-0.05 mm at 100-400 px (docs/benchmarks.md, "Held-out rigs").
inline constexpr double kMinImprintPixels = 100.0;

// Area (px) of the contact disc of a ball of `ball_radius` pressed `press_depth` into the gel at
// `point_sensor` (outward unit `normal_sensor`), taken as flat there (radius sqrt(2 R d - d^2)),
// as the camera sees it: the disc's projected ellipse. 0 when the point is behind the camera,
// outside the lens's valid field or the image, or is seen from outside (the camera looks at the
// gel from within: its outward normal points away from the lens).
double ExpectedImprintPixels(const FisheyeCamera& camera, const Rigid3d& cam_from_sensor,
                             const Eigen::Vector3d& point_sensor,
                             const Eigen::Vector3d& normal_sensor, double ball_radius,
                             double press_depth);

// The probes of a plan whose imprints will be under kMinImprintPixels (those seen at all).
struct SmallImprints {
  int probes = 0;       // under kMinImprintPixels
  int seen = 0;         // probes whose imprint projects into the image at all
  double z_min_mm = 0;  // sensor z range of the small ones (0 when none)
  double z_max_mm = 0;
  double median_px = 0;  // median expected area of the small ones
  double Share() const { return seen > 0 ? static_cast<double>(probes) / seen : 0.0; }
};

// Throws std::invalid_argument when points and normals differ in count or ball_radius,
// press_depth are not 0 < press_depth < ball_radius.
SmallImprints FindSmallImprints(const FisheyeCamera& camera, const Rigid3d& cam_from_sensor,
                                const std::vector<Eigen::Vector3d>& points_sensor,
                                const std::vector<Eigen::Vector3d>& normals_sensor,
                                double ball_radius, double press_depth);

}  // namespace gs360
