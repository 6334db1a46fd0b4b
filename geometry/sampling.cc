#include "geometry/sampling.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <string>

namespace gs360 {
namespace {

// SplitMix64: small, fast, well-distributed, and identical on every platform.
class Random {
 public:
  explicit Random(std::uint64_t seed) : state_(seed) {}
  std::uint64_t Next() {
    std::uint64_t z = (state_ += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
  }
  // Uniform in [0, 1).
  double Uniform() { return static_cast<double>(Next() >> 11) * 0x1.0p-53; }

 private:
  std::uint64_t state_;
};

// Area-weighted triangle picker and uniform point-in-triangle.
class AreaSampler {
 public:
  explicit AreaSampler(const TriangleMesh& mesh) : mesh_(mesh) {
    cdf_.reserve(mesh.triangles.size());
    double acc = 0.0;
    for (int t = 0; t < mesh.NumTriangles(); ++t) {
      const double a = mesh.TriangleArea(t);
      acc += std::isfinite(a) ? a : 0.0;
      cdf_.push_back(acc);
    }
    total_ = acc;
    if (!(total_ > 0.0)) {
      throw std::invalid_argument("sampling: the mesh has zero area (" +
                                  std::to_string(mesh.NumTriangles()) + " triangles)");
    }
  }
  double total_area() const { return total_; }

  SurfaceSample Draw(Random& rng) const {
    const double x = rng.Uniform() * total_;
    int t = static_cast<int>(std::upper_bound(cdf_.begin(), cdf_.end(), x) - cdf_.begin());
    t = std::min(t, static_cast<int>(cdf_.size()) - 1);
    // Skip zero-area triangles that upper_bound cannot land on anyway (defensive).
    const double r1 = std::sqrt(rng.Uniform());
    const double u2 = rng.Uniform();
    SurfaceSample s;
    s.triangle = t;
    s.b1 = r1 * (1.0 - u2);
    s.b2 = r1 * u2;
    const double b0 = 1.0 - s.b1 - s.b2;
    const Eigen::Vector3i& f = mesh_.triangles[t];
    s.point = b0 * mesh_.vertices[f[0]] + s.b1 * mesh_.vertices[f[1]] + s.b2 * mesh_.vertices[f[2]];
    Eigen::Vector3d n = Eigen::Vector3d::Zero();
    if (mesh_.HasNormals()) {
      n = b0 * mesh_.normals[f[0]] + s.b1 * mesh_.normals[f[1]] + s.b2 * mesh_.normals[f[2]];
    }
    if (!(n.norm() > 1e-12)) n = mesh_.TriangleNormal(t);
    s.normal = n.norm() > 0.0 ? Eigen::Vector3d(n.normalized()) : Eigen::Vector3d::UnitZ();
    return s;
  }

 private:
  const TriangleMesh& mesh_;
  std::vector<double> cdf_;
  double total_ = 0.0;
};

// Draws up to `wanted` kept samples; `attempts` receives the number of draws.
std::vector<SurfaceSample> DrawKept(const AreaSampler& sampler, int wanted, Random& rng,
                                    const SamplePredicate& keep, long long* attempts) {
  std::vector<SurfaceSample> out;
  out.reserve(wanted);
  const long long max_attempts = std::max<long long>(1000, 200LL * wanted);
  long long n = 0;
  while (static_cast<int>(out.size()) < wanted && n < max_attempts) {
    SurfaceSample s = sampler.Draw(rng);
    ++n;
    if (!keep || keep(s)) out.push_back(s);
  }
  *attempts = n;
  return out;
}

// Uniform grid over points with cubic cells of `cell` size: the point indices sorted by a cell
// key in which the three z-neighbours of a cell are consecutive, so a 3x3x3 neighbourhood is 9
// binary searches over one sorted array (no hashing; cache friendly when the points themselves
// are in key order).
class PointGrid {
 public:
  PointGrid(const std::vector<Eigen::Vector3d>& pts, double cell) : cell_(cell) {
    const int n = static_cast<int>(pts.size());
    std::vector<std::pair<std::uint64_t, int>> keyed(n);
    for (int i = 0; i < n; ++i) keyed[i] = {Key(Cell(pts[i])), i};
    std::sort(keyed.begin(), keyed.end());
    keys_.resize(n);
    sorted_.resize(n);
    for (int i = 0; i < n; ++i) {
      keys_[i] = keyed[i].first;
      sorted_[i] = keyed[i].second;
    }
  }

  // Point indices in key order (a spatially coherent order).
  const std::vector<int>& SortedIndices() const { return sorted_; }

  // Calls f(j) for every point j in the 27 cells around p.
  template <typename F>
  void ForNeighbourCells(const Eigen::Vector3d& p, F&& f) const {
    const Eigen::Vector3i c = Cell(p);
    for (int dx = -1; dx <= 1; ++dx) {
      for (int dy = -1; dy <= 1; ++dy) {
        const std::uint64_t lo = Key(c + Eigen::Vector3i(dx, dy, -1));
        const std::uint64_t hi = Key(c + Eigen::Vector3i(dx, dy, 1));
        auto it = std::lower_bound(keys_.begin(), keys_.end(), lo);
        for (; it != keys_.end() && *it <= hi; ++it) f(sorted_[it - keys_.begin()]);
      }
    }
  }

 private:
  Eigen::Vector3i Cell(const Eigen::Vector3d& p) const {
    return Eigen::Vector3i(static_cast<int>(std::floor(p.x() / cell_)),
                           static_cast<int>(std::floor(p.y() / cell_)),
                           static_cast<int>(std::floor(p.z() / cell_)));
  }
  // 21 bits per axis, offset so that cells -2^20 .. 2^20-1 keep their order.
  static std::uint64_t Key(const Eigen::Vector3i& c) {
    auto field = [](int v) {
      return static_cast<std::uint64_t>(static_cast<std::uint32_t>(v + (1 << 20)) & 0x1FFFFF);
    };
    return (field(c.x()) << 42) | (field(c.y()) << 21) | field(c.z());
  }

  double cell_;
  std::vector<std::uint64_t> keys_;
  std::vector<int> sorted_;
};

// (1 - x)^alpha with a fast path for small integer exponents (alpha = 8 by default).
double WeightPow(double base, double alpha) {
  if (alpha == std::floor(alpha) && alpha >= 1.0 && alpha <= 32.0) {
    int e = static_cast<int>(alpha);
    double result = 1.0, b = base;
    while (e > 0) {
      if (e & 1) result *= b;
      b *= b;
      e >>= 1;
    }
    return result;
  }
  return std::pow(base, alpha);
}

// Indexed binary max-heap on (weight, index).
class WeightHeap {
 public:
  explicit WeightHeap(const std::vector<double>& w) : w_(w), heap_(w.size()), pos_(w.size()) {
    for (std::size_t i = 0; i < w.size(); ++i)
      heap_[i] = static_cast<int>(i), pos_[i] = static_cast<int>(i);
    for (int i = static_cast<int>(heap_.size()) / 2 - 1; i >= 0; --i) Down(i);
  }
  bool Empty() const { return heap_.empty(); }
  int Top() const { return heap_[0]; }
  void Pop() {
    const int last = heap_.back();
    pos_[heap_[0]] = -1;
    heap_.pop_back();
    if (!heap_.empty()) {
      heap_[0] = last;
      pos_[last] = 0;
      Down(0);
    }
  }
  // After w[i] decreased.
  void Decreased(int i) {
    if (pos_[i] >= 0) Down(pos_[i]);
  }

 private:
  bool Greater(int a, int b) const { return w_[a] > w_[b] || (w_[a] == w_[b] && a > b); }
  void Swap(int i, int j) {
    std::swap(heap_[i], heap_[j]);
    pos_[heap_[i]] = i;
    pos_[heap_[j]] = j;
  }
  void Down(int i) {
    const int n = static_cast<int>(heap_.size());
    while (true) {
      const int l = 2 * i + 1, r = l + 1;
      int m = i;
      if (l < n && Greater(heap_[l], heap_[m])) m = l;
      if (r < n && Greater(heap_[r], heap_[m])) m = r;
      if (m == i) return;
      Swap(i, m);
      i = m;
    }
  }
  const std::vector<double>& w_;
  std::vector<int> heap_;
  std::vector<int> pos_;
};

}  // namespace

double IdealBlueNoiseSpacing(double area, int count) {
  if (count <= 0 || !(area > 0.0)) return 0.0;
  return 2.0 * std::sqrt(area / (2.0 * std::sqrt(3.0) * count));
}

std::vector<SurfaceSample> SampleUniform(const TriangleMesh& mesh, int count, std::uint64_t seed,
                                         const SamplePredicate& keep) {
  if (count < 0)
    throw std::invalid_argument("SampleUniform: count must be >= 0, got " + std::to_string(count));
  const AreaSampler sampler(mesh);
  Random rng(seed);
  long long attempts = 0;
  return DrawKept(sampler, count, rng, keep, &attempts);
}

void BlueNoiseOptions::Check() const {
  auto bad = [](const char* field, double v, const char* rule) {
    std::ostringstream os;
    os << "BlueNoiseOptions." << field << " " << rule << ", got " << v;
    throw std::invalid_argument(os.str());
  };
  if (count < 0) bad("count", count, "must be >= 0");
  if (!(candidate_factor >= 1.0) || !std::isfinite(candidate_factor) || candidate_factor > 1000) {
    bad("candidate_factor", candidate_factor, "must be in [1, 1000]");
  }
  if (!(alpha > 0.0) || !std::isfinite(alpha)) bad("alpha", alpha, "must be finite and > 0");
  if (!(beta >= 0.0) || !(beta < 1.0)) bad("beta", beta, "must be in [0, 1)");
  if (!(gamma > 0.0) || !std::isfinite(gamma)) bad("gamma", gamma, "must be finite and > 0");
}

std::vector<SurfaceSample> SampleBlueNoise(const TriangleMesh& mesh,
                                           const BlueNoiseOptions& options,
                                           const SamplePredicate& keep) {
  options.Check();
  const AreaSampler sampler(mesh);
  if (options.count == 0) return {};
  Random rng(options.seed);
  const int wanted = static_cast<int>(std::ceil(options.candidate_factor * options.count));
  long long attempts = 0;
  std::vector<SurfaceSample> cand = DrawKept(sampler, wanted, rng, keep, &attempts);
  const int m = static_cast<int>(cand.size());
  const int n = options.count;
  if (m <= n) return cand;

  // Region area from the acceptance rate (exact without a predicate).
  const double area = sampler.total_area() * static_cast<double>(m) / static_cast<double>(attempts);
  const double d_max = IdealBlueNoiseSpacing(area, n);  // 2 r_max
  const double d_min =
      d_max * options.beta * (1.0 - std::pow(static_cast<double>(n) / m, options.gamma));

  // Work in a spatially coherent order (grid-key order); `orig[k]` is the candidate index.
  std::vector<int> orig;
  {
    std::vector<Eigen::Vector3d> raw(m);
    for (int i = 0; i < m; ++i) raw[i] = cand[i].point;
    orig = PointGrid(raw, d_max).SortedIndices();
  }
  std::vector<Eigen::Vector3d> pts(m);
  for (int k = 0; k < m; ++k) pts[k] = cand[orig[k]].point;
  const PointGrid grid(pts, d_max);

  // Neighbour lists (CSR) with their weights.
  std::vector<int> offsets(m + 1, 0);
  std::vector<int> nbr;
  std::vector<double> nbr_w;
  nbr.reserve(static_cast<std::size_t>(m) * 24);
  nbr_w.reserve(nbr.capacity());
  const double d_max2 = d_max * d_max;
  std::vector<double> weight(m, 0.0);
  for (int i = 0; i < m; ++i) {
    grid.ForNeighbourCells(pts[i], [&](int j) {
      if (j == i) return;
      const double d2 = (pts[j] - pts[i]).squaredNorm();
      if (d2 >= d_max2) return;
      const double d = std::max(std::sqrt(d2), d_min);
      const double w = WeightPow(1.0 - d / d_max, options.alpha);
      nbr.push_back(j);
      nbr_w.push_back(w);
      weight[i] += w;
    });
    offsets[i + 1] = static_cast<int>(nbr.size());
  }

  // Eliminate the heaviest candidate until n remain (ties: the higher working index first).
  std::vector<char> alive(m, 1);
  WeightHeap heap(weight);
  for (int remaining = m; remaining > n; --remaining) {
    const int i = heap.Top();
    heap.Pop();
    alive[i] = 0;
    for (int k = offsets[i]; k < offsets[i + 1]; ++k) {
      const int j = nbr[k];
      if (!alive[j]) continue;
      weight[j] -= nbr_w[k];
      heap.Decreased(j);
    }
  }
  std::vector<int> kept;
  kept.reserve(n);
  for (int k = 0; k < m; ++k)
    if (alive[k]) kept.push_back(orig[k]);
  std::sort(kept.begin(), kept.end());  // candidate-draw order
  std::vector<SurfaceSample> out;
  out.reserve(n);
  for (int i : kept) out.push_back(cand[i]);
  return out;
}

double MinimumSpacing(const std::vector<SurfaceSample>& samples) {
  const int n = static_cast<int>(samples.size());
  if (n < 2) return std::numeric_limits<double>::infinity();
  std::vector<Eigen::Vector3d> pts(n);
  Eigen::AlignedBox3d box;
  for (int i = 0; i < n; ++i) {
    pts[i] = samples[i].point;
    box.extend(pts[i]);
  }
  const double diag = box.diagonal().norm();
  if (!(diag > 0.0)) return 0.0;
  // Any pair closer than `cell` shares a cell neighbourhood; grow the cell until one is found.
  double cell = diag / std::sqrt(static_cast<double>(n));
  while (true) {
    const PointGrid grid(pts, cell);
    double best2 = std::numeric_limits<double>::infinity();
    for (int i = 0; i < n; ++i) {
      grid.ForNeighbourCells(pts[i], [&](int j) {
        if (j > i) best2 = std::min(best2, (pts[j] - pts[i]).squaredNorm());
      });
    }
    if (best2 < cell * cell || cell > 2.0 * diag) return std::sqrt(best2);
    cell *= 2.0;
  }
}

std::vector<int> FarthestPointOrder(const std::vector<Eigen::Vector3d>& points, int first) {
  const int n = static_cast<int>(points.size());
  if (n == 0) return {};
  if (first < 0 || first >= n) {
    throw std::invalid_argument("FarthestPointOrder: first = " + std::to_string(first) +
                                " is not in 0.." + std::to_string(n - 1));
  }
  std::vector<int> order;
  order.reserve(static_cast<std::size_t>(n));
  // Squared distance of every point to the nearest chosen one (-1: chosen).
  std::vector<double> nearest(static_cast<std::size_t>(n), std::numeric_limits<double>::infinity());
  int next = first;
  while (next >= 0) {
    order.push_back(next);
    nearest[static_cast<std::size_t>(next)] = -1.0;
    const Eigen::Vector3d& chosen = points[static_cast<std::size_t>(next)];
    next = -1;
    double farthest = -1.0;
    for (int i = 0; i < n; ++i) {
      double& d = nearest[static_cast<std::size_t>(i)];
      if (d < 0.0) continue;
      d = std::min(d, (points[static_cast<std::size_t>(i)] - chosen).squaredNorm());
      if (d > farthest) farthest = d, next = i;
    }
  }
  return order;
}

double PrefixCoveringRadius(const std::vector<Eigen::Vector3d>& points,
                            const std::vector<int>& order, int k) {
  const int n = static_cast<int>(points.size());
  if (static_cast<int>(order.size()) != n || k < 1 || k > n) {
    throw std::invalid_argument("PrefixCoveringRadius: k = " + std::to_string(k) + " of " +
                                std::to_string(order.size()) + " ordered points, " +
                                std::to_string(n) + " points");
  }
  double worst = 0.0;
  for (const Eigen::Vector3d& p : points) {
    double best = std::numeric_limits<double>::infinity();
    for (int j = 0; j < k; ++j) {
      const int index = order[static_cast<std::size_t>(j)];
      if (index < 0 || index >= n) {
        throw std::invalid_argument("PrefixCoveringRadius: order holds " + std::to_string(index));
      }
      best = std::min(best, (p - points[static_cast<std::size_t>(index)]).squaredNorm());
    }
    worst = std::max(worst, best);
  }
  return std::sqrt(worst);
}

}  // namespace gs360
