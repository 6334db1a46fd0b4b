#pragma once
// A direct solver for weighted Laplacians on a rectangular grid: the linear system of each
// height-field pass (recon/height_field.h).
//
// The unknowns are the interior nodes (x, y), 1 <= x <= w - 2, 1 <= y <= h - 2, of a w x h
// grid whose border nodes are fixed at 0. Every edge between 4-neighbours has a weight > 0; the
// matrix is
//     A(i, i) = sum of the weights of i's four edges (edges to the border included),
//     A(i, j) = -weight(i, j) for interior neighbours,
// symmetric positive definite. The grid's structure is known before any weight is, so the
// elimination order is fixed once (nested dissection: a grid line splits each rectangle in two,
// recursively) and each factorisation works on small dense blocks (a multifrontal Cholesky), with
// no sparse-matrix assembly, ordering or pattern analysis per solve.
//
// Indexing: node (x, y) is y * w + x, as in the height field's grid. Edge weights are indexed by
// their first node: weight_u[i] is the edge i -> i + 1, weight_v[i] is i -> i + w.
//
// Not thread-safe: one solver per thread (Factorize and Solve use its own buffers).

#include <cstddef>
#include <memory>
#include <vector>

namespace gs360 {

class GridLaplacianSolver {
 public:
  // w, h >= 3. Throws std::invalid_argument otherwise. Builds the elimination tree and sizes
  // the solver's own buffers once (Eigen's dense kernels may still take scratch per call).
  GridLaplacianSolver(int w, int h);
  ~GridLaplacianSolver();
  GridLaplacianSolver(const GridLaplacianSolver&) = delete;
  GridLaplacianSolver& operator=(const GridLaplacianSolver&) = delete;

  int width() const { return w_; }
  int height() const { return h_; }

  // weight_u, weight_v: w * h entries (entries of edges that do not exist, past the last column
  // or row, are ignored). Returns false when the matrix is not numerically positive definite (a
  // weight <= 0 or not finite); the solver then holds no factorisation. Throws
  // std::invalid_argument for fewer than w * h entries.
  bool Factorize(const std::vector<double>& weight_u, const std::vector<double>& weight_v);

  // In: x holds the right-hand side at each interior node (w * h entries; the border's are
  // ignored). Out: the solution there, 0 on the border. Throws std::logic_error without a
  // successful Factorize, std::invalid_argument for fewer than w * h entries.
  void Solve(std::vector<double>* x) const;

 private:
  struct Front;
  struct Assembly {
    int offset;   // into the front's values
    int edge;     // 2 * first node + (0: u, 1: v)
    double sign;  // + on a diagonal, - off it
  };
  int Build(int x0, int y0, int x1, int y1);
  void AddAssembly(Front& f);
  void FactorFront(const Front& f, const std::vector<double>& weight_u,
                   const std::vector<double>& weight_v);
  bool Interior(int node) const;

  int w_ = 0, h_ = 0;
  std::vector<Front> fronts_;  // children before parents: the elimination order
  std::vector<int> nodes_;     // each front's separator, then its ring (grid node ids)
  std::vector<Assembly> assembly_;
  std::vector<int> child_, child_pos_;
  std::unique_ptr<double[]> values_;  // every front's dense matrix (filled by Factorize)
  bool factorized_ = false;
  std::vector<int> pos_;  // while building: a node's position in the front being built
  mutable std::vector<double> scratch_;
};

}  // namespace gs360
