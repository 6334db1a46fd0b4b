#pragma once
// From surface normals to distance along the rays, for a curved sensor seen by a central camera
// (docs/design.md, "Reconstruction"). With d(u, v) the unit ray and rho the distance along it to
// the (deformed) surface, x = rho d, and n the surface normal there:
//     d(log rho)/du = -(n.d_u)/(n.d),   d(log rho)/dv = -(n.d_v)/(n.d)      (exact)
// We integrate psi = log rho - log rho0 (rho0 the undeformed surface's distance, from the surface
// map), whose gradient is the formula above minus the same formula with n0, on a rectangular
// region of interest with psi = 0 on its border (the gel outside the ROI is undeformed). Then
// rho = rho0 e^psi.
//
// Two integrators, both reported by validation:
//   kPoisson: plain least squares (the Poisson equation) solved exactly on the rectangle with
//     a DST-I (FFTW RODFT00) fast solver -- the paper's method with the log-distance formula. It
//     errs where the indentation, seen obliquely, hides the wall behind it: at that occluding
//     contour rho jumps and no normal says by how much.
//   kDiscontinuityAware (default): weighted least squares whose edge weights drop across depth
//     discontinuities (grazing normals, n.d -> 0, and large one-sided disagreement), so that the
//     occluded side is tied to the undeformed surface through the region's border instead of
//     being dragged by the bump.
// Pixels with unknown gradients (fins, masked) are filled: Poisson inpaints them smoothly,
// weighted least squares gives them zero data weight.
//
// Images: roi-sized cv::Mat, CV_64F, row = v, column = u (relative to roi.tl()).

#include <opencv2/core/mat.hpp>
#include <string_view>

#include "recon/height_field.h"
#include "recon/surface_map.h"

namespace gs360 {

struct GradientOptions {
  // Pixels whose normal is within this angle of grazing (|n.d| < sin(angle)) get no gradient
  // (valid = 0): the division would explode. Degrees, [0, 45).
  double min_grazing_deg = 3.0;
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("min_grazing_deg", self.min_grazing_deg);
  }
  void Check() const;
};

struct LogDepthGradients {
  cv::Rect roi;     // image pixels
  cv::Mat gu;       // CV_64F d(psi)/du, 0 where not valid
  cv::Mat gv;       // CV_64F d(psi)/dv
  cv::Mat valid;    // CV_8U 255 = gradient known
  cv::Mat n_dot_d;  // CV_64F n.d (negative for a surface facing the camera), NaN where unknown
};

// normals: roi-sized CV_64FC3, camera-frame unit normals of the deformed surface (NaN = unknown,
// e.g. not visible). Pixels not visible in the map are not valid. Throws std::invalid_argument
// for a roi outside the map or a size mismatch.
LogDepthGradients ComputeLogDepthGradients(const SurfaceMap& map, const cv::Rect& roi,
                                           const cv::Mat& normals,
                                           const GradientOptions& options = {});

// kPoisson and kDiscontinuityAware integrate psi = log(rho / rho0) over the pixel grid (this
// file); kHeightField integrates the indentation along n0 over the undeformed surface
// (recon/height_field.h: it needs the camera, so the Reconstructor runs it).
enum class IntegrationMethod { kPoisson, kDiscontinuityAware, kHeightField };
std::string_view ToString(IntegrationMethod m);
// "poisson", "discontinuity", "heightfield"
IntegrationMethod ParseIntegrationMethod(std::string_view s);

struct IntegrationOptions {
  IntegrationMethod method = IntegrationMethod::kHeightField;
  // Discontinuity-aware weights (see integration.cc for their meaning).
  int iterations = 5;       // bilateral re-weighting passes, 1..1000
  double sharpness = 20.0;  // slope of the weights' sigmoid, > 0
  // The one-sided residual scale (psi per pixel) under which two
  // sides are considered equally good (> 0); the smallest edge weight (keeps the system
  // positive definite, (0, 1]); stop when psi changes less than this between passes (>= 0).
  double scale = 1e-3;
  double min_weight = 1e-4;
  double tolerance = 1e-7;
  HeightFieldOptions height_field;  // kHeightField only
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("method", self.method);
    visit("iterations", self.iterations);
    visit("sharpness", self.sharpness);
    visit("scale", self.scale);
    visit("min_weight", self.min_weight);
    visit("tolerance", self.tolerance);
    visit("height_field", self.height_field);
  }
  void Check() const;
};

struct IntegrationResult {
  cv::Mat psi;  // CV_64F roi-sized, psi = log(rho / rho0), 0 on the border
  cv::Mat rho;  // CV_64F roi-sized, rho0 e^psi (NaN where the map has no gel)
  int iterations = 0;
  double seconds = 0.0;
};

// Solves for psi on g.roi with psi = 0 on the roi's border. Throws std::invalid_argument for a roi
// smaller than 3 x 3, sizes that do not match, or the kHeightField method.
IntegrationResult IntegrateLogDepth(const SurfaceMap& map, const LogDepthGradients& g,
                                    const IntegrationOptions& options = {});

// Indentation along the undeformed normal, (rho0 - rho) |d . n0| (mm, + into the gel), for rho
// over roi (CV_64F roi-sized); NaN where the map has no gel or rho is not finite. Throws
// std::invalid_argument for a rho of the wrong type or size.
cv::Mat IndentationFromRho(const SurfaceMap& map, const cv::Rect& roi, const cv::Mat& rho);

// How far the gel moved along its own normal (mm, + into the gel) to reach each reconstructed
// point x = rho d: the h with x = x0' - h n0' for the undeformed surface point x0' (normal n0')
// whose normal line passes through x. That is what an indentation depth means on a curved gel,
// and what the gel's own displacement is. IndentationFromRho projects the along-ray gap on the
// pixel's own undeformed normal instead: the same at the deepest point of an exact surface, but
// where a reconstructed point sits sideways of its pixel's surface point (rims, bridged hidden
// parts) it measures to the wrong tangent plane and reads the peak too deep on average; this one
// far less (figures in docs/benchmarks.md, "Calibration", session 5, "Peak"). Found by a few
// foot-point steps: the foot of x on the tangent plane at x0, projected through `camera` (the
// map's) to the pixel whose x0 is next.
// Where a step lands off the visible surface (a fin, the image's edge), the last valid step's
// value is kept. NaN where the map has no gel or rho is not finite. Throws
// std::invalid_argument for a rho of the wrong type or size.
cv::Mat NormalIndentation(const SurfaceMap& map, const FisheyeCamera& camera, const cv::Rect& roi,
                          const cv::Mat& rho);

// The DST-I Poisson solver itself: solves lap(psi) = f on the interior of a w x h grid with
// psi = 0 on the outer boundary ring (first/last row and column are boundary, value 0). f is
// CV_64F h x w; the result has the same size with a zero border. Exposed for tests and reuse.
cv::Mat SolvePoissonDirichlet(const cv::Mat& f);

}  // namespace gs360
