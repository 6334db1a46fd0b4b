#pragma once
// Built-in sensor shapes (GelSight360 paper: cylinder with a hemispherical cap, cone with a
// rounded tip, spline of revolution) and the LED fins.
//
// Frame: sensor frame. Base plane z = 0, axis +z toward the tip, units mm. Every shape is a
// surface of revolution about the z axis, generated from a 2D profile curve (r, z) that starts on
// the base rim (r > 0, z = 0) and ends on the axis at the tip (r = 0, z = height) with a
// horizontal tangent (outward normal +z), so the tip is smooth and the surface is closed except
// at the base opening. One generator (MakeRevolutionMesh) tessellates every profile.

#include <Eigen/Core>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "geometry/mesh.h"

namespace gs360 {

// Profile of a surface of revolution, parameterised by t in [0, 1]: t = 0 the base rim,
// t = 1 the tip on the axis. Requirements (guaranteed by the built-in profiles through their
// options' Check()): z(t) strictly increasing (so r(z) is single-valued), r(t) > 0 for t < 1,
// r(1) = 0, normal (0, 1) at t = 1. A subclass must call Tabulate() at the end of its
// constructor. Immutable after construction; all methods are thread-safe.
class RevolutionProfile {
 public:
  virtual ~RevolutionProfile() = default;

  // (r, z) in mm at parameter t (clamped to [0, 1]).
  virtual Eigen::Vector2d Point(double t) const = 0;
  // Outward unit normal (n_r, n_z) of the profile at t (pointing away from the axis / up).
  virtual Eigen::Vector2d Normal(double t) const = 0;
  // e.g. "cylinder-cap radius=10 height=30".
  virtual std::string Describe() const = 0;

  double Height() const { return Point(1.0).y(); }
  double BaseRadius() const { return Point(0.0).x(); }
  // Radius (mm) of the surface at height z; 0 above the tip, BaseRadius() below the base.
  double RadiusAt(double z) const;
  // Parameter t with z(t) = z (clamped to [0, 1]).
  double ParameterAtZ(double z) const;
  // Arc length (mm) of the profile curve from the rim to the tip, and the parameter at arc
  // length s (clamped), both from a dense table (relative accuracy ~1e-7).
  double ArcLength() const { return arc_length_.back(); }
  double ParameterAtArcLength(double s) const;
  // Area (mm^2) of the surface of revolution (the base disc excluded), by Pappus over the table.
  double SurfaceArea() const;

  // 3D point and outward unit normal at parameter t and azimuth phi (rad, from +x toward +y).
  Eigen::Vector3d SurfacePoint(double t, double phi) const;
  Eigen::Vector3d SurfaceNormal(double t, double phi) const;

  // Closest point of the surface (base disc excluded) to p (sensor frame). signed_distance is
  // positive outside the finger, negative inside. For p on the axis the azimuth is 0.
  struct Closest {
    Eigen::Vector3d point;
    Eigen::Vector3d normal;  // outward unit normal at `point`
    double signed_distance = 0.0;
    double t = 0.0;    // profile parameter of `point`
    double phi = 0.0;  // azimuth of `point`
  };
  Closest ClosestPoint(const Eigen::Vector3d& p) const;

 protected:
  // Concrete profiles call this at the end of their constructor (fills the arc-length table).
  void Tabulate();

 private:
  std::vector<double> table_t_;
  std::vector<double> arc_length_{0.0};
};

// Cylinder of `radius` from z = 0 up to z = height - radius, closed by a hemisphere.
struct CylinderCapOptions {
  double radius = 10.0;  // mm
  double height = 30.0;  // mm, total (cap included); must be >= radius
  void Check() const;
};

// Cone from the base rim (base_radius, 0) toward the axis, closed by a sphere of tip_radius
// tangent to the cone; the top of that sphere is at z = height.
struct ConeOptions {
  double base_radius = 10.0;  // mm
  double height = 30.0;       // mm, total (rounded tip included)
  double tip_radius = 3.0;    // mm, radius of the tangent tip sphere, < base_radius
  void Check() const;
};

// Spline of revolution: radius profile r(z) through control points (z_i, r_i) with z_0 = 0,
// z strictly increasing, r_i > 0, and a last point (height, 0) on the axis. r(z)^2 is
// interpolated by a monotone (Fritsch-Carlson PCHIP) cubic, which never overshoots (r stays
// positive), is C1, and gives the tip a horizontal tangent (r ~ sqrt(height - z) near the tip,
// the slope of r^2 at the tip being that of the last interval). The default is a finger like
// the paper's spline sensor: a wide base, a slight waist, a bulb and a rounded tip.
struct SplineOptions {
  std::vector<Eigen::Vector2d> control_points = {{0.0, 10.0}, {6.0, 9.0},  {12.0, 8.5}, {18.0, 9.0},
                                                 {23.0, 8.0}, {27.0, 5.5}, {30.0, 0.0}};
  void Check() const;
};

std::shared_ptr<const RevolutionProfile> MakeCylinderCapProfile(const CylinderCapOptions& options);
std::shared_ptr<const RevolutionProfile> MakeConeProfile(const ConeOptions& options);
std::shared_ptr<const RevolutionProfile> MakeSplineProfile(const SplineOptions& options);

// Tessellation of a surface of revolution: `segments` vertices around each ring, `rings` rings
// from the base rim (ring 0, at z = 0) to the last ring before the tip, evenly spaced in arc
// length, plus one tip vertex: segments * rings + 1 vertices, segments * (2 * rings - 1)
// triangles. rings = 0 picks rings so that the spacing along the profile
// matches the spacing around the base rim (square-ish quads).
struct TessellationOptions {
  int segments = 128;
  int rings = 0;
  void Check() const;
  // About `triangles` triangles with square-ish quads for this profile.
  static TessellationOptions ForTriangleCount(const RevolutionProfile& profile, int triangles);
};

// Surface of revolution: vertices exactly on the profile, exact analytic normals, CCW outward,
// closed except at the base ring (z = 0), which is left open. Vertex 0..segments-1 is the rim.
// Throws std::invalid_argument (before allocating) when segments x rings, rings = 0 resolved,
// exceeds kMaxRevolutionVertices.
inline constexpr double kMaxRevolutionVertices = 4e6;
TriangleMesh MakeRevolutionMesh(const RevolutionProfile& profile,
                                const TessellationOptions& tessellation = {});

enum class SensorShape { kCylinderCap, kCone, kSpline };
// "cylinder" (or "cylinder-cap"), "cone", "spline"; throws std::invalid_argument listing the
// accepted names.
SensorShape ParseSensorShape(std::string_view name);
std::string_view SensorShapeName(SensorShape shape);  // "cylinder", "cone", "spline"

// Everything needed to build a built-in sensor (for CLIs and configs).
struct SensorShapeOptions {
  SensorShape shape = SensorShape::kCylinderCap;
  CylinderCapOptions cylinder;
  ConeOptions cone;
  SplineOptions spline;
  TessellationOptions tessellation;
  void Check() const;  // checks the selected shape's options and the tessellation
};
std::shared_ptr<const RevolutionProfile> MakeProfile(const SensorShapeOptions& options);
TriangleMesh MakeSensorMesh(const SensorShapeOptions& options);

// LED fins: two thin boards in the sensor's xz and yz planes, crossing at the axis. Each is a
// closed slab of `thickness` (across its plane). Its outline follows the sensor's inner wall:
// the profile curve offset inward along its normal by `inset`, clipped to bottom_z <= z <= top_z;
// at the top the two half-outlines meet on the axis (or are cut flat at top_z).
struct FinOptions {
  // false: a sensor without fins (MakeFin / MakeFins give empty meshes, FinHalfWidthAt 0).
  bool enabled = true;
  double thickness = 0.45;  // mm, board plus LEDs
  double inset = 1.5;       // mm, from the outer surface to the board edge (gel + shell)
  double bottom_z = 0.0;    // mm
  double top_z = 1e9;       // mm; above the natural top it has no effect
  int samples = 96;         // outline points along each half-outline
  void Check() const;
};

enum class FinPlane { kXZ, kYZ };

// One fin (closed slab, CCW outward, exact shared vertices). Throws std::invalid_argument if the
// inset is too large for the profile (the offset outline folds over or is empty).
TriangleMesh MakeFin(const FinOptions& options, const RevolutionProfile& profile, FinPlane plane);
// Both fins in one mesh: triangles [0, n/2) are the xz fin (red LEDs), [n/2, n) the yz fin
// (green LEDs). The two slabs intersect each other along the axis (two closed components).
TriangleMesh MakeFins(const FinOptions& options, const RevolutionProfile& profile);

class Bvh;
// A spline profile inscribed in an arbitrary finger mesh around the +z axis (sensor frame):
// at `samples` heights (denser toward the tip) the smallest radius over 16 azimuths, closed
// with the axis hit at the top. For the fins of a sensor given as a mesh. Throws
// std::invalid_argument if the axis or a wall ray misses the mesh (naming the height).
SplineOptions FitInscribedProfile(const Bvh& mesh, int samples = 24);
// The height (mm) where the inner-wall outline (the profile offset inward by options.inset,
// ignoring top_z) first folds over or meets the axis below the tip, +inf when it never does:
// fins must be cut (top_z) below it. Throws as FinOptions::Check().
double FinFoldZ(const FinOptions& options, const RevolutionProfile& profile);
// Half-width (mm) of a fin at height z: the inner-wall outline's radius there, or 0 outside
// [bottom_z, top_z] or the outline's span. About 100 profile evaluations (a few microseconds);
// it does not repeat MakeFin's fold check.
double FinHalfWidthAt(const FinOptions& options, const RevolutionProfile& profile, double z);

}  // namespace gs360
