#pragma once
// Signed distance from points to the sensor's outer surface, for the planner's collision checks
// (ball and stylus against the finger). Millions of queries per plan, so both backends are
// accelerated:
// - surface of revolution (built-in shapes): the profile curve as a dense polyline in the
//   meridian half-plane (rho, z) (uniform in arc length; chord error ~1e-5 mm for the built-in
//   shapes at the default 4096 segments) with a segment hierarchy for the closest point;
// - any triangle mesh: a bounding-volume hierarchy over the triangles for the closest point, the
//   sign from angle-weighted pseudo-normals (Baerentzen & Aanaes 2005), exact for a closed,
//   consistently outward-wound mesh and correct near the base opening of a sensor mesh.
//
// Frame: sensor frame (base plane z = 0, axis +z), mm. Sign: > 0 outside the finger, < 0 inside.
// The base disc (z = 0) is not part of the surface: for the revolution backend, points below
// z = 0 or above the tip are outside; the mount below the base plane is a separate obstacle
// (the planner's option). Immutable after construction; queries are const and thread-safe;
// copies share the acceleration structure.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <memory>

#include "geometry/mesh.h"
#include "geometry/shapes.h"

namespace gs360 {

class SurfaceDistance {
 public:
  // Surface of revolution about the sensor z axis. `segments` >= 16 polyline segments. Throws
  // std::invalid_argument for fewer segments.
  // Throws std::invalid_argument for a null profile too.
  static SurfaceDistance FromProfile(std::shared_ptr<const RevolutionProfile> profile,
                                     int segments = 4096);
  // Any triangle mesh (degenerate triangles ignored). Throws std::invalid_argument for a mesh
  // without a non-degenerate triangle or with non-finite vertices.
  static SurfaceDistance FromMesh(const TriangleMesh& mesh);

  // Signed distance (mm) from p to the surface.
  double Signed(const Eigen::Vector3d& p) const;
  // Signed distance and the closest surface point (sensor frame).
  double Signed(const Eigen::Vector3d& p, Eigen::Vector3d* closest) const;

  // Closest surface point with its outward unit normal. Revolution backend: the point and normal
  // are evaluated on the exact profile at the closest polyline point's parameter (exactly on
  // the surface, within ~1e-5 mm of the true closest point). Mesh backend: the closest point on
  // the triangles and the normalised pseudo-normal of the closest feature.
  struct Closest {
    Eigen::Vector3d point = Eigen::Vector3d::Zero();
    Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();
    double signed_distance = 0.0;
  };
  Closest ClosestPoint(const Eigen::Vector3d& p) const;

  // True for the revolution backend: RadiusAt / MaxRadius are then exact for the polyline.
  bool IsRevolution() const;
  // Revolution backend: radius of the surface at height z (0 outside [0, height]). Mesh backend:
  // throws std::logic_error.
  double RadiusAt(double z) const;
  // Revolution backend: largest surface radius over heights [z0, z1] intersected with
  // [0, height], or -inf when that intersection is empty. Mesh backend: std::logic_error.
  double MaxRadius(double z0, double z1) const;

  // Axis-aligned bounds of the surface and the largest distance of a surface point from the z
  // axis (mm).
  const Eigen::AlignedBox3d& Bounds() const;
  double BoundingRadius() const;

  struct Impl;

 private:
  explicit SurfaceDistance(std::shared_ptr<const Impl> impl) : impl_(std::move(impl)) {}
  std::shared_ptr<const Impl> impl_;
};

}  // namespace gs360
