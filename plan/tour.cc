#include "plan/tour.h"

#include <algorithm>
#include <cmath>
#include <deque>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>

namespace gs360 {
namespace {

constexpr double kEps = 1e-9;  // s: improvements smaller than this are ignored

// Uniform grid over the points for nearest-neighbour queries; points can be removed.
class PointGrid {
 public:
  explicit PointGrid(const std::vector<Eigen::Vector3d>& pts) : pts_(pts) {
    Eigen::AlignedBox3d box;
    box.setEmpty();
    for (const auto& p : pts_) box.extend(p);
    lo_ = box.min();
    const double extent = std::max(box.sizes().maxCoeff(), 1e-9);
    const int k = std::clamp(static_cast<int>(std::sqrt(pts_.size() / 4.0)), 1, 128);
    cell_ = extent / k;
    for (int a = 0; a < 3; ++a) {
      dims_[a] = std::max(1, static_cast<int>(std::floor(box.sizes()[a] / cell_)) + 1);
    }
    cells_.resize(static_cast<std::size_t>(dims_[0]) * dims_[1] * dims_[2]);
    slot_.resize(pts_.size());
    for (int i = 0; i < static_cast<int>(pts_.size()); ++i) {
      auto& c = cells_[CellIndex(CellOf(pts_[i]))];
      slot_[i] = static_cast<int>(c.size());
      c.push_back(i);
    }
  }

  void Remove(int i) {
    auto& c = cells_[CellIndex(CellOf(pts_[i]))];
    const int s = slot_[i];
    const int last = c.back();
    c[s] = last;
    slot_[last] = s;
    c.pop_back();
  }

  // Nearest remaining point to q (ties: lowest index), or -1 when empty.
  int Nearest(const Eigen::Vector3d& q) const {
    std::vector<std::pair<double, int>> found;
    Search(q, 1, &found);
    return found.empty() ? -1 : found.front().second;
  }

  // The k nearest remaining points (sorted by distance, then index), excluding `self`.
  std::vector<int> KNearest(const Eigen::Vector3d& q, int k, int self) const {
    std::vector<std::pair<double, int>> found;
    Search(q, k + 1, &found);
    std::vector<int> out;
    for (const auto& [d, i] : found) {
      if (i != self && static_cast<int>(out.size()) < k) out.push_back(i);
    }
    return out;
  }

 private:
  Eigen::Vector3i CellOf(const Eigen::Vector3d& p) const {
    Eigen::Vector3i c;
    for (int a = 0; a < 3; ++a) {
      c[a] = std::clamp(static_cast<int>(std::floor((p[a] - lo_[a]) / cell_)), 0, dims_[a] - 1);
    }
    return c;
  }
  std::size_t CellIndex(const Eigen::Vector3i& c) const {
    return (static_cast<std::size_t>(c[2]) * dims_[1] + c[1]) * dims_[0] + c[0];
  }

  void Search(const Eigen::Vector3d& q, int k, std::vector<std::pair<double, int>>* found) const {
    found->clear();
    const Eigen::Vector3i c0 = CellOf(q);
    const int max_r = std::max({dims_[0], dims_[1], dims_[2]});
    for (int r = 0; r <= max_r; ++r) {
      for (int z = c0[2] - r; z <= c0[2] + r; ++z) {
        if (z < 0 || z >= dims_[2]) continue;
        for (int y = c0[1] - r; y <= c0[1] + r; ++y) {
          if (y < 0 || y >= dims_[1]) continue;
          const bool shell_yz = std::abs(z - c0[2]) == r || std::abs(y - c0[1]) == r;
          for (int x = c0[0] - r; x <= c0[0] + r; ++x) {
            if (x < 0 || x >= dims_[0]) continue;
            if (!shell_yz && std::abs(x - c0[0]) != r) continue;  // only the ring's shell
            for (int i : cells_[CellIndex({x, y, z})]) {
              found->emplace_back((pts_[i] - q).squaredNorm(), i);
            }
          }
        }
      }
      if (static_cast<int>(found->size()) >= k) {
        std::sort(found->begin(), found->end());
        found->resize(k);
        // Points in rings beyond r are at least r * cell_ away.
        const double bound = r * cell_;
        if (found->back().first <= bound * bound) return;
      }
    }
    std::sort(found->begin(), found->end());
    if (static_cast<int>(found->size()) > k) found->resize(k);
  }

  const std::vector<Eigen::Vector3d>& pts_;
  Eigen::Vector3d lo_;
  double cell_ = 1.0;
  int dims_[3] = {1, 1, 1};
  std::vector<std::vector<int>> cells_;
  std::vector<int> slot_;
};

class LocalSearch {
 public:
  LocalSearch(std::vector<int> tour, const std::vector<std::vector<int>>& neighbours,
              const TourCost& cost, const TourCost& lower)
      : t_(std::move(tour)), nbr_(neighbours), cost_(cost), lower_(lower) {
    m_ = static_cast<int>(t_.size());
    pos_.resize(m_);
    for (int i = 0; i < m_; ++i) pos_[t_[i]] = i;
  }

  void Run(long long budget, int* two_opt, int* or_opt) {
    std::deque<int> queue(t_.begin(), t_.end());
    std::vector<char> queued(m_, 1);
    long long visits = 0;
    while (!queue.empty() && visits < budget) {
      const int a = queue.front();
      queue.pop_front();
      queued[a] = 0;
      ++visits;
      std::vector<int> touched;
      bool improved = TwoOpt(a, &touched);
      if (improved) {
        ++*two_opt;
      } else if (m_ >= 6 && OrOpt(a, &touched)) {
        improved = true;
        ++*or_opt;
      }
      if (improved) {
        touched.push_back(a);
        for (int x : touched) {
          if (!queued[x]) {
            queued[x] = 1;
            queue.push_back(x);
          }
        }
      }
    }
  }

  const std::vector<int>& Tour() const { return t_; }

 private:
  int Succ(int x) const { return t_[pos_[x] + 1 == m_ ? 0 : pos_[x] + 1]; }
  int Pred(int x) const { return t_[pos_[x] == 0 ? m_ - 1 : pos_[x] - 1]; }

  // Reverses the cyclic position range [i, j] (forward from i), or its complement when shorter
  // (the same cycle, traversed the other way).
  void Reverse(int i, int j) {
    int len = (j - i + m_) % m_ + 1;
    if (2 * len > m_) {
      const int ni = (j + 1) % m_, nj = (i - 1 + m_) % m_;
      i = ni;
      j = nj;
      len = m_ - len;
    }
    for (int k = 0; k < len / 2; ++k) {
      const int pi = (i + k) % m_, pj = (j - k + m_) % m_;
      std::swap(t_[pi], t_[pj]);
      pos_[t_[pi]] = pi;
      pos_[t_[pj]] = pj;
    }
  }

  bool TwoOpt(int a, std::vector<int>* touched) {
    for (int dir = 0; dir < 2; ++dir) {
      const int b = dir == 0 ? Succ(a) : Pred(a);
      const double ab = cost_(a, b);
      for (int c : nbr_[a]) {
        if (c == b) continue;
        if (ab - lower_(a, c) <= kEps) break;
        const int d = dir == 0 ? Succ(c) : Pred(c);
        if (d == a) continue;
        const double cd = cost_(c, d);
        if (ab + cd - lower_(a, c) - lower_(b, d) <= kEps) continue;
        const double gain = ab + cd - cost_(a, c) - cost_(b, d);
        if (gain <= kEps) continue;
        if (dir == 0) {
          Reverse(pos_[b], pos_[c]);  // a [b .. c] d -> a [c .. b] d
        } else {
          Reverse(pos_[a], pos_[d]);  // b [a .. d] c -> b [d .. a] c
        }
        touched->insert(touched->end(), {b, c, d});
        return true;
      }
    }
    return false;
  }

  bool OrOpt(int a, std::vector<int>* touched) {
    for (int len = 1; len <= 3; ++len) {
      if (m_ < len + 3) break;
      std::vector<int> seg{a};
      for (int k = 1; k < len; ++k) seg.push_back(Succ(seg.back()));
      const int s1 = seg.front(), s2 = seg.back();
      const int p = Pred(s1), nx = Succ(s2);
      const double removed = cost_(p, s1) + cost_(s2, nx) - cost_(p, nx);
      if (removed <= kEps) continue;
      auto in_seg = [&](int x) { return std::find(seg.begin(), seg.end(), x) != seg.end(); };
      for (int end = 0; end < 2; ++end) {
        const int anchor = end == 0 ? s1 : s2;
        for (int c : nbr_[anchor]) {
          if (in_seg(c)) continue;
          if (removed - lower_(anchor, c) <= kEps) break;
          for (int side = 0; side < 2; ++side) {
            const int d = side == 0 ? Succ(c) : Pred(c);
            if (in_seg(d)) continue;
            if ((c == p && d == nx) || (c == nx && d == p)) continue;
            const double cd = cost_(c, d);
            // Connect c to the anchor end, d to the other end.
            const int other = anchor == s1 ? s2 : s1;
            if (removed + cd - lower_(c, anchor) - lower_(other, d) <= kEps) continue;
            const double gain = removed + cd - cost_(c, anchor) - cost_(other, d);
            if (gain <= kEps) continue;
            ApplyOrOpt(seg, c, d, anchor);
            touched->insert(touched->end(), {p, nx, c, d, s1, s2});
            return true;
          }
        }
      }
    }
    return false;
  }

  // Moves `seg` between the adjacent nodes c and d with `anchor` (an end of seg) next to c.
  void ApplyOrOpt(const std::vector<int>& seg, int c, int d, int anchor) {
    std::vector<int> rest;
    rest.reserve(m_);
    const int start = (pos_[seg.back()] + 1) % m_;
    for (int k = 0; k < m_ - static_cast<int>(seg.size()); ++k)
      rest.push_back(t_[(start + k) % m_]);
    std::vector<int> x = seg;
    // In `rest`, find the order of c and d.
    const auto ic = std::find(rest.begin(), rest.end(), c) - rest.begin();
    const auto id = std::find(rest.begin(), rest.end(), d) - rest.begin();
    const int n = static_cast<int>(rest.size());
    std::vector<int> out;
    out.reserve(m_);
    // c then d consecutively (possibly wrapping), or d then c.
    const bool c_first = (ic + 1) % n == id;
    if (c_first) {
      // ... c X d ...: X.front() must be the anchor.
      if (x.front() != anchor) std::reverse(x.begin(), x.end());
      out.assign(rest.begin(), rest.begin() + ic + 1);
      out.insert(out.end(), x.begin(), x.end());
      out.insert(out.end(), rest.begin() + ic + 1, rest.end());
    } else {
      // ... d X c ...: X.back() must be the anchor.
      if (x.back() != anchor) std::reverse(x.begin(), x.end());
      out.assign(rest.begin(), rest.begin() + id + 1);
      out.insert(out.end(), x.begin(), x.end());
      out.insert(out.end(), rest.begin() + id + 1, rest.end());
    }
    t_ = std::move(out);
    for (int i = 0; i < m_; ++i) pos_[t_[i]] = i;
  }

  std::vector<int> t_;
  std::vector<int> pos_;
  int m_ = 0;
  const std::vector<std::vector<int>>& nbr_;
  const TourCost& cost_;
  const TourCost& lower_;
};

}  // namespace

void TourOptions::Check() const {
  if (neighbours < 1) {
    throw std::invalid_argument("TourOptions.neighbours must be >= 1, got " +
                                std::to_string(neighbours));
  }
  if (max_passes < 0) {
    throw std::invalid_argument("TourOptions.max_passes must be >= 0, got " +
                                std::to_string(max_passes));
  }
}

double TourLength(const std::vector<int>& order, int depot, const TourCost& cost) {
  if (order.empty()) return 0.0;
  double total = cost(depot, order.front()) + cost(order.back(), depot);
  for (std::size_t i = 1; i < order.size(); ++i) total += cost(order[i - 1], order[i]);
  return total;
}

TourResult SolveTour(const std::vector<Eigen::Vector3d>& positions, const Eigen::Vector3d& depot,
                     const TourCost& cost, const TourCost& lower_bound,
                     const TourOptions& options) {
  options.Check();
  const int n = static_cast<int>(positions.size());
  for (int i = 0; i < n; ++i) {
    if (!positions[i].allFinite()) {
      throw std::invalid_argument("SolveTour: position " + std::to_string(i) + " is not finite");
    }
  }
  if (!depot.allFinite()) throw std::invalid_argument("SolveTour: depot is not finite");
  TourResult result;
  if (n == 0) return result;

  // Nearest-neighbour construction from the depot.
  {
    PointGrid grid(positions);
    Eigen::Vector3d at = depot;
    result.order.reserve(n);
    for (int k = 0; k < n; ++k) {
      const int next = grid.Nearest(at);
      result.order.push_back(next);
      grid.Remove(next);
      at = positions[next];
    }
  }
  result.nearest_neighbour_cost = TourLength(result.order, n, cost);
  result.cost = result.nearest_neighbour_cost;
  if (!options.optimise || options.max_passes == 0 || n < 3) return result;

  // Candidate lists over nodes and depot.
  std::vector<Eigen::Vector3d> all = positions;
  all.push_back(depot);
  std::vector<std::vector<int>> neighbours(n + 1);
  {
    PointGrid grid(all);
    const int k = std::min(options.neighbours, n);
    for (int i = 0; i <= n; ++i) neighbours[i] = grid.KNearest(all[i], k, i);
  }
  std::vector<int> cycle;
  cycle.reserve(n + 1);
  cycle.push_back(n);
  cycle.insert(cycle.end(), result.order.begin(), result.order.end());
  LocalSearch search(std::move(cycle), neighbours, cost, lower_bound);
  search.Run(static_cast<long long>(options.max_passes) * (n + 1), &result.two_opt_moves,
             &result.or_opt_moves);
  // Rotate so that the depot comes first; drop it.
  const std::vector<int>& t = search.Tour();
  const int at = static_cast<int>(std::find(t.begin(), t.end(), n) - t.begin());
  result.order.clear();
  for (int k = 1; k <= n; ++k) result.order.push_back(t[(at + k) % (n + 1)]);
  result.cost = TourLength(result.order, n, cost);
  return result;
}

}  // namespace gs360
