#include "geometry/bvh.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <new>
#include <stdexcept>
#include <string>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif
#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace gs360 {
namespace {

// Beyond this depth the build switches to median splits, bounding the binary depth to
// kMedianDepth + log2(n) <= 95. A 4-wide node spans at least one binary level and pushes at most
// 3 entries, so the traversal stack never exceeds 3 * 95 < kStackSize.
constexpr int kMedianDepth = 64;
constexpr int kStackSize = 320;

struct Box {
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d hi = Eigen::Vector3d::Constant(-std::numeric_limits<double>::infinity());
  void Extend(const Eigen::Vector3d& p) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  void Extend(const Box& b) {
    lo = lo.cwiseMin(b.lo);
    hi = hi.cwiseMax(b.hi);
  }
  bool Valid() const { return lo.x() <= hi.x(); }
  double HalfArea() const {
    if (!Valid()) return 0.0;
    const Eigen::Vector3d e = hi - lo;
    return e.x() * e.y() + e.y() * e.z() + e.z() * e.x();
  }
};

// 4-lane float vectors (GCC/Clang vector extensions: SSE on x86, NEON on ARM).
typedef float F4 __attribute__((vector_size(16)));
typedef std::int32_t I4 __attribute__((vector_size(16)));

inline F4 Splat(float v) {
  return F4{v, v, v, v};
}
inline F4 Load(const float* p) {
  F4 v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}
inline F4 Min(F4 a, F4 b) {
  return a < b ? a : b;
}
inline F4 Max(F4 a, F4 b) {
  return a > b ? a : b;
}
inline F4 Abs(F4 a) {
  return a < 0.0f ? -a : a;
}
// Bit k set when lane k of the comparison result `m` (all ones / all zeros) is set.
inline unsigned MoveMask(I4 m) {
#if defined(__SSE2__)
  return static_cast<unsigned>(_mm_movemask_ps(reinterpret_cast<__m128>(m)));
#else
  return (m[0] ? 1u : 0u) | (m[1] ? 2u : 0u) | (m[2] ? 4u : 0u) | (m[3] ? 8u : 0u);
#endif
}

float RoundDown(double v) {
  float f = static_cast<float>(v);
  if (static_cast<double>(f) > v) f = std::nextafter(f, -std::numeric_limits<float>::infinity());
  return f;
}

float RoundUp(double v) {
  float f = static_cast<float>(v);
  if (static_cast<double>(f) < v) f = std::nextafter(f, std::numeric_limits<float>::infinity());
  return f;
}

struct Builder {
  const BvhOptions& options;
  std::vector<Box> tri_box;
  std::vector<Eigen::Vector3d> centroid;
  std::vector<std::int32_t>& order;
  int max_depth = 0;

  struct BuildNode {
    Box box;
    std::int32_t index = 0;  // leaf: first triangle; inner: right child
    std::int32_t count = 0;
    std::int32_t left = -1;  // inner: left child
  };
  std::vector<BuildNode> nodes;

  int Build(int begin, int end, int depth) {
    max_depth = std::max(max_depth, depth);
    const int node = static_cast<int>(nodes.size());
    nodes.emplace_back();
    Box box, cbox;
    for (int i = begin; i < end; ++i) {
      box.Extend(tri_box[order[i]]);
      cbox.Extend(centroid[order[i]]);
    }
    nodes[node].box = box;
    const int count = end - begin;
    // Leaves hold at most max_leaf_size triangles; below that the SAH decides whether a split
    // (traversal_cost + expected triangle tests of the children) beats testing all of them.
    const bool may_be_leaf = count <= options.max_leaf_size;
    int mid = -1;
    if (count > 1 && depth < kMedianDepth) mid = SahSplit(begin, end, box, cbox, may_be_leaf);
    if (may_be_leaf && (mid <= begin || mid >= end)) {
      nodes[node].index = begin;
      nodes[node].count = count;
      return node;
    }
    if (mid <= begin || mid >= end) {
      // Median split along the widest centroid axis (or by index when all centroids coincide).
      int axis = 0;
      const Eigen::Vector3d ext = cbox.hi - cbox.lo;
      if (ext.y() > ext[axis]) axis = 1;
      if (ext.z() > ext[axis]) axis = 2;
      mid = begin + count / 2;
      if (ext[axis] > 0.0) {
        std::nth_element(order.begin() + begin, order.begin() + mid, order.begin() + end,
                         [&](std::int32_t a, std::int32_t b) {
                           if (centroid[a][axis] != centroid[b][axis])
                             return centroid[a][axis] < centroid[b][axis];
                           return a < b;
                         });
      }
    }
    const int left = Build(begin, mid, depth + 1);
    const int right = Build(mid, end, depth + 1);
    nodes[node].left = left;
    nodes[node].index = right;
    nodes[node].count = 0;
    return node;
  }

  // Binned SAH; returns the partition point, or -1 when no axis can be split.
  // With `leaf_allowed`, returns -1 unless the split is cheaper than a leaf.
  int SahSplit(int begin, int end, const Box& box, const Box& cbox, bool leaf_allowed) {
    const int bins = options.sah_bins;
    double best_cost = std::numeric_limits<double>::infinity();
    int best_axis = -1, best_bin = -1;
    std::vector<Box> bin_box(bins);
    std::vector<int> bin_count(bins);
    std::vector<double> right_area(bins);
    std::vector<int> right_count(bins);
    for (int axis = 0; axis < 3; ++axis) {
      const double lo = cbox.lo[axis], extent = cbox.hi[axis] - cbox.lo[axis];
      if (!(extent > 0.0)) continue;
      const double scale = bins / extent;
      std::fill(bin_box.begin(), bin_box.end(), Box());
      std::fill(bin_count.begin(), bin_count.end(), 0);
      for (int i = begin; i < end; ++i) {
        const int t = order[i];
        const int b = std::min(bins - 1, static_cast<int>((centroid[t][axis] - lo) * scale));
        bin_box[b].Extend(tri_box[t]);
        ++bin_count[b];
      }
      Box acc;
      int n = 0;
      for (int b = bins - 1; b > 0; --b) {
        acc.Extend(bin_box[b]);
        n += bin_count[b];
        right_area[b] = acc.HalfArea();
        right_count[b] = n;
      }
      acc = Box();
      n = 0;
      for (int b = 0; b + 1 < bins; ++b) {
        acc.Extend(bin_box[b]);
        n += bin_count[b];
        if (n == 0 || right_count[b + 1] == 0) continue;
        const double cost = acc.HalfArea() * n + right_area[b + 1] * right_count[b + 1];
        if (cost < best_cost) {
          best_cost = cost;
          best_axis = axis;
          best_bin = b;
        }
      }
    }
    if (best_axis < 0) return -1;
    const double parent = box.HalfArea();
    const double split_cost =
        options.traversal_cost + (parent > 0.0 ? best_cost / parent : end - begin);
    if (leaf_allowed && split_cost >= end - begin) return -1;
    const double lo = cbox.lo[best_axis];
    const double scale = bins / (cbox.hi[best_axis] - lo);
    const auto it =
        std::stable_partition(order.begin() + begin, order.begin() + end, [&](std::int32_t t) {
          const int b = std::min(bins - 1, static_cast<int>((centroid[t][best_axis] - lo) * scale));
          return b <= best_bin;
        });
    return static_cast<int>(it - order.begin());
  }
};

// Per-ray constants of the watertight test (Woop, Benthin, Wald 2013), in double.
struct WatertightRay {
  Eigen::Vector3d origin;
  int kx, ky, kz;
  double sx, sy, sz;

  explicit WatertightRay(const Ray& ray) : origin(ray.origin) {
    const Eigen::Vector3d& d = ray.direction;
    kz = 0;
    if (std::abs(d.y()) > std::abs(d[kz])) kz = 1;
    if (std::abs(d.z()) > std::abs(d[kz])) kz = 2;
    kx = (kz + 1) % 3;
    ky = (kx + 1) % 3;
    if (d[kz] < 0.0) std::swap(kx, ky);
    sx = d[kx] / d[kz];
    sy = d[ky] / d[kz];
    sz = 1.0 / d[kz];
  }

  // On a hit with t in [t_min, t_max] writes t and the barycentrics of v1, v2.
  bool Intersect(const Eigen::Vector3d& v0, const Eigen::Vector3d& v1, const Eigen::Vector3d& v2,
                 double t_min, double t_max, double* t, double* b1, double* b2) const {
    const Eigen::Vector3d a = v0 - origin, b = v1 - origin, c = v2 - origin;
    const double ax = a[kx] - sx * a[kz], ay = a[ky] - sy * a[kz];
    const double bx = b[kx] - sx * b[kz], by = b[ky] - sy * b[kz];
    const double cx = c[kx] - sx * c[kz], cy = c[ky] - sy * c[kz];
    const double u = cx * by - cy * bx;
    const double v = ax * cy - ay * cx;
    const double w = bx * ay - by * ax;
    if ((u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0)) return false;
    const double det = u + v + w;
    if (det == 0.0) return false;
    const double az = sz * a[kz], bz = sz * b[kz], cz = sz * c[kz];
    const double tt = (u * az + v * bz + w * cz) / det;
    if (!(tt >= t_min && tt <= t_max)) return false;
    *t = tt;
    *b1 = v / det;
    *b2 = w / det;
    return true;
  }
};

}  // namespace

namespace {
constexpr std::size_t kHugePage = std::size_t{1} << 21;
constexpr std::size_t kLargeBlock = std::size_t{1} << 20;
constexpr std::size_t kSmallAlignment = 64;
}  // namespace

void* Bvh::AllocateLarge(std::size_t bytes) {
#if defined(__linux__)
  if (bytes >= kLargeBlock) {
    const std::size_t size = (bytes + kHugePage - 1) / kHugePage * kHugePage;
    void* p = std::aligned_alloc(kHugePage, size);
    if (p == nullptr) throw std::bad_alloc();
    madvise(p, size, MADV_HUGEPAGE);  // a hint: failure only costs speed
    return p;
  }
#endif
  return ::operator new(bytes, std::align_val_t(kSmallAlignment));
}

void Bvh::DeallocateLarge(void* p, std::size_t bytes) noexcept {
#if defined(__linux__)
  if (bytes >= kLargeBlock) {
    std::free(p);
    return;
  }
#endif
  ::operator delete(p, std::align_val_t(kSmallAlignment));
}

void BvhOptions::Check() const {
  if (max_leaf_size < 1 || max_leaf_size > 64) {
    throw std::invalid_argument("BvhOptions.max_leaf_size must be in [1, 64], got " +
                                std::to_string(max_leaf_size));
  }
  if (sah_bins < 2 || sah_bins > 256) {
    throw std::invalid_argument("BvhOptions.sah_bins must be in [2, 256], got " +
                                std::to_string(sah_bins));
  }
  if (!(traversal_cost >= 0.0) || !std::isfinite(traversal_cost)) {
    throw std::invalid_argument("BvhOptions.traversal_cost must be finite and >= 0, got " +
                                std::to_string(traversal_cost));
  }
}

Bvh::Bvh(const TriangleMesh& mesh, const BvhOptions& options) : mesh_(mesh) {
  options.Check();
  const auto start = std::chrono::steady_clock::now();
  const int nv = mesh_.NumVertices();
  for (int i = 0; i < nv; ++i) {
    if (!mesh_.vertices[i].allFinite()) {
      throw std::invalid_argument("Bvh: vertex " + std::to_string(i) + " is not finite");
    }
  }
  const int nt = mesh_.NumTriangles();
  for (int t = 0; t < nt; ++t) {
    const Eigen::Vector3i& f = mesh_.triangles[t];
    if (f.minCoeff() < 0 || f.maxCoeff() >= nv) {
      throw std::invalid_argument("Bvh: triangle " + std::to_string(t) +
                                  " has a vertex index out of range [0, " + std::to_string(nv) +
                                  ")");
    }
  }
  if (!mesh_.HasNormals()) mesh_.ComputeVertexNormals();
  if (nt == 0) {
    stats_.build_seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return;
  }

  Box scene;
  for (const auto& v : mesh_.vertices) scene.Extend(v);
  const double diag = (scene.hi - scene.lo).norm();
  const double max_abs = std::max(scene.lo.cwiseAbs().maxCoeff(), scene.hi.cwiseAbs().maxCoeff());
  // Pads every float box against the rounding of the float ray origin and inverse direction.
  const double pad = 1e-5 * diag + 1e-6 * max_abs + 1e-30;

  // Exactly degenerate triangles (zero cross product) can never be hit: leave them out.
  std::vector<std::int32_t> order;  // binary-tree leaf order -> triangle index
  order.reserve(nt);
  for (int t = 0; t < nt; ++t) {
    const Eigen::Vector3i& f = mesh_.triangles[t];
    const Eigen::Vector3d c = (mesh_.vertices[f[1]] - mesh_.vertices[f[0]])
                                  .cross(mesh_.vertices[f[2]] - mesh_.vertices[f[0]]);
    if (c.squaredNorm() > 0.0) order.push_back(t);
  }
  const int n = static_cast<int>(order.size());
  if (n == 0) {
    stats_.build_seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return;
  }
  max_abs_coordinate_ = max_abs;
  Builder builder{options, {}, {}, order};
  builder.tri_box.resize(nt);
  builder.centroid.resize(nt);
  for (int t = 0; t < nt; ++t) {
    Box b;
    for (int k = 0; k < 3; ++k) b.Extend(mesh_.vertices[mesh_.triangles[t][k]]);
    builder.tri_box[t] = b;
    builder.centroid[t] = 0.5 * (b.lo + b.hi);
  }
  builder.nodes.reserve(2 * n / std::max(1, options.max_leaf_size) + 1);
  builder.Build(0, n, 0);

  // Appends the triangles order[begin, end) as packs of four; returns the first pack.
  std::vector<std::int32_t> record_of(nv, -1);  // mesh vertex -> vertices_ index
  auto add_leaf = [&](int begin, int end) {
    const int first = static_cast<int>(packs_.size());
    for (int p = begin; p < end; p += 4) {
      TrianglePack4 pack;
      for (int lane = 0; lane < 4; ++lane) {
        // Padding lanes repeat the first triangle (masked out by the leaf's count).
        const int t = order[p + lane < end ? p + lane : p];
        triangle_.push_back(p + lane < end ? t : -1);
        for (int j = 0; j < 3; ++j) {
          const int mv = mesh_.triangles[t][j];
          if (record_of[mv] < 0) {
            record_of[mv] = static_cast<std::int32_t>(vertices_.size());
            vertices_.push_back({mesh_.vertices[mv], mesh_.normals[mv]});
          }
          pack.vertex[j][lane] = record_of[mv];
          for (int a = 0; a < 3; ++a)
            pack.v[j][a][lane] = static_cast<float>(mesh_.vertices[mv][a]);
        }
      }
      packs_.push_back(pack);
    }
    return first;
  };

  // Collapse the binary tree into 4-wide nodes, depth first: each node takes up to four
  // descendants, opening the inner candidate with the largest box surface first. Leaves get
  // their packs in the same depth-first order.
  const auto& bnodes = builder.nodes;
  std::vector<std::pair<int, int>> todo = {{0, 0}};  // (binary node, Node4 index)
  nodes_.emplace_back();
  while (!todo.empty()) {
    const auto [b, n4] = todo.back();
    todo.pop_back();
    std::vector<int> slots;
    if (bnodes[b].count > 0) {
      slots.push_back(b);  // the whole tree is one leaf
    } else {
      slots = {bnodes[b].left, bnodes[b].index};
      while (slots.size() < 4) {
        int open = -1;
        double open_area = -1.0;
        for (int k = 0; k < static_cast<int>(slots.size()); ++k) {
          const auto& c = bnodes[slots[k]];
          if (c.count == 0 && c.box.HalfArea() > open_area) {
            open_area = c.box.HalfArea();
            open = k;
          }
        }
        if (open < 0) break;
        const int opened = slots[open];
        slots[open] = bnodes[opened].left;
        slots.insert(slots.begin() + open + 1, bnodes[opened].index);
      }
    }
    Node4 node{};
    for (int k = 0; k < 4; ++k) {
      if (k >= static_cast<int>(slots.size())) {
        // Empty slot: child = -1 masks it out (NaN box for good measure).
        node.lo_x[k] = node.lo_y[k] = node.lo_z[k] = std::numeric_limits<float>::quiet_NaN();
        node.hi_x[k] = node.hi_y[k] = node.hi_z[k] = std::numeric_limits<float>::quiet_NaN();
        node.child[k] = -1;
        node.count[k] = 0;
        continue;
      }
      const auto& c = bnodes[slots[k]];
      node.lo_x[k] = RoundDown(c.box.lo.x() - pad);
      node.lo_y[k] = RoundDown(c.box.lo.y() - pad);
      node.lo_z[k] = RoundDown(c.box.lo.z() - pad);
      node.hi_x[k] = RoundUp(c.box.hi.x() + pad);
      node.hi_y[k] = RoundUp(c.box.hi.y() + pad);
      node.hi_z[k] = RoundUp(c.box.hi.z() + pad);
      if (c.count > 0) {
        node.child[k] = add_leaf(c.index, c.index + c.count);
        node.count[k] = c.count;
        ++stats_.leaves;
      } else {
        node.child[k] = static_cast<std::int32_t>(nodes_.size());
        node.count[k] = 0;
        nodes_.emplace_back();
        todo.emplace_back(slots[k], node.child[k]);
      }
    }
    nodes_[n4] = node;
  }
  packs_.shrink_to_fit();
  vertices_.shrink_to_fit();
  triangle_.shrink_to_fit();
  stats_.nodes = static_cast<int>(nodes_.size());
  stats_.max_depth = builder.max_depth;
  stats_.build_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

template <bool kAnyHit>
int Bvh::Traverse(const Ray& ray, double t_min, double t_max, double* best_t, double* best_b1,
                  double* best_b2) const {
  if (packs_.empty()) return -1;
  const Eigen::Vector3d& d = ray.direction;
  if (!ray.origin.allFinite() || !d.allFinite() || d.squaredNorm() == 0.0) return -1;
  if (!(t_max >= t_min)) return -1;
  const WatertightRay wray(ray);

  float inv[3];
  for (int k = 0; k < 3; ++k) {
    double dk = d[k];
    if (std::abs(dk) < 1e-30) dk = dk < 0.0 ? -1e-30 : 1e-30;
    inv[k] = static_cast<float>(1.0 / dk);
  }
  const F4 ox = Splat(static_cast<float>(ray.origin.x()));
  const F4 oy = Splat(static_cast<float>(ray.origin.y()));
  const F4 oz = Splat(static_cast<float>(ray.origin.z()));
  const F4 ix = Splat(inv[0]), iy = Splat(inv[1]), iz = Splat(inv[2]);
  // Conservative float interval: slightly wider than [t_min, best].
  constexpr float kGrow = 1.0f + 4.0f * std::numeric_limits<float>::epsilon();
  float tmin_f = static_cast<float>(t_min);
  tmin_f = tmin_f > 0.0f ? tmin_f / kGrow : tmin_f * kGrow;
  const F4 tmin4 = Splat(tmin_f);
  const F4 grow4 = Splat(kGrow);
  auto to_tmax_f = [](double t) {
    return t >= static_cast<double>(std::numeric_limits<float>::max())
               ? std::numeric_limits<float>::infinity()
               : static_cast<float>(t) * kGrow;
  };

  // Float pre-test: the watertight test's edge functions u, v, w in float, with the same axis
  // permutation and shear. With e = 2^-24, L = max |vertex coordinate| + max |origin
  // coordinate|: each float relative coordinate is within 2.01 e L of the exact one (rounding
  // of vertex, origin, difference), each sheared one within D = 8.1 e L (plus the shear's own
  // rounding, |sx|, |sy| <= 1), so with P = the largest |sheared coordinate| of the triangle
  // each float edge function is within 4 P D + 2 D^2 + 5 e P^2 of the exact one. The double
  // test's own error is ~2^-29 of that. A lane is rejected only when one edge function is below
  // -E and another above +E with E twice that bound: the double test then surely sees opposite
  // signs and rejects too, so results are exactly those of the double test alone. Beyond
  // L = 1e15 (float overflow of P^2) the pre-test is off.
  const double max_abs_origin = ray.origin.cwiseAbs().maxCoeff();
  const double big_l = max_abs_coordinate_ + max_abs_origin;
  const bool pretest = big_l <= 1e15;
  constexpr double kE = 1.0 / 16777216.0;  // 2^-24
  const float dd = static_cast<float>(10.0 * kE * big_l + 1e-37);
  const F4 e_lin = Splat(pretest ? 8.0f * dd : std::numeric_limits<float>::infinity());
  const F4 e_quad = Splat(static_cast<float>(10.0 * kE));
  const F4 e_const = Splat(4.0f * dd * dd + 1e-37f);
  const int kx = wray.kx, ky = wray.ky, kz = wray.kz;
  const F4 ro_x = Splat(static_cast<float>(ray.origin[kx]));
  const F4 ro_y = Splat(static_cast<float>(ray.origin[ky]));
  const F4 ro_z = Splat(static_cast<float>(ray.origin[kz]));
  const F4 sx4 = Splat(static_cast<float>(wray.sx));
  const F4 sy4 = Splat(static_cast<float>(wray.sy));
  static constexpr I4 kLane = {0, 1, 2, 3};

  double best = t_max;
  float best_f = to_tmax_f(best);
  int best_i = -1;

  struct Entry {
    std::int32_t child;
    std::int32_t count;
    float t;
  };
  Entry stack[kStackSize];
  int sp = 0;
  Entry cur{0, 0, 0.0f};  // the root
  while (true) {
    if (cur.count > 0) {
      const int last = cur.child + (cur.count - 1) / 4;
      for (int p = cur.child; p <= last; ++p) {
        const TrianglePack4& pack = packs_[p];
        // Sheared float vertex coordinates relative to the ray, 4 triangles at a time.
        F4 sxv[3], syv[3];
        for (int j = 0; j < 3; ++j) {
          const F4 az = Load(pack.v[j][kz]) - ro_z;
          sxv[j] = (Load(pack.v[j][kx]) - ro_x) - sx4 * az;
          syv[j] = (Load(pack.v[j][ky]) - ro_y) - sy4 * az;
        }
        const F4 u = sxv[2] * syv[1] - syv[2] * sxv[1];
        const F4 v = sxv[0] * syv[2] - syv[0] * sxv[2];
        const F4 w = sxv[1] * syv[0] - syv[1] * sxv[0];
        const F4 mag = Max(Max(Max(Abs(sxv[0]), Abs(syv[0])), Max(Abs(sxv[1]), Abs(syv[1]))),
                           Max(Abs(sxv[2]), Abs(syv[2])));
        const F4 err = mag * (e_lin + e_quad * mag) + e_const;
        const I4 miss = (Min(Min(u, v), w) < -err) & (Max(Max(u, v), w) > err);
        const I4 valid = kLane < (cur.count - 4 * (p - cur.child));
        unsigned candidates = MoveMask(valid & ~miss);
        while (candidates != 0) {
          const int lane = __builtin_ctz(candidates);
          candidates &= candidates - 1;
          const int i = 4 * p + lane;
          double t, b1, b2;
          if (!wray.Intersect(vertices_[pack.vertex[0][lane]].position,
                              vertices_[pack.vertex[1][lane]].position,
                              vertices_[pack.vertex[2][lane]].position, t_min, best, &t, &b1, &b2))
            continue;
          if constexpr (kAnyHit) {
            return i;
          } else {
            if (best_i >= 0 && t == best && triangle_[i] > triangle_[best_i]) continue;
            best = t;
            best_f = to_tmax_f(best);
            best_i = i;
            *best_t = t;
            *best_b1 = b1;
            *best_b2 = b2;
          }
        }
      }
    } else {
      const Node4& n = nodes_[cur.child];
      const F4 t0x = (Load(n.lo_x) - ox) * ix, t1x = (Load(n.hi_x) - ox) * ix;
      const F4 t0y = (Load(n.lo_y) - oy) * iy, t1y = (Load(n.hi_y) - oy) * iy;
      const F4 t0z = (Load(n.lo_z) - oz) * iz, t1z = (Load(n.hi_z) - oz) * iz;
      const F4 tnear = Max(Max(Min(t0x, t1x), Min(t0y, t1y)), Max(Min(t0z, t1z), tmin4));
      const F4 tfar =
          Min(Min(Max(t0x, t1x), Max(t0y, t1y)), Min(Max(t0z, t1z), Splat(best_f))) * grow4;
      I4 child;
      std::memcpy(&child, n.child, sizeof(child));
      unsigned hit = MoveMask((tnear <= tfar) & (child >= 0));  // empty slots have child -1
      if (hit != 0) {
        Entry found[4];
        int nf = 0;
        do {
          const int k = __builtin_ctz(hit);
          hit &= hit - 1;
          found[nf++] = {n.child[k], n.count[k], tnear[k]};
        } while (hit != 0);
        // Nearest first: sort by entry distance (descending), push all but the nearest.
        for (int a = 1; a < nf; ++a) {
          for (int b = a; b > 0 && found[b].t > found[b - 1].t; --b)
            std::swap(found[b], found[b - 1]);
        }
        for (int k = 0; k + 1 < nf; ++k) stack[sp++] = found[k];
        cur = found[nf - 1];
        continue;
      }
    }
    // Pop the next node still in front of the closest hit so far.
    do {
      if (sp == 0) return best_i;
      --sp;
    } while (stack[sp].t > best_f);
    cur = stack[sp];
  }
}

std::optional<RayHit> Bvh::Intersect(const Ray& ray, double t_min, double t_max) const {
  double t = 0.0, b1 = 0.0, b2 = 0.0;
  const int i = Traverse<false>(ray, t_min, t_max, &t, &b1, &b2);
  if (i < 0) return std::nullopt;
  const TrianglePack4& pack = packs_[i / 4];
  const VertexRecord& r0 = vertices_[pack.vertex[0][i % 4]];
  const VertexRecord& r1 = vertices_[pack.vertex[1][i % 4]];
  const VertexRecord& r2 = vertices_[pack.vertex[2][i % 4]];
  RayHit hit;
  hit.t = t;
  hit.triangle = triangle_[i];
  hit.b1 = b1;
  hit.b2 = b2;
  hit.point = ray.origin + t * ray.direction;
  const Eigen::Vector3d gn = (r1.position - r0.position).cross(r2.position - r0.position);
  const double gl = gn.norm();
  hit.geometric_normal = gl > 0.0 ? Eigen::Vector3d(gn / gl) : Eigen::Vector3d::UnitZ();
  const Eigen::Vector3d sn = (1.0 - b1 - b2) * r0.normal + b1 * r1.normal + b2 * r2.normal;
  const double sl = sn.norm();
  hit.normal = sl > 0.0 ? Eigen::Vector3d(sn / sl) : hit.geometric_normal;
  hit.front_face = ray.direction.dot(hit.geometric_normal) < 0.0;
  return hit;
}

bool Bvh::Occluded(const Ray& ray, double t_min, double t_max) const {
  double t, b1, b2;
  return Traverse<true>(ray, t_min, t_max, &t, &b1, &b2) >= 0;
}

}  // namespace gs360
