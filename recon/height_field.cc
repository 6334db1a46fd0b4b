#include "recon/height_field.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "base/field_error.h"
#include "recon/grid_solver.h"

namespace gs360 {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
// A projected grid cell wider than this (pixels) is a fold across the occluding contour seen
// edge-on, not a surface patch: it is not rasterised.
constexpr double kMaxTrianglePx = 32.0;

[[noreturn]] void Bad(const char* field, double value, const char* want) {
  ThrowFieldError(std::string("HeightFieldOptions.") + field, value,
                  std::string("must be ") + want);
}

// The undeformed surface on the region's grid: point, normal and derivatives along u and v.
struct Grid {
  int w = 0, h = 0;
  std::vector<Eigen::Vector3d> x0, n0, xu, xv, nu, nv;  // nu, nv: derivatives of n0
  std::vector<std::uint8_t> ok;                         // visible with usable derivatives
  int Index(int x, int y) const { return y * w + x; }
};

Grid BuildGrid(const SurfaceMap& map, const cv::Rect& roi) {
  Grid g;
  g.w = roi.width, g.h = roi.height;
  const std::size_t n = static_cast<std::size_t>(g.w) * static_cast<std::size_t>(g.h);
  const Eigen::Vector3d zero = Eigen::Vector3d::Zero();
  g.x0.assign(n, zero), g.n0.assign(n, zero), g.xu.assign(n, zero), g.xv.assign(n, zero);
  g.nu.assign(n, zero), g.nv.assign(n, zero);
  g.ok.assign(n, 0);
  auto vis = [&](int u, int v) {
    return u >= 0 && v >= 0 && u < map.width() && v < map.height() && map.visible(u, v);
  };
  // Central difference where both neighbours are visible (map pixels beyond the roi count),
  // one-sided otherwise.
  auto derivative = [&](int u, int v, int du, int dv, Eigen::Vector3d* dx, Eigen::Vector3d* dn) {
    const bool fwd = vis(u + du, v + dv), back = vis(u - du, v - dv);
    if (fwd && back) {
      *dx = 0.5 * (map.point0(u + du, v + dv) - map.point0(u - du, v - dv));
      *dn = 0.5 * (map.normal0(u + du, v + dv) - map.normal0(u - du, v - dv));
    } else if (fwd) {
      *dx = map.point0(u + du, v + dv) - map.point0(u, v);
      *dn = map.normal0(u + du, v + dv) - map.normal0(u, v);
    } else if (back) {
      *dx = map.point0(u, v) - map.point0(u - du, v - dv);
      *dn = map.normal0(u, v) - map.normal0(u - du, v - dv);
    } else {
      return false;
    }
    return true;
  };
  for (int y = 0; y < g.h; ++y) {
    for (int x = 0; x < g.w; ++x) {
      const int u = roi.x + x, v = roi.y + y, i = g.Index(x, y);
      if (!map.visible(u, v)) continue;
      g.x0[i] = map.point0(u, v);
      g.n0[i] = map.normal0(u, v);
      if (derivative(u, v, 1, 0, &g.xu[i], &g.nu[i]) &&
          derivative(u, v, 0, 1, &g.xv[i], &g.nv[i])) {
        g.ok[i] = 1;
      }
    }
  }
  return g;
}

// Depth-buffered rasterisation of the deformed grid surface into the region's pixels.
struct Raster {
  std::vector<double> depth;  // distance from the camera centre; +inf = nothing seen
  std::vector<float> sx, sy;  // grid position of the point seen
};

void Rasterize(const Grid& g, const FisheyeCamera& camera, const cv::Rect& roi,
               const std::vector<double>& h, Raster* r) {
  const std::size_t n = g.x0.size();
  std::vector<Eigen::Vector2d> p(n, Eigen::Vector2d::Zero());
  std::vector<double> dist(n, kNaN);
  for (std::size_t i = 0; i < n; ++i) {
    if (!g.ok[i]) continue;
    const Eigen::Vector3d x = g.x0[i] - h[i] * g.n0[i];
    if (!(x.norm() > 1e-9)) continue;
    p[i] = camera.ProjectUnchecked(x) - Eigen::Vector2d(roi.x, roi.y);
    dist[i] = x.norm();
    if (!p[i].allFinite()) dist[i] = kNaN;
  }
  r->depth.assign(n, std::numeric_limits<double>::infinity());
  r->sx.assign(n, 0.0f);
  r->sy.assign(n, 0.0f);
  auto triangle = [&](int a, int b, int c) {
    if (!std::isfinite(dist[a]) || !std::isfinite(dist[b]) || !std::isfinite(dist[c])) return;
    const Eigen::Vector2d &pa = p[a], &pb = p[b], &pc = p[c];
    const double area = (pb - pa).x() * (pc - pa).y() - (pb - pa).y() * (pc - pa).x();
    if (std::abs(area) < 1e-12) return;
    const double lo_x = std::min({pa.x(), pb.x(), pc.x()}),
                 hi_x = std::max({pa.x(), pb.x(), pc.x()});
    const double lo_y = std::min({pa.y(), pb.y(), pc.y()}),
                 hi_y = std::max({pa.y(), pb.y(), pc.y()});
    if (hi_x - lo_x > kMaxTrianglePx || hi_y - lo_y > kMaxTrianglePx) return;
    // Wholly outside the region (also keeps the casts below in range).
    if (hi_x < 0.0 || hi_y < 0.0 || lo_x > g.w - 1.0 || lo_y > g.h - 1.0) return;
    const int x0 = std::max(0, static_cast<int>(std::ceil(lo_x - 1e-9)));
    const int x1 = std::min(g.w - 1, static_cast<int>(std::floor(hi_x + 1e-9)));
    const int y0 = std::max(0, static_cast<int>(std::ceil(lo_y - 1e-9)));
    const int y1 = std::min(g.h - 1, static_cast<int>(std::floor(hi_y + 1e-9)));
    const double kEps = 1e-7;
    for (int y = y0; y <= y1; ++y) {
      for (int x = x0; x <= x1; ++x) {
        const Eigen::Vector2d q(x, y);
        const double l1 = ((q - pa).x() * (pc - pa).y() - (q - pa).y() * (pc - pa).x()) / area;
        const double l2 = ((pb - pa).x() * (q - pa).y() - (pb - pa).y() * (q - pa).x()) / area;
        const double l0 = 1.0 - l1 - l2;
        if (l0 < -kEps || l1 < -kEps || l2 < -kEps) continue;
        const double d = l0 * dist[a] + l1 * dist[b] + l2 * dist[c];
        const int k = g.Index(x, y);
        if (d >= r->depth[k]) continue;
        r->depth[k] = d;
        r->sx[k] = static_cast<float>(l0 * (a % g.w) + l1 * (b % g.w) + l2 * (c % g.w));
        r->sy[k] = static_cast<float>(l0 * (a / g.w) + l1 * (b / g.w) + l2 * (c / g.w));
      }
    }
  };
  for (int y = 0; y + 1 < g.h; ++y) {
    for (int x = 0; x + 1 < g.w; ++x) {
      const int i00 = g.Index(x, y), i10 = i00 + 1, i01 = i00 + g.w, i11 = i01 + 1;
      // Most cells are about a pixel wide and cover no pixel centre: skip them at once.
      const double lo_x = std::min({p[i00].x(), p[i10].x(), p[i01].x(), p[i11].x()});
      const double hi_x = std::max({p[i00].x(), p[i10].x(), p[i01].x(), p[i11].x()});
      if (std::ceil(lo_x - 1e-9) > std::floor(hi_x + 1e-9)) continue;
      const double lo_y = std::min({p[i00].y(), p[i10].y(), p[i01].y(), p[i11].y()});
      const double hi_y = std::max({p[i00].y(), p[i10].y(), p[i01].y(), p[i11].y()});
      if (std::ceil(lo_y - 1e-9) > std::floor(hi_y + 1e-9)) continue;
      triangle(i00, i10, i11);
      triangle(i00, i11, i01);
    }
  }
}

}  // namespace

void HeightFieldOptions::Check() const {
  if (iterations < 1 || iterations > 100) Bad("iterations", iterations, "in 1..100");
  if (oblique_iterations < 1 || oblique_iterations > 100) {
    Bad("oblique_iterations", oblique_iterations, "in 1..100");
  }
  if (!(oblique_view_angle_deg >= 0.0 && oblique_view_angle_deg <= 90.0)) {
    Bad("oblique_view_angle_deg", oblique_view_angle_deg, "in [0, 90]");
  }
  if (!(tolerance >= 0.0)) Bad("tolerance", tolerance, ">= 0");
  if (!(unobserved_weight > 0.0 && unobserved_weight <= 1.0)) {
    Bad("unobserved_weight", unobserved_weight, "in (0, 1]");
  }
  if (!(min_normal_dot > 0.0 && min_normal_dot < 1.0)) {
    Bad("min_normal_dot", min_normal_dot, "in (0, 1)");
  }
  if (!(min_view_angle_deg >= 0.0 && min_view_angle_deg < 90.0)) {
    Bad("min_view_angle_deg", min_view_angle_deg, "in [0, 90)");
  }
  if (!(window_grow_fraction >= 0.0 && window_grow_fraction <= 5.0)) {
    Bad("window_grow_fraction", window_grow_fraction, "in [0, 5]");
  }
}

namespace {

void CheckInputs(const SurfaceMap& map, const cv::Rect& roi, const cv::Mat& normals,
                 const HeightFieldOptions& options, const cv::Mat& initial_height) {
  options.Check();
  if (roi.width < 3 || roi.height < 3 || roi.x < 0 || roi.y < 0 ||
      roi.x + roi.width > map.width() || roi.y + roi.height > map.height()) {
    throw std::invalid_argument("IntegrateHeightField: roi must be at least 3 x 3 inside the map");
  }
  if (normals.type() != CV_64FC3 || normals.size() != roi.size()) {
    throw std::invalid_argument("IntegrateHeightField: normals must be CV_64FC3 of the roi's size");
  }
  if (!initial_height.empty() &&
      (initial_height.type() != CV_64F || initial_height.size() != roi.size())) {
    throw std::invalid_argument("IntegrateHeightField: initial_height must be CV_64F roi-sized");
  }
}

// The iterated least-squares fit of h to the observed normals (see height_field.h).
class HeightFieldSolver {
 public:
  HeightFieldSolver(const SurfaceMap& map, const FisheyeCamera& camera, const cv::Rect& roi,
                    const cv::Mat& normals, const HeightFieldOptions& options,
                    const cv::Mat& initial_height)
      : map_(map),
        camera_(camera),
        roi_(roi),
        options_(options),
        g_(BuildGrid(map, roi)),
        w_(g_.w),
        hgt_(g_.h),
        n_(g_.x0.size()),
        solver_(w_, hgt_) {
    // Each pixel's observed normal (camera frame), where it has one.
    normal_.assign(n_, Eigen::Vector3d::Zero());
    has_normal_.assign(n_, 0);
    for (int y = 0; y < hgt_; ++y) {
      for (int x = 0; x < w_; ++x) {
        const cv::Vec3d nn = normals.at<cv::Vec3d>(y, x);
        if (!map.visible(roi.x + x, roi.y + y) || !std::isfinite(nn[0]) || !std::isfinite(nn[1]) ||
            !std::isfinite(nn[2])) {
          continue;
        }
        normal_[g_.Index(x, y)] = Eigen::Vector3d(nn[0], nn[1], nn[2]);
        has_normal_[g_.Index(x, y)] = 1;
      }
    }
    interior_.assign(n_, 0);
    for (int y = 1; y + 1 < hgt_; ++y)
      for (int x = 1; x + 1 < w_; ++x) interior_[g_.Index(x, y)] = 1;
    h_.assign(n_, 0.0);
    if (!initial_height.empty()) {
      for (std::size_t i = 0; i < n_; ++i) {
        const int x = static_cast<int>(i % static_cast<std::size_t>(w_));
        const int y = static_cast<int>(i / static_cast<std::size_t>(w_));
        const double v = initial_height.at<double>(y, x);
        if (interior_[i] && std::isfinite(v)) h_[i] = v;
      }
    }
    target_u_.resize(n_), weight_u_.resize(n_), target_v_.resize(n_), weight_v_.resize(n_);
    edge_u_.assign(n_, 1.0), edge_v_.assign(n_, 1.0), rhs_.resize(n_);
  }

  HeightFieldResult Solve() {
    HeightFieldResult out;
    for (int pass = 0; pass < options_.iterations; ++pass) {
      Rasterize(g_, camera_, roi_, h_, &raster_);
      GatherSlopes();
      double change = 0.0;
      if (!SolvePass(&change)) break;
      out.iterations = pass + 1;
      if (change < options_.tolerance) break;
    }
    Rasterize(g_, camera_, roi_, h_, &raster_);
    out.height = cv::Mat(roi_.size(), CV_64F, cv::Scalar::all(0.0));
    out.rho = cv::Mat(roi_.size(), CV_64F, cv::Scalar::all(kNaN));
    for (int y = 0; y < hgt_; ++y) {
      for (int x = 0; x < w_; ++x) {
        const int i = g_.Index(x, y);
        out.height.at<double>(y, x) = h_[i];
        if (!map_.visible(roi_.x + x, roi_.y + y)) continue;
        // Nothing rasterised here (a roi edge or a hole next to an invisible pixel): the pixel's
        // own grid point, moved along its normal, is the best guess.
        out.rho.at<double>(y, x) = std::isfinite(raster_.depth[i])
                                       ? raster_.depth[i]
                                       : (g_.x0[i] - h_[i] * g_.n0[i]).norm();
      }
    }
    return out;
  }

 private:
  // Observations: pixel k sees grid position s'(k) = (sx, sy); its normal gives dh/du and
  // dh/dv there. A difference h(x + 1) - h(x) is the slope at its midpoint x + 1/2, so the u
  // slope goes to the two u edges whose midpoints bracket sx, linearly weighted, on the row
  // nearest sy (likewise v). Measured against giving it to the nearest grid node, whose two
  // edges then share it equally (a blur of one pixel across the imprint's edge): mean error
  // with exact slopes < 30 / 30-50 / > 50 deg 0.0100 / 0.0120 / 0.0315 mm against 0.0133 /
  // 0.0113 / 0.0369 (bench_integration --hf-init --hf-iterations 6); on the 2,000-probe virtual
  // rig 0.0233 mm against 0.0249 and the peak error 0.054 against 0.060 (docs/benchmarks.md).
  // Spreading across rows as well blurs the slope jump at the imprint's rim again (0.0241 mm).
  void GatherSlopes() {
    std::fill(target_u_.begin(), target_u_.end(), 0.0);
    std::fill(weight_u_.begin(), weight_u_.end(), 0.0);
    std::fill(target_v_.begin(), target_v_.end(), 0.0);
    std::fill(weight_v_.begin(), weight_v_.end(), 0.0);
    for (std::size_t k = 0; k < n_; ++k) {
      if (!has_normal_[k]) continue;
      double sx = static_cast<double>(k % static_cast<std::size_t>(w_));
      double sy = static_cast<double>(k / static_cast<std::size_t>(w_));
      if (std::isfinite(raster_.depth[k])) sx = raster_.sx[k], sy = raster_.sy[k];
      // The surface's geometry at s' is that of its nearest grid point (it varies slowly).
      const int i = g_.Index(std::clamp(static_cast<int>(std::lround(sx)), 0, w_ - 1),
                             std::clamp(static_cast<int>(std::lround(sy)), 0, hgt_ - 1));
      if (!g_.ok[i]) continue;
      const Eigen::Vector3d& nn = normal_[k];
      const double nd = nn.dot(g_.n0[i]);
      if (nd < options_.min_normal_dot) continue;
      // n is normal to dX/du = dx0/du - dh/du n0 - h dn0/du (h from the last pass).
      Spread(sx, sy, true, (nn.dot(g_.xu[i]) - h_[i] * nn.dot(g_.nu[i])) / nd);
      Spread(sy, sx, false, (nn.dot(g_.xv[i]) - h_[i] * nn.dot(g_.nv[i])) / nd);
    }
  }

  // along: the observation's coordinate along the slope's direction, across: the other one.
  void Spread(double along, double across, bool along_u, double t) {
    const int len_along = along_u ? w_ : hgt_, len_across = along_u ? hgt_ : w_;
    const int row = static_cast<int>(std::lround(across));
    if (row < 0 || row >= len_across) return;
    const double a = along - 0.5;
    const int first = static_cast<int>(std::floor(a));
    const double frac = a - first;
    for (int e = 0; e < 2; ++e) {
      const int start = first + e;  // the edge start -> start + 1
      const double we = e == 0 ? 1.0 - frac : frac;
      if (start < 0 || start + 1 >= len_along || we <= 0.0) continue;
      const int node = along_u ? g_.Index(start, row) : g_.Index(row, start);
      (along_u ? target_u_ : target_v_)[node] += we * t;
      (along_u ? weight_u_ : weight_v_)[node] += we;
    }
  }

  // Solves the normal equations of sum_e w_e (h_b - h_a - t_e)^2 and moves h there; *change:
  // the largest move. False (h kept) when the factorisation fails.
  bool SolvePass(double* change) {
    std::fill(rhs_.begin(), rhs_.end(), 0.0);
    auto edge = [&](int a, int b, double wsum, double target, double* weight) {
      double t = 0.0, we = options_.unobserved_weight;
      if (wsum > 1e-9) {
        t = target / wsum;
        we = std::clamp(wsum, options_.unobserved_weight, 1.0);
      }
      *weight = we;
      rhs_[a] -= we * t;
      rhs_[b] += we * t;
    };
    for (int y = 0; y < hgt_; ++y) {
      for (int x = 0; x < w_; ++x) {
        const int i = g_.Index(x, y);
        if (x + 1 < w_) edge(i, i + 1, weight_u_[i], target_u_[i], &edge_u_[i]);
        if (y + 1 < hgt_) edge(i, i + w_, weight_v_[i], target_v_[i], &edge_v_[i]);
      }
    }
    // Every unknown has four edges of weight > 0 and the border is fixed: the matrix is
    // positive definite. Should the factorisation still fail, keep the last pass's h.
    if (!solver_.Factorize(edge_u_, edge_v_)) return false;
    solver_.Solve(&rhs_);
    *change = 0.0;
    for (std::size_t i = 0; i < n_; ++i) {
      if (!interior_[i]) continue;
      *change = std::max(*change, std::abs(rhs_[i] - h_[i]));
      h_[i] = rhs_[i];
    }
    return true;
  }

  const SurfaceMap& map_;
  const FisheyeCamera& camera_;
  const cv::Rect roi_;
  const HeightFieldOptions& options_;
  const Grid g_;
  const int w_, hgt_;
  const std::size_t n_;
  std::vector<Eigen::Vector3d> normal_;  // observed, per grid point
  std::vector<std::uint8_t> has_normal_;
  std::vector<std::uint8_t> interior_;  // the unknowns (the border is h = 0)
  std::vector<double> h_;
  Raster raster_;
  // Per grid edge, indexed by its first node: weighted sum of slope targets and of weights
  // (u: edge i -> i + 1, v: edge i -> i + w).
  std::vector<double> target_u_, weight_u_, target_v_, weight_v_;
  std::vector<double> edge_u_, edge_v_, rhs_;  // the pass's edge weights and right-hand side
  GridLaplacianSolver solver_;
};

}  // namespace

HeightFieldResult IntegrateHeightField(const SurfaceMap& map, const FisheyeCamera& camera,
                                       const cv::Rect& roi, const cv::Mat& normals,
                                       const HeightFieldOptions& options,
                                       const cv::Mat& initial_height) {
  CheckInputs(map, roi, normals, options, initial_height);
  return HeightFieldSolver(map, camera, roi, normals, options, initial_height).Solve();
}

}  // namespace gs360
