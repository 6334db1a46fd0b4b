#pragma once
// The surface map: for every pixel of the camera, where its ray first meets the gel's undeformed
// outer surface, and the frame the calibration's slopes are expressed in. Computed once per camera
// pose (the sensor is static); every probe and every reconstructed frame reuses it.
//
// Frames and units: everything per pixel is in the CAMERA frame (OpenCV: x right, y down,
// z forward), mm. Pixel (u, v) = (column, row), (0, 0) the centre of the top-left pixel, as in
// geometry/fisheye.h.
//
// Per pixel (valid where status == kVisible; kOutside pixels hold zeros, see below for others):
//   ray d        unit ray of the pixel (FisheyeCamera::PixelToRay)
//   ray_du/dv    derivatives of the unit ray with respect to u and v (1/px)
//   rho0         distance along d to the first hit x0 = rho0 d on the gel (mm)
//   n0           smooth outward unit normal of the gel at x0 (the mesh's barycentric normal)
//   t1           unit tangent along the image's u direction on the surface:
//                  t1 = normalise(d_u - d (n0.d_u)/(n0.d)), which is dx0/du projected on the
//                  tangent plane (exactly tangent: it follows from d(log rho0)/du =
//                  -(n0.d_u)/(n0.d))
//   t2           n0 x t1 (unit, tangent; (t1, t2, n0) right-handed)
//   view angle   angle between -d and n0 (0 = the camera looks straight at the surface),
//                computed orientation-free as acos(|n0.d|): seen from inside the finger the
//                OUTWARD normal n0 points away from the camera (n0.d > 0), which is expected.
// Beyond kVisible pixels (implementation detail, do not rely on it for status): ray, ray_du and
// ray_dv are filled for every pixel with a valid ray (status != kOutside); rho0, n0, t1, t2 and
// the view angle also for kGrazing pixels and for kFin pixels (the gel behind the fin).
// Status: kOutside (no valid ray: outside the image or the fisheye's valid field), kNoHit (the
// ray leaves through the base opening or misses), kFin (a fin is hit before the gel, or the pixel
// is within fin_margin_px of such a pixel), kGrazing (view angle > max_view_angle_deg), kVisible.
//
// Slopes (docs/design.md, "Render"): a deformed normal n at a visible pixel is described by
// gx = (n.t1)/(n.n0), gy = (n.t2)/(n.n0), and recovered as n = normalise(n0 + gx t1 + gy t2).
//
// Thread safety: immutable after Build/Deserialize; const methods may be called from any thread.

#include <Eigen/Core>
#include <cstdint>
#include <span>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "geometry/bvh.h"
#include "geometry/fisheye.h"
#include "geometry/rigid3.h"

namespace gs360 {

struct SurfaceMapOptions {
  double max_view_angle_deg = 80.0;  // larger view angles are kGrazing (0 < value < 90)
  double fin_margin_px = 1.0;        // dilate the fin pixels by this radius (>= 0)
  int threads = 2;                   // for Build (1..64)
  // Throws std::invalid_argument naming the field and its value.
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("max_view_angle_deg", self.max_view_angle_deg);
    visit("fin_margin_px", self.fin_margin_px);
    visit("threads", self.threads);
  }
  void Check() const;
};

enum class SurfacePixel : std::uint8_t {
  kOutside = 0,
  kNoHit = 1,
  kFin = 2,
  kGrazing = 3,
  kVisible = 4
};

struct SurfaceMapStats {
  int visible = 0, fin = 0, grazing = 0, no_hit = 0, outside = 0;
  double build_seconds = 0.0;
};

class SurfaceMap {
 public:
  SurfaceMap() = default;

  // Ray-casts every pixel. `gel` and `fins` are BVHs of meshes in the SENSOR frame (fins may be
  // null: no fins). Throws std::invalid_argument for invalid options; std::runtime_error when no
  // pixel sees the gel (naming the camera pose), which means the pose or the mesh is wrong.
  static SurfaceMap Build(const FisheyeCamera& camera, const Rigid3d& cam_from_sensor,
                          const Bvh& gel, const Bvh* fins, const SurfaceMapOptions& options = {});

  int width() const { return width_; }
  int height() const { return height_; }
  const Rigid3d& cam_from_sensor() const { return cam_from_sensor_; }
  const SurfaceMapOptions& options() const { return options_; }
  const SurfaceMapStats& stats() const { return stats_; }

  SurfacePixel status(int u, int v) const { return status_[Index(u, v)]; }
  bool visible(int u, int v) const { return status(u, v) == SurfacePixel::kVisible; }
  Eigen::Vector3d ray(int u, int v) const { return Get(ray_, u, v); }
  Eigen::Vector3d ray_du(int u, int v) const { return Get(ray_du_, u, v); }
  Eigen::Vector3d ray_dv(int u, int v) const { return Get(ray_dv_, u, v); }
  double rho0(int u, int v) const { return rho0_[Index(u, v)]; }
  Eigen::Vector3d point0(int u, int v) const { return rho0(u, v) * ray(u, v); }
  Eigen::Vector3d normal0(int u, int v) const { return Get(n0_, u, v); }
  Eigen::Vector3d t1(int u, int v) const { return Get(t1_, u, v); }
  Eigen::Vector3d t2(int u, int v) const { return Get(t2_, u, v); }
  double view_angle(int u, int v) const { return view_angle_[Index(u, v)]; }  // rad

  // Full-image CV_8U mask, 255 where visible.
  cv::Mat VisibleMask() const;
  // Full-image CV_8U of the SurfacePixel values.
  cv::Mat StatusImage() const;

  // Normal from slopes at a visible pixel: normalise(n0 + gx t1 + gy t2).
  Eigen::Vector3d NormalFromSlopes(int u, int v, double gx, double gy) const;
  // Slopes of a normal at a visible pixel: ((n.t1)/(n.n0), (n.t2)/(n.n0)); n.n0 must be > 0.
  Eigen::Vector2d SlopesFromNormal(int u, int v, const Eigen::Vector3d& n) const;

  // Binary form (little-endian, versioned, checksummed). Deserialize throws std::runtime_error
  // naming what is wrong (bad magic, unsupported version, truncated, checksum mismatch).
  std::vector<std::uint8_t> Serialize() const;
  static SurfaceMap Deserialize(std::span<const std::uint8_t> bytes);

 private:
  std::size_t Index(int u, int v) const {
    return static_cast<std::size_t>(v) * static_cast<std::size_t>(width_) +
           static_cast<std::size_t>(u);
  }
  static Eigen::Vector3d Get(const std::vector<float>& a, std::size_t i) {
    return {a[3 * i], a[3 * i + 1], a[3 * i + 2]};
  }
  Eigen::Vector3d Get(const std::vector<float>& a, int u, int v) const {
    return Get(a, Index(u, v));
  }

  int width_ = 0, height_ = 0;
  Rigid3d cam_from_sensor_;
  SurfaceMapOptions options_;
  SurfaceMapStats stats_;
  std::vector<SurfacePixel> status_;
  // 3 floats per pixel, row-major. rho0 in double (it is differenced).
  std::vector<float> ray_, ray_du_, ray_dv_, n0_, t1_, t2_;
  std::vector<double> rho0_;
  std::vector<float> view_angle_;
};

}  // namespace gs360
