#pragma once
// Area-uniform sampling of triangle meshes: white (independent uniform) and blue-noise
// (well-spaced) point sets, optionally restricted to a region given by a predicate.
//
// Blue noise: weighted sample elimination (Yuksel 2015, "Sample Elimination for Generating
// Poisson Disk Sample Sets"): draw candidate_factor * count area-uniform candidates in the
// region, then repeatedly remove the candidate with the largest weight
//   w_i = sum_j (1 - d_ij / (2 r_max))^alpha  over neighbours with d_ij < 2 r_max,
// r_max = sqrt(A / (2 sqrt(3) N)) (A = region area, N = count; 2 r_max is the spacing of a
// hexagonal packing of N points on A), until `count` remain. Neighbours come from a spatial hash
// grid. Distances are Euclidean in 3D, which equals the geodesic distance to second order when
// 2 r_max is small against the surface's radius of curvature (the sensor's walls).
//
// Determinism: for a given mesh, options and predicate the result is identical on every run and
// platform (own 64-bit generator and integer-to-double conversion, no std distributions,
// deterministic tie-breaking).
//
// Units: mm, frame of the mesh.

#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <vector>

#include "geometry/mesh.h"

namespace gs360 {

struct SurfaceSample {
  Eigen::Vector3d point = Eigen::Vector3d::Zero();
  // Smooth normal: barycentric blend of the mesh's vertex normals (or the face normal if the
  // mesh has none), unit.
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();
  int triangle = -1;  // index into the mesh's triangles
  // Barycentrics: point = (1 - b1 - b2) * v0 + b1 * v1 + b2 * v2.
  double b1 = 0.0;
  double b2 = 0.0;
};

// Optional region of interest: a sample is kept only if the predicate returns true. Called from
// the calling thread only.
using SamplePredicate = std::function<bool(const SurfaceSample&)>;

// `count` independent area-uniform samples of the mesh (those rejected by `keep` are redrawn).
// Returns fewer than count only when the region is too small to be hit in max(1000, 200 * count)
// draws. Throws std::invalid_argument for count < 0 or a mesh with zero area.
std::vector<SurfaceSample> SampleUniform(const TriangleMesh& mesh, int count, std::uint64_t seed,
                                         const SamplePredicate& keep = {});

struct BlueNoiseOptions {
  int count = 10000;            // samples wanted (>= 0)
  std::uint64_t seed = 1;       // candidate generator seed
  double candidate_factor = 5;  // candidates per sample (>= 1; Yuksel uses 5)
  double alpha = 8.0;           // weight exponent (> 0)
  // Weight limiting (Yuksel sec. 3.2): distances below d_min = beta * (1 - (N/M)^gamma) * 2 r_max
  // (M = candidates) count as d_min, so dense candidate clusters do not dominate. beta = 0
  // disables it.
  double beta = 0.65;
  double gamma = 1.5;
  void Check() const;  // throws std::invalid_argument naming the field and value
};

// Blue-noise samples of the mesh (or of the region `keep` accepts). Returns options.count samples,
// or fewer only when the region is too small to yield that many candidates (see SampleUniform);
// the result is in candidate-draw order. Throws std::invalid_argument for invalid options or a
// mesh with zero area. Single-threaded; its speed: bench/bench_sampling, figures in
// docs/benchmarks.md ("Geometry").
std::vector<SurfaceSample> SampleBlueNoise(const TriangleMesh& mesh,
                                           const BlueNoiseOptions& options = {},
                                           const SamplePredicate& keep = {});

// 2 * sqrt(area / (2 sqrt(3) count)): the nearest-neighbour distance of `count` points in a
// hexagonal packing of `area` (mm^2) -- the ideal blue-noise spacing (mm). 0 if count <= 0.
double IdealBlueNoiseSpacing(double area, int count);

// Minimum pairwise Euclidean distance (mm) of the samples (grid accelerated); +inf for < 2.
double MinimumSpacing(const std::vector<SurfaceSample>& samples);

// A progressive order of `points`: `first`, then repeatedly the point farthest (Euclidean) from
// all chosen so far, ties to the lower index (Gonzalez's farthest-point traversal). Every prefix
// of k points then covers the set within twice the best possible radius for k centres, so a run
// stopped after any prefix has probed the whole surface evenly, only more sparsely. Returns a
// permutation of 0..n-1 (empty for no points). O(n^2) time, O(n) memory. Throws
// std::invalid_argument when `first` is out of range for a non-empty set.
std::vector<int> FarthestPointOrder(const std::vector<Eigen::Vector3d>& points, int first = 0);

// The covering radius of a prefix: the largest distance (mm) from any of `points` to the nearest
// of its first `k` entries in `order` (k in 1..n). O(n k). Throws std::invalid_argument for k or
// order out of range.
double PrefixCoveringRadius(const std::vector<Eigen::Vector3d>& points,
                            const std::vector<int>& order, int k);

}  // namespace gs360
