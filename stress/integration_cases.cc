// Integration at its edges: slopes that are zero, huge, NaN or discontinuous, through the model's
// own integrator (Reconstructor::IntegrateSlopes: normals, log-depth gradients, the height field
// passes), and the height field's grid solver with extreme weights.

#include <cmath>
#include <limits>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "recon/grid_solver.h"
#include "recon/model_bundle.h"
#include "recon/reconstructor.h"
#include "stress/stress_cases.h"

namespace gs360::stress {
namespace {

constexpr int kRoiSize = 64;

// The kRoiSize square of pixels the camera sees entirely that lies nearest to halfway between
// the image centre and the image circle's rim (where a contact on the side of a finger shows).
cv::Rect VisibleRoi(const SurfaceMap& map) {
  cv::Mat visible(map.height(), map.width(), CV_8U);
  for (int v = 0; v < map.height(); ++v) {
    for (int u = 0; u < map.width(); ++u) visible.at<std::uint8_t>(v, u) = map.visible(u, v);
  }
  cv::Mat sum;
  cv::integral(visible, sum, CV_32S);
  const cv::Point2d target(0.5 * map.width() + 0.25 * map.height(), 0.5 * map.height());
  cv::Rect best;
  double best_distance = 1e300;
  for (int y = 0; y + kRoiSize <= map.height(); y += 2) {
    for (int x = 0; x + kRoiSize <= map.width(); x += 2) {
      const int count = sum.at<int>(y + kRoiSize, x + kRoiSize) - sum.at<int>(y, x + kRoiSize) -
                        sum.at<int>(y + kRoiSize, x) + sum.at<int>(y, x);
      if (count != kRoiSize * kRoiSize) continue;
      const cv::Point2d centre(x + 0.5 * kRoiSize, y + 0.5 * kRoiSize);
      const double d = cv::norm(centre - target);
      if (d < best_distance) {
        best_distance = d;
        best = cv::Rect(x, y, kRoiSize, kRoiSize);
      }
    }
  }
  if (best.empty()) throw std::runtime_error("the model's map has no 64 x 64 visible square");
  return best;
}

struct Depths {
  int visible = 0, nonfinite = 0;
  double max_abs_mm = 0.0;
  std::string Text() const {
    return Format("%d visible pixels: %d non-finite, largest |indentation| %.3g mm", visible,
                  nonfinite, max_abs_mm);
  }
};

Depths Inspect(const Reconstructor& r, const RegionReconstruction& out) {
  Depths d;
  const cv::Rect& roi = out.region.roi;
  for (int y = 0; y < roi.height; ++y) {
    for (int x = 0; x < roi.width; ++x) {
      if (!r.map().visible(roi.x + x, roi.y + y)) continue;
      ++d.visible;
      const double h = out.indentation.at<double>(y, x);
      if (!std::isfinite(h)) {
        ++d.nonfinite;
      } else {
        d.max_abs_mm = std::max(d.max_abs_mm, std::abs(h));
      }
    }
  }
  return d;
}

// Integrates `fill(x, y)` as the slopes of a kRoiSize region on the model's map.
Depths IntegrateField(const StressContext& c, const std::function<cv::Vec2f(int, int)>& fill) {
  if (!c.model) throw std::invalid_argument("no model given (StressContext.model)");
  const Reconstructor r = c.model->MakeReconstructor(1);
  ContactRegion region;
  region.roi = VisibleRoi(r.map());
  region.blob = region.roi;
  region.area_px = region.roi.area();
  cv::Mat slopes(region.roi.size(), CV_32FC2);
  for (int y = 0; y < slopes.rows; ++y) {
    for (int x = 0; x < slopes.cols; ++x) slopes.at<cv::Vec2f>(y, x) = fill(x, y);
  }
  return Inspect(r, r.IntegrateSlopes(slopes, region, r.options().integration));
}

StressCase Slopes(const std::string& name, const std::string& expected, double max_abs_mm,
                  std::function<cv::Vec2f(int, int)> fill) {
  return {"integration", name, expected,
          [max_abs_mm, fill](const StressContext& c, std::string* observed) {
            const Depths d = IntegrateField(c, fill);
            *observed = d.Text();
            return d.nonfinite == 0 && d.max_abs_mm <= max_abs_mm;
          }};
}

std::vector<StressCase> SlopeCases() {
  constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
  const float huge = 1e6f;
  return {
      Slopes("zero slopes over a 64 x 64 region (the undeformed gel)",
             "indentation at most 0.005 mm (a quarter of the 0.02 mm mean target) everywhere",
             0.005, [](int, int) { return cv::Vec2f(0.f, 0.f); }),
      Slopes("slopes of 1e6 everywhere (normals at grazing)",
             "finite everywhere, no deeper than the 1.5 mm gel", 1.5,
             [huge](int x, int) { return cv::Vec2f(x % 2 ? huge : -huge, huge); }),
      Slopes("NaN slopes at one pixel in 10", "finite everywhere, no deeper than the 1.5 mm gel",
             1.5,
             [kNaN](int x, int y) {
               return (x * 7 + y * 3) % 10 == 0 ? cv::Vec2f(kNaN, kNaN) : cv::Vec2f(0.1f, 0.f);
             }),
      Slopes("a step: slope +0.5 left of the middle, -0.5 right of it (a ridge)",
             "finite everywhere, at most 64 px x 0.5 x pixel pitch (< 8 mm)", 8.0,
             [](int x, int) { return cv::Vec2f(x < kRoiSize / 2 ? 0.5f : -0.5f, 0.f); }),
  };
}

// The height field's solver with edge weights spanning twelve orders of magnitude (the passes'
// weights fall by that much across a sharp edge): the residual of the solution, relative.
StressCase SolverContrast() {
  return {"integration", "grid solver, 40 x 40, edge weights from 1e-12 to 1",
          "factorises; normwise backward error ||Ax - b|| / (||A|| ||x|| + ||b||) at most 1e-13",
          [](const StressContext& c, std::string* observed) {
            const int w = 40, h = 40, n = w * h;
            std::mt19937_64 rng(c.seed);
            std::uniform_real_distribution<double> exponent(-12.0, 0.0), rhs(-1.0, 1.0);
            std::vector<double> wu(n), wv(n), b(n, 0.0);
            for (int i = 0; i < n; ++i) {
              wu[i] = std::pow(10.0, exponent(rng));
              wv[i] = std::pow(10.0, exponent(rng));
            }
            GridLaplacianSolver solver(w, h);
            if (!solver.Factorize(wu, wv)) {
              *observed = "Factorize refused the weights";
              return false;
            }
            const auto interior = [&](int x, int y) {
              return x >= 1 && x <= w - 2 && y >= 1 && y <= h - 2;
            };
            for (int y = 1; y < h - 1; ++y) {
              for (int x = 1; x < w - 1; ++x) b[y * w + x] = rhs(rng);
            }
            std::vector<double> x = b;
            solver.Solve(&x);
            // r = A x - b over the interior, A as grid_solver.h defines it (border values 0).
            double rr = 0.0, bb = 0.0, xx2 = 0.0, a_inf = 0.0;
            for (int y = 1; y < h - 1; ++y) {
              for (int xx = 1; xx < w - 1; ++xx) {
                const int i = y * w + xx;
                const double e[4] = {wu[i - 1], wu[i], wv[i - w], wv[i]};
                const int nb[4] = {i - 1, i + 1, i - w, i + w};
                double ax = 0.0;
                a_inf = std::max(a_inf, 2.0 * (e[0] + e[1] + e[2] + e[3]));
                xx2 += x[i] * x[i];
                for (int k = 0; k < 4; ++k) {
                  const int jx = nb[k] % w, jy = nb[k] / w;
                  ax += e[k] * (x[i] - (interior(jx, jy) ? x[nb[k]] : 0.0));
                }
                rr += (ax - b[i]) * (ax - b[i]);
                bb += b[i] * b[i];
              }
            }
            const double backward = std::sqrt(rr) / (a_inf * std::sqrt(xx2) + std::sqrt(bb));
            *observed = Format("backward error %.2g (relative residual %.2g)", backward,
                               std::sqrt(rr / bb));
            return std::isfinite(backward) && backward <= 1e-13;
          }};
}

StressCase SolverSingular() {
  return {"integration", "grid solver, a node whose four edges weigh 0",
          "Factorize returns false (not positive definite), no NaN",
          [](const StressContext&, std::string* observed) {
            const int w = 12, h = 10, n = w * h;
            std::vector<double> wu(n, 1.0), wv(n, 1.0);
            const int i = 5 * w + 6;
            wu[i] = wu[i - 1] = wv[i] = wv[i - w] = 0.0;
            GridLaplacianSolver solver(w, h);
            const bool ok = solver.Factorize(wu, wv);
            *observed = ok ? "factorised" : "refused";
            return !ok;
          }};
}

}  // namespace

std::vector<StressCase> IntegrationCases() {
  std::vector<StressCase> cases = SlopeCases();
  cases.push_back(SolverContrast());
  cases.push_back(SolverSingular());
  return cases;
}

}  // namespace gs360::stress
