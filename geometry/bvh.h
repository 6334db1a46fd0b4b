#pragma once
// Bounding volume hierarchy over a triangle mesh: closest-hit and any-hit ray casting.
//
// Build: binned SAH (surface area heuristic) binary tree collapsed into 4-wide float nodes (boxes
// rounded outward and padded so they always contain the double-precision triangles), traversed
// front to back with 4-lane vector box tests. Each leaf stores its distinct vertices as exact
// double copies; the watertight ray/triangle test (Woop, Benthin, Wald 2013) runs on them in
// double precision, so a ray never slips between two triangles sharing an edge and t is exact to
// double rounding (~1e-15 relative). Results are exactly those of the double test over all
// triangles. Memory layout for incoherent rays: a node and its leaves share one contiguous block
// that is prefetched as a whole when the parent enters the node, and large arrays use 2 MiB
// transparent huge pages on Linux (madvise) against TLB misses.
//
// Determinism: Intersect returns the hit with the smallest t; among hits at exactly the same t
// the smallest triangle index wins, independent of traversal order. Results do not depend on the
// thread or on previous queries.
//
// Thread safety: the Bvh is immutable after construction; Intersect and Occluded are const and may
// be called from any number of threads at once.

#include <Eigen/Core>
#include <array>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <optional>
#include <vector>

#include "geometry/mesh.h"

namespace gs360 {

struct Ray {
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();      // mm, frame of the mesh
  Eigen::Vector3d direction = Eigen::Vector3d::UnitZ();  // unit (t is then a distance in mm)
};

struct RayHit {
  double t = 0.0;     // ray parameter: point = origin + t * direction
  int triangle = -1;  // index into the mesh's triangles
  // Barycentrics: point = (1 - b1 - b2) * v0 + b1 * v1 + b2 * v2.
  double b1 = 0.0;
  double b2 = 0.0;
  Eigen::Vector3d point = Eigen::Vector3d::Zero();
  // Smooth normal: barycentric blend of the vertex normals, unit. Never flipped toward the ray.
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();
  // Unit right-hand normal of the triangle (outward for an outward-wound mesh).
  Eigen::Vector3d geometric_normal = Eigen::Vector3d::UnitZ();
  // True when the ray hits the side the geometric normal points to (direction . n < 0).
  bool front_face = true;
};

struct BvhOptions {
  int max_leaf_size = 8;  // triangles per leaf at most (1..64)
  int sah_bins = 16;      // bins per axis for the SAH split search (2..256)
  // Relative cost of one node traversal against one triangle test, for the SAH: below
  // max_leaf_size a range is split only if traversal_cost + the children's expected triangle
  // tests beat testing all of its triangles. Larger values give fewer, fuller leaves.
  double traversal_cost = 2.0;
  void Check() const;  // throws std::invalid_argument naming the field and value
};

struct BvhStats {
  int nodes = 0;      // 4-wide nodes
  int leaves = 0;     // leaves (triangle ranges)
  int max_depth = 0;  // depth of the binary SAH tree before collapsing
  double build_seconds = 0.0;
};

class Bvh {
 public:
  // Copies the mesh (the Bvh owns its geometry; `mesh` may be destroyed afterwards). If the
  // mesh has no (or a wrong number of) vertex normals, angle-weighted ones are computed for the
  // copy. Exactly degenerate (zero-area) triangles are left out: never hit. Throws
  // std::invalid_argument for a triangle index out of range or a non-finite vertex; an empty mesh
  // is allowed (never hit).
  explicit Bvh(const TriangleMesh& mesh, const BvhOptions& options = {});

  // Closest hit with t in [t_min, t_max] (mm if direction is unit), or nullopt. Both faces of
  // each triangle are hit. The direction need not be unit (t scales with it) but must be
  // finite and non-zero; otherwise no hit.
  std::optional<RayHit> Intersect(const Ray& ray, double t_min = 0.0,
                                  double t_max = std::numeric_limits<double>::infinity()) const;
  // True if any triangle is hit with t in [t_min, t_max] (shadow / occlusion query; faster).
  bool Occluded(const Ray& ray, double t_min = 0.0,
                double t_max = std::numeric_limits<double>::infinity()) const;

  const TriangleMesh& mesh() const { return mesh_; }
  const BvhStats& stats() const { return stats_; }

 private:
  // Layout: one array of 64-byte lines (lines_). It starts with a never-hit leaf that empty node
  // slots point to, then holds one block per 4-wide node, depth first: the Node4, the records of
  // its leaf children, then those leaves' vertex normals. Entering a node prefetches its block up
  // to the normals, so the node's leaves arrive with the node: an incoherent ray waits about one
  // memory latency per tree level below the cached top, not two. Offsets are in 8-byte words
  // (int32: at most 16 GiB of tree).
  //
  // 4-wide node (128 bytes, two lines): the boxes of up to four children in structure-of-arrays
  // float form, tested with 4-lane vector instructions (near and far planes picked per ray by
  // the direction's signs). Empty slots have an inverted infinite box (never entered) and point
  // to the never-hit leaf.
  struct alignas(64) Node4 {
    float lo_x[4], lo_y[4], lo_z[4];
    float hi_x[4], hi_y[4], hi_z[4];
    // Per child: word offset into lines_ of its Node4 (inner) or leaf record (leaf).
    std::int32_t child[4];
    // Per child: leaf -> its triangles (1..64); inner -> minus the lines of its block to
    // prefetch (at most 32; the normals excluded).
    std::int32_t count[4];
  };
  // A leaf record (8-byte aligned, in its parent's block), with nt triangles and nv distinct
  // vertices, m = nv rounded up to even: a header word (byte 0: nv, byte 1: nt, bytes 4..7:
  // int32 offset in words from the record to its normals); the vertices as exact doubles in
  // structure-of-arrays form x[m], y[m], z[m] (an odd count repeats the last one); int32
  // triangle[nt] (mesh indices); uint8 corner[nt][3] (each triangle's vertices as indices into
  // the leaf's). Its normals, double[nv][3], follow the block's leaves (read for a final hit only).
  struct alignas(64) Line {
    unsigned char bytes[64];
  };
  // The closest (or any) hit found by Traverse: the leaf record and the triangle within it.
  struct HitSlot {
    std::int32_t leaf = -1;  // word offset of the leaf record, -1: no hit
    int index = 0;           // triangle within the leaf
  };

  // Allocator for the large arrays: on Linux, blocks of 1 MiB and more are 2 MiB aligned and
  // advised to use transparent huge pages (random ray access is otherwise dominated by TLB
  // misses); smaller ones are 64-byte aligned.
  static void* AllocateLarge(std::size_t bytes);
  static void DeallocateLarge(void* p, std::size_t bytes) noexcept;
  template <typename T>
  struct LargeAllocator {
    using value_type = T;
    LargeAllocator() = default;
    template <typename U>
    LargeAllocator(const LargeAllocator<U>&) {}
    T* allocate(std::size_t n) { return static_cast<T*>(AllocateLarge(n * sizeof(T))); }
    void deallocate(T* p, std::size_t n) noexcept { DeallocateLarge(p, n * sizeof(T)); }
    template <typename U>
    bool operator==(const LargeAllocator<U>&) const {
      return true;
    }
  };
  template <typename T>
  using LargeVector = std::vector<T, LargeAllocator<T>>;

  // The hit (closest, or any for kAnyHit) with t in [t_min, t_max]; writes t and barycentrics.
  template <bool kAnyHit>
  HitSlot Traverse(const Ray& ray, double t_min, double t_max, double* best_t, double* best_b1,
                   double* best_b2) const;
  struct RayTests;  // Traverse's per-ray box and triangle tests (bvh.cc)

  class Writer;  // lays the tree out in lines_ (bvh.cc)

  TriangleMesh mesh_;
  LargeVector<Line> lines_;  // see Layout above; empty for a mesh without hittable triangles
  BvhStats stats_;
};

}  // namespace gs360
