#include "geometry/bvh.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstddef>
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
constexpr int kWordsPerLine = 8;  // 8-byte words per 64-byte line
// A child's block is prefetched up to this many lines (its node and first leaves).
constexpr int kMaxPrefetchLines = 32;
// At most 64 triangles per leaf, so at most 192 distinct vertices.
constexpr int kMaxLeafVertices = 192;
// Word offsets in Bvh::lines_: a never-hit leaf (one degenerate triangle) that empty node slots
// point to, then the root's block.
constexpr std::int32_t kEmptyLeaf = 0;
constexpr std::int32_t kRoot = kWordsPerLine;

// Bytes of a leaf record (see Bvh::Line) with nt triangles and m (even) vertex slots: header
// word, x[m], y[m], z[m], triangle[nt], corner[nt][3], padding to 8 bytes.
std::size_t LeafBytes(int nt, int m) {
  return (8 + 24 * static_cast<std::size_t>(m) + 7 * static_cast<std::size_t>(nt) + 7) / 8 * 8;
}
// A leaf record's vertex normals, double[nv][3] (header bytes 4..7: their offset in words).
const unsigned char* LeafNormals(const unsigned char* leaf) {
  std::int32_t at;
  std::memcpy(&at, leaf + 4, sizeof(at));
  return leaf + 8 * static_cast<std::ptrdiff_t>(at);
}

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
// 2-lane double vectors (SSE2 on x86-64, NEON on AArch64) for the leaves' vertices.
typedef double D2 __attribute__((vector_size(16)));

inline F4 Splat(float v) {
  return F4{v, v, v, v};
}
inline F4 LoadBytes(const unsigned char* p) {
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
// Bit k set when lane k of the comparison result `m` (all ones / all zeros) is set.
inline unsigned MoveMask(I4 m) {
#if defined(__SSE2__)
  return static_cast<unsigned>(_mm_movemask_ps(reinterpret_cast<__m128>(m)));
#else
  return (m[0] ? 1u : 0u) | (m[1] ? 2u : 0u) | (m[2] ? 4u : 0u) | (m[3] ? 8u : 0u);
#endif
}

inline D2 Splat2(double v) {
  return D2{v, v};
}
inline D2 Load2(const unsigned char* p) {
  D2 v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}
inline void Store2(double* p, D2 v) {
  std::memcpy(p, &v, sizeof(v));
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
};

// Throws std::invalid_argument for a non-finite vertex or an index out of range.
void CheckIndexedMesh(const TriangleMesh& mesh) {
  const int nv = mesh.NumVertices();
  for (int i = 0; i < nv; ++i) {
    if (!mesh.vertices[i].allFinite()) {
      throw std::invalid_argument("Bvh: vertex " + std::to_string(i) + " is not finite");
    }
  }
  const int nt = mesh.NumTriangles();
  for (int t = 0; t < nt; ++t) {
    const Eigen::Vector3i& f = mesh.triangles[t];
    if (f.minCoeff() < 0 || f.maxCoeff() >= nv) {
      throw std::invalid_argument("Bvh: triangle " + std::to_string(t) +
                                  " has a vertex index out of range [0, " + std::to_string(nv) +
                                  ")");
    }
  }
}

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

// Lays the binary tree out in lines_, in 8-byte words (see Layout in bvh.h): the empty leaf,
// then depth first one block per 4-wide node: the Node4, the records of its leaf children, their
// normals. Capacity for the largest possible size is reserved (untouched pages cost nothing), so
// lines_ never moves.
class Bvh::Writer {
 public:
  using Nodes = std::vector<Builder::BuildNode>;

  Writer(Bvh& bvh, const Nodes& nodes) : bvh_(bvh) {
    std::size_t capacity = 16 * static_cast<std::size_t>(nodes.size() + 2);  // nodes
    for (const auto& bn : nodes) {
      if (bn.count > 0) capacity += 32 + 19 * static_cast<std::size_t>(bn.count);  // leaf, padding
    }
    bvh_.lines_.reserve(capacity / kWordsPerLine + 1);
  }

  std::size_t used() const { return used_; }

  // The empty leaf: one vertex (at the origin) and one triangle whose three corners are that
  // vertex, so u = v = w = 0 (or NaN): never a hit. It has no normals (never read). Empty node
  // slots point to it, so that entering one (NaN box tests from absurd rays) is harmless.
  void AddEmptyLeaf() {
    static_assert(kEmptyLeaf == 0 && kRoot == kWordsPerLine);  // the record is one line
    unsigned char* rec = Word(Grow(LeafBytes(1, 2) / 8));
    rec[0] = 1;  // vertices; then x, y, z[2] = 0, triangle[1] = -1, corner[1][3] = 0
    rec[1] = 1;  // triangles
    const std::int32_t none = -1;
    std::memcpy(rec + 8 + 24 * 2, &none, sizeof(none));
  }

  // Collapses the binary tree into 4-wide nodes, depth first: each node takes up to four
  // descendants, opening the inner candidate with the largest box surface first.
  void Collapse(const Nodes& bnodes, const std::vector<std::int32_t>& order, double pad) {
    struct Todo {
      int binary;           // binary node
      std::int32_t parent;  // word offset of the parent Node4, -1 for the root
      int slot;             // slot in the parent
    };
    std::vector<Todo> todo = {{0, -1, 0}};
    while (!todo.empty()) {
      const Todo item = todo.back();
      todo.pop_back();
      const std::vector<int> slots = Slots(bnodes, item.binary);
      const std::size_t offset = Grow(sizeof(Node4) / 8);
      Node4 node{};
      for (int k = 0; k < 4; ++k) {
        if (k >= static_cast<int>(slots.size())) {
          SetEmptySlot(&node, k);
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
          node.child[k] = AddLeaf(&order[c.index], c.count);
          node.count[k] = c.count;
          ++bvh_.stats_.leaves;
        } else {
          // Child and count are set when its block is laid out.
          todo.push_back({slots[k], static_cast<std::int32_t>(offset), k});
        }
      }
      std::memcpy(Word(offset), &node, sizeof(node));
      // The prefetched part of the block ends here; the leaves' normals follow (read only for a
      // final hit, and prefetched when their leaf is entered).
      const auto lines = static_cast<std::int32_t>(std::min<std::size_t>(
          (used_ - offset + kWordsPerLine - 1) / kWordsPerLine, kMaxPrefetchLines));
      FlushNormals();
      AlignLine();
      ++bvh_.stats_.nodes;
      if (item.parent >= 0) {
        const auto child = static_cast<std::int32_t>(offset);
        const std::int32_t count = -lines;
        unsigned char* parent = Word(static_cast<std::size_t>(item.parent));
        std::memcpy(parent + offsetof(Node4, child) + 4 * item.slot, &child, sizeof(child));
        std::memcpy(parent + offsetof(Node4, count) + 4 * item.slot, &count, sizeof(count));
      }
    }
  }

 private:
  // The storage is addressed as one array of bytes (the lines' object representation), not
  // through the first line's 64-byte member: an offset past it would leave that array.
  unsigned char* Word(std::size_t at) {
    return reinterpret_cast<unsigned char*>(bvh_.lines_.data()) + 8 * at;
  }

  // Appends zero words; returns the first one's offset.
  std::size_t Grow(std::size_t words) {
    const std::size_t at = used_;
    used_ += words;
    if (used_ > bvh_.lines_.size() * kWordsPerLine) {
      bvh_.lines_.resize((used_ + kWordsPerLine - 1) / kWordsPerLine);
    }
    return at;
  }

  void AlignLine() { Grow((kWordsPerLine - used_ % kWordsPerLine) % kWordsPerLine); }

  // Up to four descendants of binary node b for one Node4.
  static std::vector<int> Slots(const Nodes& bnodes, int b) {
    if (bnodes[b].count > 0) return {b};  // the whole tree is one leaf
    std::vector<int> slots = {bnodes[b].left, bnodes[b].index};
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
    return slots;
  }

  // Empty slot: an inverted infinite box, never entered (its near plane is at +inf and its far
  // plane at -inf whatever the ray's direction).
  static void SetEmptySlot(Node4* node, int k) {
    constexpr float kInf = std::numeric_limits<float>::infinity();
    node->lo_x[k] = node->lo_y[k] = node->lo_z[k] = kInf;
    node->hi_x[k] = node->hi_y[k] = node->hi_z[k] = -kInf;
    node->child[k] = kEmptyLeaf;
    node->count[k] = 1;
  }

  // Appends a leaf record for the triangles `tris` (mesh indices); returns its word offset.
  std::int32_t AddLeaf(const std::int32_t* tris, int leaf_nt) {
    const TriangleMesh& mesh = bvh_.mesh_;
    const std::size_t first = pending_vertices_.size();
    corner_.resize(3 * leaf_nt);
    for (int i = 0; i < leaf_nt; ++i) {
      for (int j = 0; j < 3; ++j) {
        const int mv = mesh.triangles[tris[i]][j];
        const auto begin = pending_vertices_.begin() + static_cast<std::ptrdiff_t>(first);
        const auto it = std::find(begin, pending_vertices_.end(), mv);
        corner_[3 * i + j] = static_cast<std::uint8_t>(it - begin);
        if (it == pending_vertices_.end()) pending_vertices_.push_back(mv);
      }
    }
    const int n_v = static_cast<int>(pending_vertices_.size() - first);
    const int m = n_v + (n_v & 1);
    const std::size_t at = Grow(LeafBytes(leaf_nt, m) / 8);
    unsigned char* rec = Word(at);
    rec[0] = static_cast<unsigned char>(n_v);
    rec[1] = static_cast<unsigned char>(leaf_nt);
    for (int a = 0; a < 3; ++a) {
      for (int i = 0; i < m; ++i) {  // an odd count repeats the last vertex
        const int v = pending_vertices_[first + static_cast<std::size_t>(std::min(i, n_v - 1))];
        std::memcpy(rec + 8 + 8 * (a * m + i), &mesh.vertices[v][a], sizeof(double));
      }
    }
    unsigned char* tri = rec + 8 + 24 * m;
    std::memcpy(tri, tris, 4 * static_cast<std::size_t>(leaf_nt));
    std::memcpy(tri + 4 * leaf_nt, corner_.data(), corner_.size());
    pending_normals_.emplace_back(at, first);
    return static_cast<std::int32_t>(at);
  }

  // Appends the normals of the block's leaves and points each leaf's header at them.
  void FlushNormals() {
    for (std::size_t i = 0; i < pending_normals_.size(); ++i) {
      const auto [leaf, first] = pending_normals_[i];
      const std::size_t end = i + 1 < pending_normals_.size() ? pending_normals_[i + 1].second
                                                              : pending_vertices_.size();
      const auto at = static_cast<std::int32_t>(used_ - leaf);
      std::memcpy(Word(leaf) + 4, &at, sizeof(at));
      for (std::size_t v = first; v < end; ++v) {
        std::memcpy(Word(Grow(3)), bvh_.mesh_.normals[pending_vertices_[v]].data(), 24);
      }
    }
    pending_normals_.clear();
    pending_vertices_.clear();
  }

  Bvh& bvh_;
  std::size_t used_ = 0;  // words
  // Leaves of the current block whose normals are still to be appended: (record, first vertex
  // in pending_vertices_).
  std::vector<std::pair<std::size_t, std::size_t>> pending_normals_;
  std::vector<int> pending_vertices_;
  std::vector<std::uint8_t> corner_;
};

Bvh::Bvh(const TriangleMesh& mesh, const BvhOptions& options) : mesh_(mesh) {
  options.Check();
  const auto start = std::chrono::steady_clock::now();
  CheckIndexedMesh(mesh_);
  const int nt = mesh_.NumTriangles();
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

  Writer writer(*this, builder.nodes);
  writer.AddEmptyLeaf();
  writer.Collapse(builder.nodes, order, pad);
  const std::size_t used = writer.used();
  if (used > static_cast<std::size_t>(std::numeric_limits<std::int32_t>::max())) {
    throw std::length_error("Bvh: " + std::to_string(nt) +
                            " triangles need more than 16 GiB of tree (32-bit offsets)");
  }
  stats_.max_depth = builder.max_depth;
  stats_.build_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

// Traverse's per-ray constants and tests, built once per ray. Box test in float: slab distances
// (plane - origin) * (1 / direction), over an interval slightly wider than [t_min, closest hit].
// Triangle test: the watertight test (Woop, Benthin, Wald 2013) in double. A leaf's vertices are
// translated, permuted and sheared once (two at a time), then each triangle's edge functions are
// formed from them with exactly the operations of the scalar test.
struct Bvh::RayTests {
  // Conservative float interval: slightly wider than [t_min, best].
  static constexpr float kGrow = 1.0f + 4.0f * std::numeric_limits<float>::epsilon();

  // A node or leaf to visit: leaf -> at = its record, count = its triangles; inner -> at = its
  // Node4, count <= 0. t: entry distance along the ray (float, never above the exact one).
  struct Entry {
    std::int32_t at;
    std::int32_t count;
    float t;
  };

  // The closest hit so far, and the box test's far bound that follows it.
  struct Closest {
    explicit Closest(double t_max) : t(t_max), t_f(ToFloatBound(t_max)), t4(Splat(t_f)) {}
    double t;
    float t_f;
    F4 t4;
    std::int32_t triangle = -1;
    HitSlot slot;
  };

  // Scratch for one leaf's translated, permuted and sheared vertices.
  struct LeafVertices {
    alignas(16) double sx[kMaxLeafVertices], sy[kMaxLeafVertices], dz[kMaxLeafVertices];
  };

  static float ToFloatBound(double t) {
    return t >= static_cast<double>(std::numeric_limits<float>::max())
               ? std::numeric_limits<float>::infinity()
               : static_cast<float>(t) * kGrow;
  }

  RayTests(const Ray& ray, double t_min_in) : wray(ray), t_min(t_min_in) {
    const Eigen::Vector3d& d = ray.direction;
    float inv[3];
    for (int k = 0; k < 3; ++k) {
      double dk = d[k];
      if (std::abs(dk) < 1e-30) dk = dk < 0.0 ? -1e-30 : 1e-30;
      inv[k] = static_cast<float>(1.0 / dk);
    }
    ox = Splat(static_cast<float>(ray.origin.x()));
    oy = Splat(static_cast<float>(ray.origin.y()));
    oz = Splat(static_cast<float>(ray.origin.z()));
    ix = Splat(inv[0]), iy = Splat(inv[1]), iz = Splat(inv[2]);
    // Byte offsets in a Node4 of each axis's near and far planes: lo where the direction is
    // positive, else hi (the same distances as min / max of both, without computing both).
    for (int k = 0; k < 3; ++k) {
      const std::size_t lo_at = offsetof(Node4, lo_x) + 16 * k;
      const std::size_t hi_at = offsetof(Node4, hi_x) + 16 * k;
      near_at[k] = inv[k] >= 0.0f ? lo_at : hi_at;
      far_at[k] = inv[k] >= 0.0f ? hi_at : lo_at;
    }
    float tmin_f = static_cast<float>(t_min);
    tmin_f = tmin_f > 0.0f ? tmin_f / kGrow : tmin_f * kGrow;
    tmin4 = Splat(tmin_f);
    grow4 = Splat(kGrow);
    o_x = Splat2(ray.origin[wray.kx]), o_y = Splat2(ray.origin[wray.ky]);
    o_z = Splat2(ray.origin[wray.kz]);
    sx2 = Splat2(wray.sx), sy2 = Splat2(wray.sy);
  }

  // The children of `node` whose boxes the ray enters before `far`: bit k for child k; *tnear:
  // the entry distances.
  unsigned Boxes(const unsigned char* node, F4 far, F4* tnear) const {
    const F4 t0x = (LoadBytes(node + near_at[0]) - ox) * ix;
    const F4 t1x = (LoadBytes(node + far_at[0]) - ox) * ix;
    const F4 t0y = (LoadBytes(node + near_at[1]) - oy) * iy;
    const F4 t1y = (LoadBytes(node + far_at[1]) - oy) * iy;
    const F4 t0z = (LoadBytes(node + near_at[2]) - oz) * iz;
    const F4 t1z = (LoadBytes(node + far_at[2]) - oz) * iz;
    *tnear = Max(Max(t0x, t0y), Max(t0z, tmin4));
    const F4 tfar = Min(Min(t1x, t1y), Min(t1z, far)) * grow4;
    return MoveMask(*tnear <= tfar);
  }

  // Tests the triangles of the leaf `cur`. Closest hit: updates *closest and writes t and the
  // barycentrics; returns false. kAnyHit: returns true at the first hit (closest->slot set).
  template <bool kAnyHit>
  bool Leaf(const unsigned char* base, const Entry& cur, LeafVertices* lv, Closest* closest,
            double* best_t, double* best_b1, double* best_b2) const {
    const unsigned char* leaf = base + 8 * static_cast<std::size_t>(cur.at);
    const int nt = cur.count;
    const int m = leaf[0] + (leaf[0] & 1);
    if constexpr (!kAnyHit) {
      // Its normals, in case it holds the final hit (they are not part of the block).
      const unsigned char* nrm = LeafNormals(leaf);
      for (int byte = 0; byte < 24 * leaf[0]; byte += 64) __builtin_prefetch(nrm + byte);
    }
    const unsigned char* px = leaf + 8 + 8 * m * wray.kx;
    const unsigned char* py = leaf + 8 + 8 * m * wray.ky;
    const unsigned char* pz = leaf + 8 + 8 * m * wray.kz;
    double* sxa = lv->sx;
    double* sya = lv->sy;
    double* dza = lv->dz;
    for (int i = 0; i < m; i += 2) {
      const D2 az = Load2(pz + 8 * i) - o_z;
      Store2(&sxa[i], (Load2(px + 8 * i) - o_x) - sx2 * az);
      Store2(&sya[i], (Load2(py + 8 * i) - o_y) - sy2 * az);
      Store2(&dza[i], az);
    }
    const unsigned char* tri = leaf + 8 + 24 * m;
    const unsigned char* corner = tri + 4 * nt;
    for (int j = 0; j < nt; ++j) {
      const int a = corner[3 * j], b = corner[3 * j + 1], c = corner[3 * j + 2];
      const double u = sxa[c] * sya[b] - sya[c] * sxa[b];
      const double v = sxa[a] * sya[c] - sya[a] * sxa[c];
      const double w = sxa[b] * sya[a] - sya[b] * sxa[a];
      if (((u < 0.0) | (v < 0.0) | (w < 0.0)) & ((u > 0.0) | (v > 0.0) | (w > 0.0))) continue;
      const double det = u + v + w;
      if (det == 0.0) continue;
      const double az = wray.sz * dza[a], bz = wray.sz * dza[b], cz = wray.sz * dza[c];
      const double t = (u * az + v * bz + w * cz) / det;
      if (!(t >= t_min && t <= closest->t)) continue;
      if constexpr (kAnyHit) {
        closest->slot = HitSlot{cur.at, j};
        return true;
      } else {
        std::int32_t triangle;
        std::memcpy(&triangle, tri + 4 * j, sizeof(triangle));
        if (closest->triangle >= 0 && t == closest->t && triangle > closest->triangle) continue;
        closest->t = t;
        closest->t_f = ToFloatBound(t);
        closest->t4 = Splat(closest->t_f);
        closest->triangle = triangle;
        closest->slot = HitSlot{cur.at, j};
        *best_t = t;
        *best_b1 = v / det;
        *best_b2 = w / det;
      }
    }
    return false;
  }

  // Enters the children of `node` set in `hit` (entry distances tnear): returns the nearest and
  // pushes the others onto stack[*sp...], farthest first. An inner child's block (its node and
  // leaves) is fetched whole right away; a leaf child is part of this node's block, fetched
  // already.
  static Entry Enter(const unsigned char* base, const unsigned char* node, unsigned hit, F4 tnear,
                     Entry* stack, int* sp) {
    const Node4& n = *reinterpret_cast<const Node4*>(node);
    auto enter = [&](int k) -> Entry {
      const unsigned char* q = base + 8 * static_cast<std::size_t>(n.child[k]);
      for (int line = 0; line < -n.count[k]; line += 4) {  // (up to 3 lines past its end)
        __builtin_prefetch(q + 64 * line);
        __builtin_prefetch(q + 64 * line + 64);
        __builtin_prefetch(q + 64 * line + 128);
        __builtin_prefetch(q + 64 * line + 192);
      }
      return {n.child[k], n.count[k], tnear[k]};
    };
    if ((hit & (hit - 1)) == 0) return enter(__builtin_ctz(hit));  // one child: the common case
    Entry found[4] = {};
    int nf = 0;
    do {
      found[nf++] = enter(__builtin_ctz(hit));
      hit &= hit - 1;
    } while (hit != 0);
    // Nearest first: sort by entry distance (descending), push all but the nearest.
    for (int a = 1; a < nf; ++a) {
      for (int b = a; b > 0 && found[b].t > found[b - 1].t; --b) std::swap(found[b], found[b - 1]);
    }
    stack[*sp] = found[0];  // entries past nf - 2 are scratch, overwritten later
    stack[*sp + 1] = found[1];
    stack[*sp + 2] = found[2];
    *sp += nf - 1;
    return found[nf - 1];
  }

  const WatertightRay wray;
  const double t_min;
  F4 ox, oy, oz, ix, iy, iz, tmin4, grow4;
  std::size_t near_at[3], far_at[3];
  D2 o_x, o_y, o_z, sx2, sy2;
};

template <bool kAnyHit>
Bvh::HitSlot Bvh::Traverse(const Ray& ray, double t_min, double t_max, double* best_t,
                           double* best_b1, double* best_b2) const {
  if (lines_.empty()) return HitSlot();
  const Eigen::Vector3d& d = ray.direction;
  if (!ray.origin.allFinite() || !d.allFinite() || d.squaredNorm() == 0.0) return HitSlot();
  if (!(t_max >= t_min)) return HitSlot();
  const unsigned char* const base = reinterpret_cast<const unsigned char*>(lines_.data());
  const RayTests tests(ray, t_min);
  RayTests::Closest closest(t_max);
  RayTests::LeafVertices leaf_vertices;
  RayTests::Entry stack[kStackSize];
  int sp = 0;
  RayTests::Entry cur{kRoot, 0, 0.0f};
  while (true) {
    if (cur.count > 0) {
      if (tests.Leaf<kAnyHit>(base, cur, &leaf_vertices, &closest, best_t, best_b1, best_b2)) {
        return closest.slot;
      }
    } else {
      const unsigned char* node = base + 8 * static_cast<std::size_t>(cur.at);
      F4 tnear;
      const unsigned hit = tests.Boxes(node, closest.t4, &tnear);
      if (hit != 0) {
        cur = RayTests::Enter(base, node, hit, tnear, stack, &sp);
        continue;
      }
    }
    // Pop the next node still in front of the closest hit so far.
    do {
      if (sp == 0) return closest.slot;
      --sp;
    } while (stack[sp].t > closest.t_f);
    cur = stack[sp];
  }
}

std::optional<RayHit> Bvh::Intersect(const Ray& ray, double t_min, double t_max) const {
  double t = 0.0, b1 = 0.0, b2 = 0.0;
  const HitSlot slot = Traverse<false>(ray, t_min, t_max, &t, &b1, &b2);
  if (slot.leaf < 0) return std::nullopt;
  const unsigned char* leaf = reinterpret_cast<const unsigned char*>(lines_.data()) +
                              8 * static_cast<std::size_t>(slot.leaf);
  const int m = leaf[0] + (leaf[0] & 1);
  const int nt = leaf[1];
  const unsigned char* tri = leaf + 8 + 24 * m;
  const unsigned char* corner = tri + 4 * nt + 3 * slot.index;
  const unsigned char* nrm = LeafNormals(leaf);
  Eigen::Vector3d p[3], vn[3];
  for (int j = 0; j < 3; ++j) {
    for (int a = 0; a < 3; ++a) std::memcpy(&p[j][a], leaf + 8 + 8 * (a * m + corner[j]), 8);
    std::memcpy(vn[j].data(), nrm + 24 * corner[j], 24);
  }
  RayHit hit;
  hit.t = t;
  std::memcpy(&hit.triangle, tri + 4 * slot.index, sizeof(std::int32_t));
  hit.b1 = b1;
  hit.b2 = b2;
  hit.point = ray.origin + t * ray.direction;
  const Eigen::Vector3d gn = (p[1] - p[0]).cross(p[2] - p[0]);
  const double gl = gn.norm();
  hit.geometric_normal = gl > 0.0 ? Eigen::Vector3d(gn / gl) : Eigen::Vector3d::UnitZ();
  const Eigen::Vector3d sn = (1.0 - b1 - b2) * vn[0] + b1 * vn[1] + b2 * vn[2];
  const double sl = sn.norm();
  hit.normal = sl > 0.0 ? Eigen::Vector3d(sn / sl) : hit.geometric_normal;
  hit.front_face = ray.direction.dot(hit.geometric_normal) < 0.0;
  return hit;
}

bool Bvh::Occluded(const Ray& ray, double t_min, double t_max) const {
  double t, b1, b2;
  return Traverse<true>(ray, t_min, t_max, &t, &b1, &b2).leaf >= 0;
}

}  // namespace gs360
