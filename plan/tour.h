#pragma once
// Tour construction for the probe order: a closed tour from a depot (the machine's start
// position) through every node, minimising the sum of a symmetric edge cost (machine seconds).
//
// Algorithm: nearest-neighbour construction (Euclidean, uniform-grid search) from the depot, then
// a local search with 2-opt and Or-opt moves (segments of 1-3 nodes, either orientation) over
// K-nearest-neighbour candidate lists, driven by don't-look bits, until no improving move is left
// or `max_passes` * (n + 1) node visits were spent. New edges are first judged with a cheap lower
// bound of the cost (e.g. the straight-line travel time) and evaluated exactly only when the move
// could improve the tour. Deterministic: no randomness, no time limits.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <functional>
#include <vector>

namespace gs360 {

struct TourOptions {
  int neighbours = 10;   // candidate list size (>= 1)
  int max_passes = 50;   // local-search budget in passes over all nodes (>= 0; 0 = NN only)
  bool optimise = true;  // false: nearest-neighbour tour only
  void Check() const;    // throws std::invalid_argument naming the field and value
};

struct TourResult {
  // Visiting order of the nodes 0..n-1 (the depot, index n, is implicit at both ends).
  std::vector<int> order;
  double nearest_neighbour_cost = 0.0;  // closed-tour cost after construction
  double cost = 0.0;                    // closed-tour cost at the end
  int two_opt_moves = 0;
  int or_opt_moves = 0;
};

// Symmetric edge cost between nodes (index n = the depot). Must be >= lower_bound for the same
// pair for the pruning to be exact; a looser bound only makes the search try fewer moves.
using TourCost = std::function<double(int, int)>;

// `positions`: the n nodes' coordinates (used for neighbour search only); `depot`: the start.
// Throws std::invalid_argument for invalid options or non-finite positions.
TourResult SolveTour(const std::vector<Eigen::Vector3d>& positions, const Eigen::Vector3d& depot,
                     const TourCost& cost, const TourCost& lower_bound,
                     const TourOptions& options = {});

// Closed-tour cost of `order` (depot -> order -> depot).
double TourLength(const std::vector<int>& order, int depot, const TourCost& cost);

}  // namespace gs360
