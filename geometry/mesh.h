#pragma once
// Triangle meshes: the in-memory type, import (STL ASCII/binary, OBJ, PLY through assimp), binary
// and ASCII writers, and validation / repair.
//
// Units: millimetres. Frame: whatever frame the vertices are in; sensor meshes live in the sensor
// frame (origin at the centre of the base plane, +z along the finger axis toward the tip), and a
// sensor surface is closed everywhere except at its base opening on the plane z = 0.
//
// Winding: counter-clockwise seen from outside, so the right-hand normal
// (v1 - v0) x (v2 - v0) of a triangle points outward.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <filesystem>
#include <stdexcept>
#include <string>
#include <vector>

#include "geometry/rigid3.h"

namespace gs360 {

// Set-up / I/O errors of mesh loading and writing. The message names the file and the problem.
class MeshError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct TriangleMesh {
  std::vector<Eigen::Vector3d> vertices;   // mm
  std::vector<Eigen::Vector3i> triangles;  // indices into `vertices`, CCW seen from outside
  // Per vertex, unit, outward (angle-weighted average of the incident face normals unless a
  // generator set exact ones). Either empty or vertices.size() long.
  std::vector<Eigen::Vector3d> normals;

  int NumVertices() const { return static_cast<int>(vertices.size()); }
  int NumTriangles() const { return static_cast<int>(triangles.size()); }
  bool Empty() const { return triangles.empty(); }
  bool HasNormals() const { return !normals.empty() && normals.size() == vertices.size(); }

  // Axis-aligned bounds of the vertices (an empty box when there are none).
  Eigen::AlignedBox3d Bounds() const;
  // Total surface area (mm^2).
  double Area() const;
  // Area (mm^2) and unit right-hand normal of triangle `t` (zero vector if degenerate).
  double TriangleArea(int t) const;
  Eigen::Vector3d TriangleNormal(int t) const;
  // Integral of (z - base_z) * n_z dA over the surface (mm^3). For a closed, outward-oriented
  // surface it is the enclosed volume; for a surface open only at the plane z = base_z it is the
  // volume closed by that plane (the missing base disc contributes nothing). Negative = inward.
  double SignedVolume(double base_z = 0.0) const;

  // Recomputes `normals` as angle-weighted averages of incident face normals (unit; a vertex
  // with no non-degenerate incident face gets (0, 0, 1)).
  void ComputeVertexNormals();
  // Applies b_from_a to vertices and rotates normals (the mesh moves from frame a to frame b).
  void Transform(const Rigid3d& b_from_a);
  // Appends another mesh (indices shifted). Normals are kept only if both meshes have them.
  void Append(const TriangleMesh& other);

  // Content hash of vertices, triangles and normals (exact bit patterns, -0.0 == 0.0): identical
  // geometry gives an identical hash, any change to a coordinate or index changes it.
  std::uint64_t Hash() const;
  std::string HashHex() const;  // 16 hex digits of Hash()
};

struct MeshRepairOptions {
  // Vertices closer than this (mm) are merged into one (the lowest index wins). 0 = exact only.
  double weld_tolerance = 1e-5;
  // Triangles with area below this (mm^2) or a repeated vertex are degenerate.
  double degenerate_area = 1e-12;
  // So are slivers: triangles whose height over their longest edge is below this (mm), such as
  // three collinear vertices that a file's float32 coordinates no longer keep exactly on a line.
  double degenerate_height = 1e-5;
  // The sensor's base plane: boundary edges with both ends within base_tolerance (mm) of
  // z = base_z are the expected base opening; all other boundary edges are holes.
  double base_z = 0.0;
  double base_tolerance = 1e-4;
  // What to fix. Each fix is counted and described in the report.
  bool remove_nonfinite = true;     // drop triangles that use NaN/Inf vertices
  bool remove_degenerate = true;    // drop degenerate triangles
  bool remove_duplicates = true;    // drop repeated triangles (same 3 vertices, either winding)
  bool weld = true;                 // merge coincident vertices (STL has none shared)
  bool make_consistent = true;      // flip triangles to agree with their neighbours' winding
  bool orient_outward = true;       // flip whole components whose SignedVolume is negative
  bool remove_unreferenced = true;  // drop vertices no triangle uses
  bool recompute_normals = true;    // recompute normals if anything changed or none are present

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

// What ValidateAndRepair found and did. Counts refer to the mesh as given, before repair.
struct MeshReport {
  int input_vertices = 0;
  int input_triangles = 0;
  int nonfinite_vertices = 0;       // NaN or Inf coordinates
  int nonfinite_triangles = 0;      // triangles using them (removed if remove_nonfinite)
  int invalid_index_triangles = 0;  // index out of range (always removed)
  int welded_vertices = 0;          // vertices merged into another
  int unreferenced_vertices = 0;    // removed (after welding)
  int degenerate_triangles = 0;     // removed if remove_degenerate
  int duplicate_triangles = 0;      // removed if remove_duplicates
  int flipped_triangles = 0;        // flipped for consistent winding
  int inconsistent_edges = 0;       // manifold edges left with conflicting winding
  int reoriented_components = 0;    // components flipped to face outward
  int components = 0;               // edge-connected components after repair
  int boundary_edges = 0;           // edges with one triangle, after repair
  int boundary_edges_on_base = 0;   // ... of which on the base plane (expected)
  int boundary_edges_off_base = 0;  // ... of which elsewhere: holes (not fixable)
  int non_manifold_edges = 0;       // edges with 3+ triangles (not fixable)
  double signed_volume = 0.0;       // SignedVolume(base_z) after repair, mm^3
  int output_vertices = 0;
  int output_triangles = 0;

  // Human-readable lines: problems found (with counts) and what was fixed.
  std::vector<std::string> problems;
  std::vector<std::string> fixes;

  // Closed except at the base plane, manifold and consistently wound.
  bool ClosedExceptBase() const {
    return boundary_edges_off_base == 0 && non_manifold_edges == 0 && inconsistent_edges == 0;
  }
  // ClosedExceptBase(), no NaN/Inf left, at least one triangle, and facing outward (positive
  // signed volume).
  bool Ok() const;
  // Multi-line text: counts, problems and fixes.
  std::string Summary() const;
};

// Validates `mesh` and repairs what can be repaired safely (see MeshRepairOptions). Usable on any
// mesh, built-in shapes too. Never throws for mesh content (only for invalid options): problems
// go into the report.
MeshReport ValidateAndRepair(TriangleMesh& mesh, const MeshRepairOptions& options = {});

// The flat base of a closed sensor solid (a CAD export of the elastomer, base included). The
// camera looks up through the base, so the sensor's surface is the solid without it. Units: mm
// (apply a file's scale first).
//
// The base plane is z = z_min, the height of the mesh's lowest vertex, when |z_min| <= max_offset
// (a base a little off z = 0); otherwise the mesh has no base on the sensor's base plane and has
// none removed. Base faces: the triangles with all three vertices within `flatness` of z_min and
// an outward normal within max_tilt_rad of -z (a face the camera, below the base, would see
// from outside).
struct BasePlaneOptions {
  double max_offset = 0.5;                  // mm, >= 0
  double flatness = 0.01;                   // mm, >= 0
  double max_tilt_rad = 0.174532925199433;  // 10 deg, in [0, pi/2)
  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

// Removes the base faces (BasePlaneOptions) and the vertices that only they used, and recomputes
// the vertex normals when any face goes (the rim's no longer lean toward -z). Returns the
// number of triangles removed. Throws only for invalid options.
int RemoveBaseFaces(TriangleMesh& mesh, const BasePlaneOptions& options = {});

struct MeshLoadOptions {
  // File units -> mm (e.g. 1000 for a file in metres). STL has no units: mm is assumed.
  double scale = 1.0;
  // Applied after scaling: places the file's geometry in the sensor frame.
  Rigid3d sensor_from_file = Rigid3d::Identity();
  MeshRepairOptions repair;
  // Run ValidateAndRepair after loading (always done when `reject_*` is set).
  bool validate = true;
  // Throw MeshError when the file has NaN/Inf vertices (instead of dropping their triangles).
  bool reject_nonfinite = true;
  // Throw MeshError when, after repair, the mesh is not closed except at the base (holes away
  // from the base plane, non-manifold or inconsistent edges).
  bool reject_open = false;
  // The importer runs in a child process (a crash in it is an error, not the end of the caller);
  // it is killed after this many seconds.
  double import_timeout_s = 60.0;

  void Check() const;
};

// Loads a mesh through assimp (STL ASCII/binary, OBJ, PLY; other assimp formats work too). All
// meshes of the file are merged with their node transforms; points and lines are dropped, polygons
// split into triangle fans (right for convex faces). Vertex normals are computed from the
// geometry (file normals are ignored: STL's are per face). Coordinates pass through float32
// (assimp's ai_real): ~2e-6 mm at 30 mm. Throws MeshError naming the file for: missing or
// unreadable file, an assimp parse error, a crash of assimp or its running past
// import_timeout_s (it reads the file in a child process), no triangles, NaN/Inf vertices (with
// counts, if reject_nonfinite), an open mesh (if reject_open). `report` (optional) receives the
// validation report.
TriangleMesh LoadMesh(const std::filesystem::path& path, const MeshLoadOptions& options = {},
                      MeshReport* report = nullptr);

// Writers, through assimp's exporters (for exporting built-in shapes, and tests). Throw
// MeshError naming the file when it cannot be written. Coordinates are written as float32; STL
// has face normals and no shared vertices, OBJ (no .mtl) and PLY (ASCII) keep shared vertices
// and the vertex normals when the mesh has them.
void WriteStlBinary(const std::filesystem::path& path, const TriangleMesh& mesh);
void WriteStlAscii(const std::filesystem::path& path, const TriangleMesh& mesh);
void WriteObj(const std::filesystem::path& path, const TriangleMesh& mesh);
void WritePlyAscii(const std::filesystem::path& path, const TriangleMesh& mesh);
// By extension: .stl (binary), .obj, .ply. Throws MeshError for any other extension.
void WriteMesh(const std::filesystem::path& path, const TriangleMesh& mesh);

}  // namespace gs360
