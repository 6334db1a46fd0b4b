#include "recon/integration.h"

#include <fftw3.h>

#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <numbers>
#include <sstream>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "base/field_error.h"

namespace gs360 {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

[[noreturn]] void BadField(const char* type, const char* field, double v, const char* rule) {
  ThrowFieldError(std::string(type) + "." + field, v, rule);
}

// 64-byte aligned scratch for fftw_execute_r2r (plans are made on arrays of the same alignment).
// std::aligned_alloc rather than fftw_malloc: FFTW documents only the execute functions as
// thread-safe.
struct FftwBuffer {
  explicit FftwBuffer(std::size_t n)
      : data(static_cast<double*>(std::aligned_alloc(64, ((n * sizeof(double) + 63) / 64) * 64))) {
    if (data == nullptr) throw std::runtime_error("SolvePoissonDirichlet: out of memory");
  }
  ~FftwBuffer() { std::free(data); }
  FftwBuffer(const FftwBuffer&) = delete;
  FftwBuffer& operator=(const FftwBuffer&) = delete;
  double* data;
};

// ---------------------------------------------------------------------------------------------
// DST-I plans, cached per size. FFTW's planner is not thread-safe: creation is serialised by a
// mutex; fftw_execute_r2r on other (equally aligned) arrays is thread-safe.
class DstPlans {
 public:
  static DstPlans& Instance() {
    static DstPlans plans;
    return plans;
  }
  // 2-D RODFT00 of an ny x nx row-major array, out of place.
  fftw_plan Get(int ny, int nx) {
    std::lock_guard<std::mutex> lock(mutex_);
    auto it = plans_.find({ny, nx});
    if (it != plans_.end()) return it->second;
    const std::size_t n = static_cast<std::size_t>(ny) * static_cast<std::size_t>(nx);
    FftwBuffer in(n), out(n);
    // FFTW_ESTIMATE does not touch the arrays' contents while planning.
    fftw_plan plan =
        fftw_plan_r2r_2d(ny, nx, in.data, out.data, FFTW_RODFT00, FFTW_RODFT00, FFTW_ESTIMATE);
    if (plan == nullptr) {
      throw std::runtime_error("SolvePoissonDirichlet: fftw_plan_r2r_2d failed for " +
                               std::to_string(ny) + " x " + std::to_string(nx));
    }
    plans_.emplace(std::make_pair(ny, nx), plan);
    return plan;
  }
  ~DstPlans() {
    for (auto& [size, plan] : plans_) fftw_destroy_plan(plan);
  }

 private:
  DstPlans() = default;
  std::mutex mutex_;
  std::map<std::pair<int, int>, fftw_plan> plans_;
};

// ---------------------------------------------------------------------------------------------
// Edge data shared by both integrators. Pixel (y, x) of an h x w roi; horizontal edge (y, x)
// joins (y, x) and (y, x + 1), vertical edge (y, x) joins (y, x) and (y + 1, x). The edge value
// is the trapezoid estimate of the psi difference, (g(a) + g(b)) / 2, which makes the plain
// least-squares solution second-order accurate.
struct EdgeData {
  int h = 0, w = 0;
  cv::Mat gu, gv;  // CV_64F, gradients after inpainting
  cv::Mat eu;      // CV_64F h x (w - 1)
  cv::Mat ev;      // CV_64F (h - 1) x w
};

// Fills the gradients of pixels that are not valid by harmonic interpolation (a Laplace
// equation over the invalid pixels, the valid ones fixed, pixels outside the roi counting as
// 0: the gel outside the roi is undeformed). Connected invalid areas far from any valid pixel
// therefore fade to 0.
void InpaintGradients(const cv::Mat& valid, cv::Mat& gu, cv::Mat& gv) {
  const int h = valid.rows, w = valid.cols;
  std::vector<int> index(static_cast<std::size_t>(h) * w, -1);
  int n = 0;
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x)
      if (valid.at<std::uint8_t>(y, x) == 0) index[static_cast<std::size_t>(y) * w + x] = n++;
  if (n == 0) return;
  std::vector<Eigen::Triplet<double>> triplets;
  triplets.reserve(static_cast<std::size_t>(n) * 5);
  Eigen::MatrixXd rhs = Eigen::MatrixXd::Zero(n, 2);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const int i = index[static_cast<std::size_t>(y) * w + x];
      if (i < 0) continue;
      triplets.emplace_back(i, i, 4.0);
      const int nb[4][2] = {{y, x - 1}, {y, x + 1}, {y - 1, x}, {y + 1, x}};
      for (const auto& p : nb) {
        if (p[0] < 0 || p[1] < 0 || p[0] >= h || p[1] >= w) continue;  // outside: value 0
        const int j = index[static_cast<std::size_t>(p[0]) * w + p[1]];
        if (j >= 0) {
          triplets.emplace_back(i, j, -1.0);
        } else {
          rhs(i, 0) += gu.at<double>(p[0], p[1]);
          rhs(i, 1) += gv.at<double>(p[0], p[1]);
        }
      }
    }
  }
  Eigen::SparseMatrix<double> a(n, n);
  a.setFromTriplets(triplets.begin(), triplets.end());
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> solver(a);
  if (solver.info() != Eigen::Success) throw std::runtime_error("gradient inpainting: LDLT failed");
  const Eigen::MatrixXd sol = solver.solve(rhs);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const int i = index[static_cast<std::size_t>(y) * w + x];
      if (i < 0) continue;
      gu.at<double>(y, x) = sol(i, 0);
      gv.at<double>(y, x) = sol(i, 1);
    }
  }
}

EdgeData MakeEdges(const LogDepthGradients& g) {
  EdgeData e;
  e.h = g.roi.height;
  e.w = g.roi.width;
  e.gu = g.gu.clone();
  e.gv = g.gv.clone();
  for (int y = 0; y < e.h; ++y)
    for (int x = 0; x < e.w; ++x)
      if (g.valid.at<std::uint8_t>(y, x) == 0) e.gu.at<double>(y, x) = e.gv.at<double>(y, x) = 0.0;
  InpaintGradients(g.valid, e.gu, e.gv);
  e.eu = cv::Mat(e.h, e.w - 1, CV_64F);
  e.ev = cv::Mat(e.h - 1, e.w, CV_64F);
  for (int y = 0; y < e.h; ++y)
    for (int x = 0; x + 1 < e.w; ++x)
      e.eu.at<double>(y, x) = 0.5 * (e.gu.at<double>(y, x) + e.gu.at<double>(y, x + 1));
  for (int y = 0; y + 1 < e.h; ++y)
    for (int x = 0; x < e.w; ++x)
      e.ev.at<double>(y, x) = 0.5 * (e.gv.at<double>(y, x) + e.gv.at<double>(y + 1, x));
  return e;
}

cv::Mat SolvePoisson(const EdgeData& e) {
  // Normal equations of sum over edges (psi_b - psi_a - e)^2 with psi = 0 on the border:
  // lap(psi) = div(e) at the interior pixels.
  cv::Mat f = cv::Mat::zeros(e.h, e.w, CV_64F);
  for (int y = 1; y + 1 < e.h; ++y) {
    for (int x = 1; x + 1 < e.w; ++x) {
      f.at<double>(y, x) = e.eu.at<double>(y, x) - e.eu.at<double>(y, x - 1) +
                           e.ev.at<double>(y, x) - e.ev.at<double>(y - 1, x);
    }
  }
  return SolvePoissonDirichlet(f);
}

// ---------------------------------------------------------------------------------------------
// Discontinuity-aware integration: bilateral normal integration (Cao et al., ECCV 2022) on the
// trapezoid edge data. Every pixel p owns a forward and a backward residual per axis,
//   r+ = psi(p + 1) - psi(p) - e(p, p + 1),   r- = psi(p) - psi(p - 1) - e(p - 1, p),
// weighted w+ and w- = 1 - w+. With all weights 1/2 this is exactly the Poisson problem above.
// Each iteration sets
//   w+ = sigmoid(sharpness * ((d-)^2 - (d+)^2) / ((d-)^2 + (d+)^2 + eps^2))
// from the current one-sided differences d+- of psi: a pixel next to a jump leans on its other
// side, so the edge across the jump loses (almost) all its weight and the occluded side is tied
// to the border instead of to the bump. The weights of an edge add up:
// W(p, p + 1) = w+(p) + w-(p + 1).
class BilateralSolver {
 public:
  BilateralSolver(const EdgeData& e, const IntegrationOptions& o) : e_(e), o_(o) {
    nx_ = e.w - 2;
    ny_ = e.h - 2;
    n_ = nx_ * ny_;
  }

  cv::Mat Solve(const cv::Mat& psi_init, int* iterations) {
    cv::Mat psi = psi_init.clone();
    const int h = e_.h, w = e_.w;
    cv::Mat wu(h, w - 1, CV_64F), wv(h - 1, w, CV_64F);  // edge weights
    for (int it = 0; it < o_.iterations; ++it) {
      EdgeWeights(psi, wu, wv);
      cv::Mat next = SolveWeighted(wu, wv);
      double change = 0.0;
      for (int y = 0; y < h; ++y)
        for (int x = 0; x < w; ++x)
          change = std::max(change, std::abs(next.at<double>(y, x) - psi.at<double>(y, x)));
      psi = next;
      *iterations = it + 1;
      if (change < o_.tolerance) break;
    }
    return psi;
  }

 private:
  double Sigmoid(double dm, double dp) const {
    const double eps2 = o_.scale * o_.scale;
    const double x = (dm * dm - dp * dp) / (dm * dm + dp * dp + eps2);
    return 1.0 / (1.0 + std::exp(-o_.sharpness * x));
  }

  void EdgeWeights(const cv::Mat& psi, cv::Mat& wu, cv::Mat& wv) const {
    const int h = e_.h, w = e_.w;
    wu.setTo(0.0);
    wv.setTo(0.0);
    for (int y = 0; y < h; ++y) {
      for (int x = 0; x < w; ++x) {
        const double p = psi.at<double>(y, x);
        // u: forward edge (y, x), backward edge (y, x - 1).
        const bool has_f = x + 1 < w, has_b = x > 0;
        if (has_f && has_b) {
          const double dp = psi.at<double>(y, x + 1) - p - e_.eu.at<double>(y, x);
          const double dm = p - psi.at<double>(y, x - 1) - e_.eu.at<double>(y, x - 1);
          const double wp = Sigmoid(dm, dp);
          wu.at<double>(y, x) += wp;
          wu.at<double>(y, x - 1) += 1.0 - wp;
        } else if (has_f) {
          wu.at<double>(y, x) += 0.5;
        } else if (has_b) {
          wu.at<double>(y, x - 1) += 0.5;
        }
        const bool has_fv = y + 1 < h, has_bv = y > 0;
        if (has_fv && has_bv) {
          const double dp = psi.at<double>(y + 1, x) - p - e_.ev.at<double>(y, x);
          const double dm = p - psi.at<double>(y - 1, x) - e_.ev.at<double>(y - 1, x);
          const double wp = Sigmoid(dm, dp);
          wv.at<double>(y, x) += wp;
          wv.at<double>(y - 1, x) += 1.0 - wp;
        } else if (has_fv) {
          wv.at<double>(y, x) += 0.5;
        } else if (has_bv) {
          wv.at<double>(y - 1, x) += 0.5;
        }
      }
    }
    const double floor = o_.min_weight;
    for (int y = 0; y < wu.rows; ++y)
      for (int x = 0; x < wu.cols; ++x) wu.at<double>(y, x) = std::max(floor, wu.at<double>(y, x));
    for (int y = 0; y < wv.rows; ++y)
      for (int x = 0; x < wv.cols; ++x) wv.at<double>(y, x) = std::max(floor, wv.at<double>(y, x));
  }

  int Id(int y, int x) const { return (y - 1) * nx_ + (x - 1); }
  bool Interior(int y, int x) const { return y >= 1 && x >= 1 && y <= ny_ && x <= nx_; }

  // Builds the fixed sparsity pattern (5-point stencil over the interior pixels) once and
  // records, per edge, where its entries live in the matrix's value array; later passes only
  // rewrite the values and refactorise (the symbolic analysis is done once).
  struct EdgeSlots {
    int a = -1, b = -1;                      // unknown ids (-1 = border pixel, psi fixed at 0)
    int aa = -1, bb = -1, ab = -1, ba = -1;  // positions in the value array
  };
  void BuildPattern() {
    std::vector<Eigen::Triplet<double>> triplets;
    triplets.reserve(static_cast<std::size_t>(n_) * 5);
    for (int y = 1; y <= ny_; ++y) {
      for (int x = 1; x <= nx_; ++x) {
        const int i = Id(y, x);
        triplets.emplace_back(i, i, 1.0);
        if (x + 1 <= nx_)
          triplets.emplace_back(i, Id(y, x + 1), 1.0), triplets.emplace_back(Id(y, x + 1), i, 1.0);
        if (y + 1 <= ny_)
          triplets.emplace_back(i, Id(y + 1, x), 1.0), triplets.emplace_back(Id(y + 1, x), i, 1.0);
      }
    }
    a_.resize(n_, n_);
    a_.setFromTriplets(triplets.begin(), triplets.end());
    a_.makeCompressed();
    auto slot = [&](int r, int c) {
      const int* inner = a_.innerIndexPtr();
      const int* lo = inner + a_.outerIndexPtr()[c];
      const int* hi = inner + a_.outerIndexPtr()[c + 1];
      return static_cast<int>(std::lower_bound(lo, hi, r) - inner);
    };
    auto make = [&](int ya, int xa, int yb, int xb) {
      EdgeSlots s;
      if (Interior(ya, xa)) s.a = Id(ya, xa), s.aa = slot(s.a, s.a);
      if (Interior(yb, xb)) s.b = Id(yb, xb), s.bb = slot(s.b, s.b);
      if (s.a >= 0 && s.b >= 0) s.ab = slot(s.a, s.b), s.ba = slot(s.b, s.a);
      return s;
    };
    hslots_.clear();
    vslots_.clear();
    for (int y = 0; y < e_.h; ++y)
      for (int x = 0; x + 1 < e_.w; ++x) hslots_.push_back(make(y, x, y, x + 1));
    for (int y = 0; y + 1 < e_.h; ++y)
      for (int x = 0; x < e_.w; ++x) vslots_.push_back(make(y, x, y + 1, x));
    solver_.analyzePattern(a_);
    analyzed_ = true;
  }

  // Minimises sum W (psi_b - psi_a - e)^2 with psi = 0 on the border.
  cv::Mat SolveWeighted(const cv::Mat& wu, const cv::Mat& wv) {
    if (!analyzed_) BuildPattern();
    double* val = a_.valuePtr();
    std::fill(val, val + a_.nonZeros(), 0.0);
    Eigen::VectorXd rhs = Eigen::VectorXd::Zero(n_);
    auto add = [&](const EdgeSlots& s, double weight, double value) {
      if (s.a >= 0) val[s.aa] += weight, rhs[s.a] -= weight * value;
      if (s.b >= 0) val[s.bb] += weight, rhs[s.b] += weight * value;
      if (s.ab >= 0) val[s.ab] -= weight, val[s.ba] -= weight;
    };
    std::size_t k = 0;
    for (int y = 0; y < e_.h; ++y) {
      const double* w = wu.ptr<double>(y);
      const double* e = e_.eu.ptr<double>(y);
      for (int x = 0; x + 1 < e_.w; ++x) add(hslots_[k++], w[x], e[x]);
    }
    k = 0;
    for (int y = 0; y + 1 < e_.h; ++y) {
      const double* w = wv.ptr<double>(y);
      const double* e = e_.ev.ptr<double>(y);
      for (int x = 0; x < e_.w; ++x) add(vslots_[k++], w[x], e[x]);
    }
    solver_.factorize(a_);
    if (solver_.info() != Eigen::Success) {
      throw std::runtime_error("IntegrateLogDepth: weighted least squares factorisation failed");
    }
    const Eigen::VectorXd sol = solver_.solve(rhs);
    cv::Mat psi = cv::Mat::zeros(e_.h, e_.w, CV_64F);
    for (int y = 1; y <= ny_; ++y) {
      double* row = psi.ptr<double>(y);
      for (int x = 1; x <= nx_; ++x) row[x] = sol[Id(y, x)];
    }
    return psi;
  }

  const EdgeData& e_;
  const IntegrationOptions& o_;
  int nx_ = 0, ny_ = 0, n_ = 0;
  bool analyzed_ = false;
  Eigen::SparseMatrix<double> a_;
  std::vector<EdgeSlots> hslots_, vslots_;
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> solver_;
};

}  // namespace

void GradientOptions::Check() const {
  if (!(min_grazing_deg >= 0.0) || !(min_grazing_deg < 45.0)) {
    BadField("GradientOptions", "min_grazing_deg", min_grazing_deg, "must be in [0, 45) deg");
  }
}

void IntegrationOptions::Check() const {
  if (method != IntegrationMethod::kPoisson && method != IntegrationMethod::kDiscontinuityAware &&
      method != IntegrationMethod::kHeightField) {
    BadField("IntegrationOptions", "method", static_cast<double>(method), "is not a known method");
  }
  if (iterations < 1 || iterations > 1000) {
    BadField("IntegrationOptions", "iterations", iterations, "must be in 1..1000");
  }
  if (!(sharpness > 0.0) || !std::isfinite(sharpness)) {
    BadField("IntegrationOptions", "sharpness", sharpness, "must be finite and > 0");
  }
  if (!(scale > 0.0) || !std::isfinite(scale)) {
    BadField("IntegrationOptions", "scale", scale, "must be finite and > 0");
  }
  if (!(min_weight > 0.0) || !(min_weight <= 1.0)) {
    BadField("IntegrationOptions", "min_weight", min_weight, "must be in (0, 1]");
  }
  if (!(tolerance >= 0.0) || !std::isfinite(tolerance)) {
    BadField("IntegrationOptions", "tolerance", tolerance, "must be finite and >= 0");
  }
  height_field.Check();
}

std::string_view ToString(IntegrationMethod m) {
  switch (m) {
    case IntegrationMethod::kPoisson:
      return "poisson";
    case IntegrationMethod::kDiscontinuityAware:
      return "discontinuity";
    case IntegrationMethod::kHeightField:
      return "heightfield";
  }
  return "unknown";
}

IntegrationMethod ParseIntegrationMethod(std::string_view s) {
  if (s == "poisson") return IntegrationMethod::kPoisson;
  if (s == "discontinuity" || s == "discontinuity-aware" || s == "bilateral") {
    return IntegrationMethod::kDiscontinuityAware;
  }
  if (s == "heightfield" || s == "height-field") return IntegrationMethod::kHeightField;
  throw std::invalid_argument("unknown integration method \"" + std::string(s) +
                              "\" (accepted: poisson, discontinuity, heightfield)");
}

LogDepthGradients ComputeLogDepthGradients(const SurfaceMap& map, const cv::Rect& roi,
                                           const cv::Mat& normals, const GradientOptions& options) {
  options.Check();
  if (roi.x < 0 || roi.y < 0 || roi.width <= 0 || roi.height <= 0 ||
      roi.x + roi.width > map.width() || roi.y + roi.height > map.height()) {
    std::ostringstream os;
    os << "ComputeLogDepthGradients: roi (" << roi.x << ", " << roi.y << ", " << roi.width << " x "
       << roi.height << ") is not inside the " << map.width() << " x " << map.height() << " map";
    throw std::invalid_argument(os.str());
  }
  if (normals.type() != CV_64FC3 || normals.rows != roi.height || normals.cols != roi.width) {
    std::ostringstream os;
    os << "ComputeLogDepthGradients: normals must be CV_64FC3 " << roi.width << " x " << roi.height
       << ", got type " << normals.type() << " " << normals.cols << " x " << normals.rows;
    throw std::invalid_argument(os.str());
  }
  const double min_nd = std::sin(options.min_grazing_deg * std::numbers::pi / 180.0);
  LogDepthGradients g;
  g.roi = roi;
  g.gu = cv::Mat::zeros(roi.height, roi.width, CV_64F);
  g.gv = cv::Mat::zeros(roi.height, roi.width, CV_64F);
  g.valid = cv::Mat::zeros(roi.height, roi.width, CV_8U);
  g.n_dot_d = cv::Mat(roi.height, roi.width, CV_64F, cv::Scalar(kNaN));
  for (int y = 0; y < roi.height; ++y) {
    for (int x = 0; x < roi.width; ++x) {
      const int u = roi.x + x, v = roi.y + y;
      if (!map.visible(u, v)) continue;
      const cv::Vec3d nv = normals.at<cv::Vec3d>(y, x);
      Eigen::Vector3d n(nv[0], nv[1], nv[2]);
      if (!n.allFinite() || !(n.norm() > 0.0)) continue;
      n.normalize();
      const Eigen::Vector3d d = map.ray(u, v), du = map.ray_du(u, v), dv = map.ray_dv(u, v);
      const Eigen::Vector3d n0 = map.normal0(u, v);
      const double nd = n.dot(d);
      const double n0d = n0.dot(d);
      g.n_dot_d.at<double>(y, x) = nd;
      // A visible map pixel has |n0.d| >= cos(max view angle) > 0; the deformed normal is
      // guarded here.
      if (!(std::abs(nd) >= min_nd) || nd == 0.0 || n0d == 0.0) continue;
      g.gu.at<double>(y, x) = -n.dot(du) / nd + n0.dot(du) / n0d;
      g.gv.at<double>(y, x) = -n.dot(dv) / nd + n0.dot(dv) / n0d;
      g.valid.at<std::uint8_t>(y, x) = 255;
    }
  }
  return g;
}

cv::Mat SolvePoissonDirichlet(const cv::Mat& f) {
  if (f.type() != CV_64F || f.rows < 3 || f.cols < 3) {
    throw std::invalid_argument("SolvePoissonDirichlet: f must be CV_64F and at least 3 x 3, got " +
                                std::to_string(f.cols) + " x " + std::to_string(f.rows));
  }
  const int ny = f.rows - 2, nx = f.cols - 2;
  const std::size_t n = static_cast<std::size_t>(ny) * static_cast<std::size_t>(nx);
  const fftw_plan plan = DstPlans::Instance().Get(ny, nx);
  FftwBuffer a(n), b(n);
  for (int y = 0; y < ny; ++y)
    for (int x = 0; x < nx; ++x)
      a.data[static_cast<std::size_t>(y) * nx + x] = f.at<double>(y + 1, x + 1);
  fftw_execute_r2r(plan, a.data, b.data);
  // Eigenvalues of the 5-point Laplacian with Dirichlet 0: 2 cos(pi k / (n + 1)) - 2.
  std::vector<double> lx(static_cast<std::size_t>(nx)), ly(static_cast<std::size_t>(ny));
  for (int k = 0; k < nx; ++k) lx[k] = 2.0 * std::cos(std::numbers::pi * (k + 1) / (nx + 1)) - 2.0;
  for (int k = 0; k < ny; ++k) ly[k] = 2.0 * std::cos(std::numbers::pi * (k + 1) / (ny + 1)) - 2.0;
  const double norm = 4.0 * (nx + 1) * (ny + 1);  // RODFT00 applied twice in 2-D
  for (int y = 0; y < ny; ++y)
    for (int x = 0; x < nx; ++x)
      b.data[static_cast<std::size_t>(y) * nx + x] /= (lx[x] + ly[y]) * norm;
  fftw_execute_r2r(plan, b.data, a.data);
  cv::Mat psi = cv::Mat::zeros(f.rows, f.cols, CV_64F);
  for (int y = 0; y < ny; ++y)
    for (int x = 0; x < nx; ++x)
      psi.at<double>(y + 1, x + 1) = a.data[static_cast<std::size_t>(y) * nx + x];
  return psi;
}

IntegrationResult IntegrateLogDepth(const SurfaceMap& map, const LogDepthGradients& g,
                                    const IntegrationOptions& options) {
  options.Check();
  if (options.method == IntegrationMethod::kHeightField) {
    throw std::invalid_argument(
        "IntegrateLogDepth: the height-field method integrates slopes, not log-depth gradients "
        "(recon/height_field.h IntegrateHeightField, or Reconstructor::IntegrateSlopes)");
  }
  const auto start = std::chrono::steady_clock::now();
  const cv::Rect& roi = g.roi;
  if (roi.width < 3 || roi.height < 3) {
    throw std::invalid_argument("IntegrateLogDepth: roi must be at least 3 x 3, got " +
                                std::to_string(roi.width) + " x " + std::to_string(roi.height));
  }
  if (roi.x < 0 || roi.y < 0 || roi.x + roi.width > map.width() ||
      roi.y + roi.height > map.height()) {
    throw std::invalid_argument("IntegrateLogDepth: roi is not inside the map");
  }
  const cv::Size size(roi.width, roi.height);
  if (g.gu.size() != size || g.gv.size() != size || g.valid.size() != size ||
      g.gu.type() != CV_64F || g.gv.type() != CV_64F || g.valid.type() != CV_8U) {
    throw std::invalid_argument(
        "IntegrateLogDepth: gu, gv (CV_64F) and valid (CV_8U) must be roi-sized");
  }
  const EdgeData edges = MakeEdges(g);
  IntegrationResult result;
  result.psi = SolvePoisson(edges);
  if (options.method == IntegrationMethod::kDiscontinuityAware) {
    BilateralSolver solver(edges, options);
    result.psi = solver.Solve(result.psi, &result.iterations);
  }
  result.rho = cv::Mat(size, CV_64F);
  for (int y = 0; y < roi.height; ++y) {
    for (int x = 0; x < roi.width; ++x) {
      const double rho0 = map.rho0(roi.x + x, roi.y + y);
      result.rho.at<double>(y, x) =
          rho0 > 0.0 ? rho0 * std::exp(result.psi.at<double>(y, x)) : kNaN;
    }
  }
  result.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return result;
}

cv::Mat IndentationFromRho(const SurfaceMap& map, const cv::Rect& roi, const cv::Mat& rho) {
  if (rho.type() != CV_64F || rho.size() != roi.size()) {
    throw std::invalid_argument("IndentationFromRho: rho must be CV_64F of the roi's size");
  }
  cv::Mat out(roi.size(), CV_64F, cv::Scalar::all(kNaN));
  for (int y = 0; y < roi.height; ++y) {
    for (int x = 0; x < roi.width; ++x) {
      const int u = roi.x + x, v = roi.y + y;
      const double r = rho.at<double>(y, x);
      if (!map.visible(u, v) || !std::isfinite(r)) continue;
      out.at<double>(y, x) = (map.rho0(u, v) - r) * std::abs(map.ray(u, v).dot(map.normal0(u, v)));
    }
  }
  return out;
}

cv::Mat NormalIndentation(const SurfaceMap& map, const FisheyeCamera& camera, const cv::Rect& roi,
                          const cv::Mat& rho) {
  if (rho.type() != CV_64F || rho.size() != roi.size()) {
    throw std::invalid_argument("NormalIndentation: rho must be CV_64F of the roi's size");
  }
  constexpr int kSteps = 4;  // the foot moves by about h tan(view angle); 2-3 steps settle it
  cv::Mat out(roi.size(), CV_64F, cv::Scalar::all(kNaN));
  for (int y = 0; y < roi.height; ++y) {
    for (int x = 0; x < roi.width; ++x) {
      int u = roi.x + x, v = roi.y + y;
      const double r = rho.at<double>(y, x);
      if (!map.visible(u, v) || !std::isfinite(r)) continue;
      const Eigen::Vector3d p = r * map.ray(u, v);
      double h = (map.point0(u, v) - p).dot(map.normal0(u, v));
      for (int step = 0; step < kSteps; ++step) {
        const Eigen::Vector3d foot = p + h * map.normal0(u, v);
        const auto uv = camera.CamToPixel(foot);
        if (!uv) break;
        const int nu = static_cast<int>(std::lround(uv->x()));
        const int nv = static_cast<int>(std::lround(uv->y()));
        if (nu < 0 || nv < 0 || nu >= map.width() || nv >= map.height() || !map.visible(nu, nv)) {
          break;
        }
        if (nu == u && nv == v) break;  // settled
        u = nu, v = nv;
        h = (map.point0(u, v) - p).dot(map.normal0(u, v));
      }
      out.at<double>(y, x) = h;
    }
  }
  return out;
}

}  // namespace gs360
