#include "recon/grid_solver.h"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace gs360 {
namespace {

// Rectangles of at most this many nodes are eliminated as one dense block, not split further:
// below it the bookkeeping of another level costs more than the dense arithmetic it saves.
constexpr int kLeafNodes = 8;

struct Rect {
  int x0, y0, x1, y1;  // [x0, x1) x [y0, y1)
  int Width() const { return x1 - x0; }
  int Height() const { return y1 - y0; }
};

}  // namespace

// One node of the elimination tree: a rectangle of the grid whose nodes not eliminated below
// (its separator, or all of a leaf) are eliminated here. Its dense front holds those nodes first
// and then its ring (the interior nodes just outside the rectangle, eliminated by ancestors).
// Every list is a range of the solver's flat arrays.
struct GridLaplacianSolver::Front {
  int nodes = 0, sep = 0, ring = 0;    // nodes_[nodes, +sep) then its ring, +ring
  int assembly = 0, assembly_end = 0;  // assembly_ entries
  int first_child = -1, children = 0;  // consecutive in child_ (front ids)
  int child_pos = 0;                   // child_pos_: each child's ring positions in this front
  std::size_t values = 0;              // values_: the (sep + ring)^2 front, column-major
  int Size() const { return sep + ring; }
};

GridLaplacianSolver::GridLaplacianSolver(int w, int h) : w_(w), h_(h) {
  if (w < 3 || h < 3) {
    throw std::invalid_argument("GridLaplacianSolver: grid " + std::to_string(w) + " x " +
                                std::to_string(h) + " must be at least 3 x 3");
  }
  pos_.assign(static_cast<std::size_t>(w) * static_cast<std::size_t>(h), -1);
  Build(1, 1, w - 1, h - 1);
  pos_ = {};
  std::size_t values = 0;
  int most = 0;
  for (Front& f : fronts_) {
    f.values = values;
    values += static_cast<std::size_t>(f.Size()) * static_cast<std::size_t>(f.Size());
    most = std::max(most, f.Size());
  }
  values_.reset(new double[values]);  // uninitialised: each factorisation fills it
  scratch_.resize(static_cast<std::size_t>(2 * most));
}

GridLaplacianSolver::~GridLaplacianSolver() = default;

bool GridLaplacianSolver::Interior(int node) const {
  const int x = node % w_, y = node / w_;
  return x >= 1 && y >= 1 && x <= w_ - 2 && y <= h_ - 2;
}

// Post-order: the children's fronts are pushed before their parent's. Returns the front's id.
int GridLaplacianSolver::Build(int x0, int y0, int x1, int y1) {
  const Rect r{x0, y0, x1, y1};
  int kids[2], n_kids = 0;
  std::vector<int> sep;
  if (r.Width() * r.Height() <= kLeafNodes) {
    for (int y = y0; y < y1; ++y)
      for (int x = x0; x < x1; ++x) sep.push_back(y * w_ + x);
  } else if (r.Width() >= r.Height()) {
    const int xm = (x0 + x1) / 2;
    if (xm > x0) kids[n_kids++] = Build(x0, y0, xm, y1);
    if (xm + 1 < x1) kids[n_kids++] = Build(xm + 1, y0, x1, y1);
    for (int y = y0; y < y1; ++y) sep.push_back(y * w_ + xm);
  } else {
    const int ym = (y0 + y1) / 2;
    if (ym > y0) kids[n_kids++] = Build(x0, y0, x1, ym);
    if (ym + 1 < y1) kids[n_kids++] = Build(x0, ym + 1, x1, y1);
    for (int x = x0; x < x1; ++x) sep.push_back(ym * w_ + x);
  }
  Front f;
  f.nodes = static_cast<int>(nodes_.size());
  f.sep = static_cast<int>(sep.size());
  nodes_.insert(nodes_.end(), sep.begin(), sep.end());
  // The ring: interior nodes 4-adjacent to the rectangle from outside.
  auto ring = [&](int x, int y) {
    if (x >= 1 && y >= 1 && x <= w_ - 2 && y <= h_ - 2) nodes_.push_back(y * w_ + x), ++f.ring;
  };
  for (int x = x0; x < x1; ++x) ring(x, y0 - 1);
  for (int y = y0; y < y1; ++y) ring(x0 - 1, y), ring(x1, y);
  for (int x = x0; x < x1; ++x) ring(x, y1);
  for (int i = 0; i < f.Size(); ++i) pos_[nodes_[f.nodes + i]] = i;
  AddAssembly(f);
  f.first_child = static_cast<int>(child_.size());
  f.children = n_kids;
  f.child_pos = static_cast<int>(child_pos_.size());
  for (int c = 0; c < n_kids; ++c) {
    child_.push_back(kids[c]);
    const Front& ch = fronts_[static_cast<std::size_t>(kids[c])];
    for (int i = ch.sep; i < ch.Size(); ++i) {
      const int at = pos_[nodes_[ch.nodes + i]];
      if (at < 0) throw std::logic_error("GridLaplacianSolver: a ring outside its parent");
      child_pos_.push_back(at);
    }
  }
  for (int i = 0; i < f.Size(); ++i) pos_[nodes_[f.nodes + i]] = -1;
  fronts_.push_back(f);
  return static_cast<int>(fronts_.size()) - 1;
}

// Each edge with an end eliminated in f is assembled there, once: its weight on the diagonal of
// every end eliminated there, and off the diagonal when both ends are in the front (an edge to a
// node eliminated further down was assembled down there, on this end's diagonal too). pos_ holds
// the front's positions.
void GridLaplacianSolver::AddAssembly(Front& f) {
  f.assembly = static_cast<int>(assembly_.size());
  const int n = f.Size();
  auto lower = [n](int a, int b) { return a >= b ? b * n + a : a * n + b; };
  auto edge = [&](int a, int b, int id) {
    const int pa = pos_[a], pb = pos_[b];
    if (pa >= 0 && pa < f.sep) assembly_.push_back({lower(pa, pa), id, 1.0});
    if (pb >= 0 && pb < f.sep) assembly_.push_back({lower(pb, pb), id, 1.0});
    if (Interior(a) && Interior(b) && pa >= 0 && pb >= 0) {
      assembly_.push_back({lower(pa, pb), id, -1.0});
    }
  };
  for (int i = 0; i < f.sep; ++i) {
    const int g = nodes_[f.nodes + i];
    // An edge between two nodes eliminated here is met from both: take it from its first node.
    auto once = [&](int a, int b, int id) {
      const int other = a == g ? b : a;
      if (a == g || !(pos_[other] >= 0 && pos_[other] < f.sep)) edge(a, b, id);
    };
    once(g - 1, g, 2 * (g - 1));
    once(g, g + 1, 2 * g);
    once(g - w_, g, 2 * (g - w_) + 1);
    once(g, g + w_, 2 * g + 1);
  }
  f.assembly_end = static_cast<int>(assembly_.size());
}

void GridLaplacianSolver::FactorFront(const Front& f, const std::vector<double>& weight_u,
                                      const std::vector<double>& weight_v) {
  const int n = f.Size();
  double* data = values_.get() + f.values;
  std::fill(data, data + static_cast<std::size_t>(n) * static_cast<std::size_t>(n), 0.0);
  for (int k = f.assembly; k < f.assembly_end; ++k) {
    const Assembly& a = assembly_[static_cast<std::size_t>(k)];
    data[a.offset] += a.sign * ((a.edge & 1) ? weight_v[a.edge >> 1] : weight_u[a.edge >> 1]);
  }
  const int* at = child_pos_.data() + f.child_pos;
  for (int c = 0; c < f.children; ++c) {
    const Front& ch = fronts_[static_cast<std::size_t>(child_[f.first_child + c])];
    const int cn = ch.Size();
    const double* child = values_.get() + ch.values;
    for (int j = 0; j < ch.ring; ++j) {
      const double* src = child + static_cast<std::size_t>(ch.sep + j) * cn + ch.sep;
      for (int i = j; i < ch.ring; ++i) {
        const int a = at[i], b = at[j];
        data[a >= b ? b * n + a : a * n + b] += src[i];
      }
    }
    at += ch.ring;
  }
}

bool GridLaplacianSolver::Factorize(const std::vector<double>& weight_u,
                                    const std::vector<double>& weight_v) {
  factorized_ = false;
  const std::size_t count = static_cast<std::size_t>(w_) * static_cast<std::size_t>(h_);
  if (weight_u.size() < count || weight_v.size() < count) {
    throw std::invalid_argument("GridLaplacianSolver::Factorize: weights must have w * h entries");
  }
  // NaN would pass Cholesky's pivot test; an edge <= 0 breaks the contract.
  for (std::size_t i = 0; i < count; ++i) {
    const bool has_u = static_cast<int>(i % w_) + 1 < w_, has_v = static_cast<int>(i / w_) + 1 < h_;
    if ((has_u && !(weight_u[i] > 0.0 && std::isfinite(weight_u[i]))) ||
        (has_v && !(weight_v[i] > 0.0 && std::isfinite(weight_v[i])))) {
      return false;
    }
  }
  for (const Front& f : fronts_) {
    FactorFront(f, weight_u, weight_v);
    Eigen::Map<Eigen::MatrixXd> front(values_.get() + f.values, f.Size(), f.Size());
    Eigen::Ref<Eigen::MatrixXd> ss = front.topLeftCorner(f.sep, f.sep);
    const Eigen::LLT<Eigen::Ref<Eigen::MatrixXd>> llt(ss);
    if (llt.info() != Eigen::Success) return false;
    if (f.ring == 0) continue;
    auto l_rs = front.bottomLeftCorner(f.ring, f.sep);
    ss.triangularView<Eigen::Lower>().transpose().solveInPlace<Eigen::OnTheRight>(l_rs);
    front.bottomRightCorner(f.ring, f.ring).selfadjointView<Eigen::Lower>().rankUpdate(l_rs, -1.0);
  }
  factorized_ = true;
  return true;
}

void GridLaplacianSolver::Solve(std::vector<double>* x) const {
  if (!factorized_) throw std::logic_error("GridLaplacianSolver::Solve without a factorisation");
  std::vector<double>& v = *x;
  if (v.size() < static_cast<std::size_t>(w_) * static_cast<std::size_t>(h_)) {
    throw std::invalid_argument("GridLaplacianSolver::Solve: x must have w * h entries");
  }
  auto front_of = [&](const Front& f) {
    return Eigen::Map<const Eigen::MatrixXd>(values_.get() + f.values, f.Size(), f.Size());
  };
  for (const Front& f : fronts_) {  // L y = b
    const auto front = front_of(f);
    const int* node = nodes_.data() + f.nodes;
    Eigen::Map<Eigen::VectorXd> y(scratch_.data(), f.sep), r(scratch_.data() + f.sep, f.ring);
    for (int i = 0; i < f.sep; ++i) y[i] = v[node[i]];
    front.topLeftCorner(f.sep, f.sep).triangularView<Eigen::Lower>().solveInPlace(y);
    for (int i = 0; i < f.sep; ++i) v[node[i]] = y[i];
    if (f.ring == 0) continue;
    r.noalias() = front.bottomLeftCorner(f.ring, f.sep) * y;
    for (int i = 0; i < f.ring; ++i) v[node[f.sep + i]] -= r[i];
  }
  for (auto it = fronts_.rbegin(); it != fronts_.rend(); ++it) {  // L^T x = y
    const Front& f = *it;
    const auto front = front_of(f);
    const int* node = nodes_.data() + f.nodes;
    Eigen::Map<Eigen::VectorXd> y(scratch_.data(), f.sep), r(scratch_.data() + f.sep, f.ring);
    for (int i = 0; i < f.sep; ++i) y[i] = v[node[i]];
    if (f.ring > 0) {
      for (int i = 0; i < f.ring; ++i) r[i] = v[node[f.sep + i]];
      y.noalias() -= front.bottomLeftCorner(f.ring, f.sep).transpose() * r;
    }
    front.topLeftCorner(f.sep, f.sep).triangularView<Eigen::Lower>().transpose().solveInPlace(y);
    for (int i = 0; i < f.sep; ++i) v[node[i]] = y[i];
  }
  const std::size_t w = static_cast<std::size_t>(w_), last_row = (h_ - 1) * w;
  for (std::size_t x0 = 0; x0 < w; ++x0) v[x0] = v[last_row + x0] = 0.0;
  for (std::size_t row = 0; row <= last_row; row += w) v[row] = v[row + w - 1] = 0.0;
}

}  // namespace gs360
