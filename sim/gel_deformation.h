#pragma once
// How the gel's outer surface deforms under the calibration ball, and the locally refined,
// displaced mesh patch the tactile camera ray-casts.
//
// Model (sensor frame, mm). Every undeformed surface point x0 with smooth outward normal n0 moves
// inward along -n0 by delta(x0):
//   p(x0)  = signed penetration of the ball along the normal line: the distance x0 must move
//            along -n0 to leave the ball (> 0 inside the ball), or minus the gap along +n0 to the
//            ball's surface (< 0 outside; extended continuously where the normal line misses
//            the ball). Outside the ball p <= r - |x0 - c|, so nothing farther than
//            r + max(w, bulge_extent) from the ball centre moves.
//   S_w(p) = 0 for p <= -w, (p + w)^2 / (4 w) for |p| < w, p for p >= w  (w = elastic_length):
//            a C1 soft version of max(0, p). Where the ball is deeper than w the gel follows the
//            ball exactly (S = p, a rigid imprint); near the edge of the imprint the gel sags
//            smoothly (S > max(0, p)) out to a gap of w, so the imprint's edge is rounded and
//            slightly larger than the rigid contact circle.
//   bulge  = bulge_fraction * D * 16 u^2 (1 - u)^2 for u = g / bulge_extent in (0, 1), else 0,
//            with g = |x0 - c| - r the distance from x0 to the ball and D the largest rigid
//            penetration: a shallow C1 outward ring around the imprint (incompressible gel pushed
//            aside), peaking at a distance bulge_extent / 2 from the ball. (g, not p: the gap
//            along the normal grows without bound where the normal line grazes the ball, which
//            would squeeze the ring into a steep step.)
//   delta  = S_w(p) - bulge.
// The calibration pipeline assumes a rigid, sharp imprint (delta = max(0, p)); the difference is
// deliberate. Rigid() gives that model (w = 0, no bulge).
//
// Patch: the gel mesh's triangles within r + max(w, bulge_extent) of the ball centre, each
// subdivided into n^2 sub-triangles on its facet (n a power of two, the smallest that makes every
// sub-edge <= max_edge in the contact zone -- triangles closer than w + 0.1 mm to the ball -- and
// <= bulge_max_edge elsewhere), vertices moved by delta along their smooth normals. Where two
// triangles with different n share an edge, the finer side's extra edge vertices are placed on
// the coarser side's displaced edge (no T-junction cracks). Coarse triangles whose refined
// vertices all have delta == 0 are left out (the background already shows them). Shading
// normals: n0 rotated by the rotation that takes the refined mesh's undisplaced vertex normal to
// its displaced one, so an undisplaced vertex keeps exactly n0 and the patch's outer border
// matches the background.

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "geometry/mesh.h"

namespace gs360 {

struct GelDeformationOptions {
  double elastic_length = 0.25;   // mm, w above
  double bulge_fraction = 0.025;  // bulge peak / maximum indentation
  double bulge_extent = 0.75;     // mm, distance from the ball at which the bulge ends
  // Longest sub-triangle edge (mm) in the contact zone (typically 0.06 mm on the default 128-
  // segment mesh, whose quads are 0.49 mm wide) and in the bulge zone.
  double max_edge = 0.09;
  double bulge_max_edge = 0.2;
  // Throws std::invalid_argument naming the field: negative or non-finite values, max_edge or
  // bulge_max_edge not in [0.005, 1] mm.
  void Check() const;
  // The rigid imprint the calibration pipeline assumes: elastic_length = 0, bulge_fraction = 0.
  static GelDeformationOptions Rigid();
};

// Pointwise model for one ball position (see the header comment).
class BallIndentation {
 public:
  BallIndentation(const Eigen::Vector3d& ball_center, double ball_radius,
                  const GelDeformationOptions& options);
  // p(x0): signed penetration along the normal (mm).
  double Penetration(const Eigen::Vector3d& x0, const Eigen::Vector3d& n0) const;
  // S_w(p) (mm, >= max(0, p)).
  double SoftDepth(double penetration) const;
  // Outward bulge (mm, >= 0) at x0, given the largest rigid penetration D.
  double Bulge(const Eigen::Vector3d& x0, double max_depth) const;
  // Surface points farther than this from the ball centre are never displaced (mm).
  double InfluenceRadius() const;

  const Eigen::Vector3d& center() const { return center_; }
  double radius() const { return radius_; }

 private:
  Eigen::Vector3d center_;
  double radius_;
  GelDeformationOptions options_;
};

// The refined, displaced patch for one ball position.
struct DisplacedPatch {
  // Displaced refined triangles (same winding as the gel mesh), with shading normals.
  TriangleMesh mesh;
  std::vector<Eigen::Vector3d> rest_vertices;  // undeformed positions, per mesh vertex
  std::vector<Eigen::Vector3d> rest_normals;   // n0, per mesh vertex
  std::vector<double> displacement;            // delta (mm, + inward), per mesh vertex
  std::vector<double> penetration;             // p (mm), per mesh vertex
  // Per patch triangle: true if any of its vertices moved.
  std::vector<std::uint8_t> triangle_displaced;
  // Gel-mesh triangles the patch replaces (sorted), and per gel triangle a flag.
  std::vector<int> replaced_triangles;
  std::vector<std::uint8_t> replaced;  // size = gel triangle count (empty if nothing replaced)
  double max_depth = 0.0;              // largest rigid penetration D (mm)
  // The undeformed surface point closest to the ball centre, and its smooth outward normal.
  Eigen::Vector3d contact_point = Eigen::Vector3d::Zero();
  Eigen::Vector3d contact_normal = Eigen::Vector3d::UnitZ();
  double max_displacement = 0.0;  // largest delta (mm)
  int max_subdivisions = 0;       // largest n used

  bool Empty() const { return mesh.triangles.empty(); }
};

// Builds patches against one gel mesh (kept by reference: it must outlive the builder).
// Immutable after construction; Build() is const and thread-safe.
class GelPatchBuilder {
 public:
  // The mesh needs vertex normals (outward, unit). Throws std::invalid_argument if it has none or
  // for invalid options.
  GelPatchBuilder(const TriangleMesh& gel_mesh, const GelDeformationOptions& options);

  // Gel triangles with a point closer than `radius` to `center` (sorted indices).
  std::vector<int> TrianglesNear(const Eigen::Vector3d& center, double radius) const;

  // The displaced patch for the ball (sensor frame). Empty when the ball does not deform the gel.
  DisplacedPatch Build(const Eigen::Vector3d& ball_center, double ball_radius) const;

  const GelDeformationOptions& options() const { return options_; }

 private:
  const TriangleMesh& mesh_;
  GelDeformationOptions options_;
  // Uniform grid over the mesh bounds; each cell lists the triangles whose box overlaps it.
  Eigen::Vector3d grid_origin_;
  double cell_ = 1.0;
  Eigen::Vector3i grid_dims_;
  std::vector<int> cell_start_;  // CSR offsets, size cells + 1
  std::vector<int> cell_items_;
};

}  // namespace gs360
