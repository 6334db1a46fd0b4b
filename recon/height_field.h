#pragma once
// Integration of slopes as a height field over the undeformed gel surface: the reconstruction's
// answer to occlusion (docs/design.md, "Reconstruction").
//
// Seen from the base camera, an imprint in the side wall is a bump that hides the wall behind
// it: along a pixel's ray the deformed distance rho jumps at the occluding contour, and no normal
// says by how much. The indentation h measured along the undeformed normal is single-valued
// there. So the unknown is h(s) on the region's pixel grid s = (u, v), read as a
// parametrisation of the UNDEFORMED surface x0(s) (the surface map): the deformed surface is
// X(s) = x0(s) - h(s) n0(s), and where its normal is n (n is normal to dX/du and dX/dv),
//     dh/du = (n . dx0/du - h n . dn0/du) / (n . n0),  and the same along v
// (h in the curvature term from the previous pass). A pixel p does not see X(p) but the first point
// of X its ray meets, shifted along the wall by about h tan(view angle). Each pass therefore
//   1. projects the current surface X into the image and rasterises it with a depth buffer:
//      every pixel gets the grid position s'(p) of the point it sees and its distance rho(p);
//      grid points no pixel sees (behind the bump) get no data;
//   2. turns each pixel's observed normal n(p) (from the MLP's slopes) into targets for dh/du,
//      dh/dv at s'(p), each given to the two grid edges whose midpoints bracket s'(p) along
//      that direction (linearly weighted, on the nearest row; averaged where several land);
//   3. solves the weighted least squares  sum_edges w (h_b - h_a - t)^2  with h = 0 on the
//      region's border; edges without data get a small weight (a membrane: the hidden far side
//      of the imprint is bridged smoothly between the border and what is seen).
// It starts from `initial_height` when given (e.g. a plain Poisson solution's indentation,
// which is close where the view is steep and sets the scale of the shifts), else from h = 0, and
// stops after `iterations` passes or when h changes by less than `tolerance` (mm). (The
// Reconstructor passes options.Passes(view angle) as `iterations`.)
//
// Frames: camera frame, mm. Pixel (u, v) of the map is camera pixel (u, v) (centres on integers).
#include <opencv2/core/mat.hpp>

#include "geometry/fisheye.h"
#include "recon/surface_map.h"

namespace gs360 {

struct HeightFieldOptions {
  // Projection / solve passes at most, 1..100. Where little is hidden the passes converge and
  // more of them help. Where the imprint is seen obliquely, each pass moves what is hidden, and
  // further passes are not reliably better: they stop earlier there (the measurements that chose
  // 12 and 5, with the window below, are in docs/benchmarks.md).
  int iterations = 12;                   // imprints seen within oblique_view_angle_deg
  int oblique_iterations = 5;            // imprints seen at oblique_view_angle_deg or beyond
  double oblique_view_angle_deg = 40.0;  // ImprintViewAngleDeg (recon/reconstructor.h), [0, 90]
  double tolerance = 1e-4;               // mm; stop when max |h change| falls below, >= 0
  double unobserved_weight = 1e-3;       // weight of edges no pixel observes, (0, 1]
  double min_normal_dot = 0.3;           // slopes steeper than ~72 deg (noise, rims) give no data
  // Regions whose imprint is seen more squarely than this (mean view angle over the pixels
  // with |slope| > 0.3) are integrated along the rays instead (the discontinuity-aware psi
  // integrator, recon/integration.h). 0 = always the height field, the default: with exact
  // slopes the rays are the better parametrisation below 30 deg, but with the MLP's slopes the
  // height field is (chosen by measurement: bench/bench_integration and the virtual rig's
  // validation, figures in docs/benchmarks.md, "Calibration"). [0, 90).
  double min_view_angle_deg = 0.0;
  // Where the passes solve (the Reconstructor's HeightFieldWindow): the region's changed pixels
  // (ContactRegion::blob) grown by this fraction of their box per side plus the detection's
  // grow_px, clipped to the region; beyond it the gel is taken as undeformed (h = 0) and no slope
  // is evaluated there. The region's own margin (ContactDetectionOptions::grow_fraction) is for
  // the MLP's context; solved as well, it only adds unknowns and the membrane's drift (measured:
  // docs/benchmarks.md, "Reconstruction"). A value >= the detection's grow_fraction solves on
  // the whole region, as models before this option did. [0, 5].
  double window_grow_fraction = 0.1;
  // The passes for an imprint seen at `imprint_view_deg` (iterations or oblique_iterations).
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("iterations", self.iterations);
    visit("oblique_iterations", self.oblique_iterations);
    visit("oblique_view_angle_deg", self.oblique_view_angle_deg);
    visit("tolerance", self.tolerance);
    visit("unobserved_weight", self.unobserved_weight);
    visit("min_normal_dot", self.min_normal_dot);
    visit("min_view_angle_deg", self.min_view_angle_deg);
    visit("window_grow_fraction", self.window_grow_fraction);
  }
  int Passes(double imprint_view_deg) const {
    return imprint_view_deg >= oblique_view_angle_deg ? oblique_iterations : iterations;
  }
  void Check() const;  // throws std::invalid_argument naming the field and value
};

struct HeightFieldResult {
  cv::Mat height;  // CV_64F roi-sized: h along -n0 (mm, + into the gel), 0 on the border
  cv::Mat rho;     // CV_64F roi-sized: first hit along each pixel's ray (mm); NaN if invisible
  int iterations = 0;
};

// normals: CV_64FC3 roi-sized, the observed unit normal per pixel in the camera frame (NaN: no
// data), as recon/integration.h ComputeLogDepthGradients takes them. `camera` is the map's
// camera. initial_height: empty, or CV_64F roi-sized (mm; non-finite values count as 0). Throws
// std::invalid_argument for a roi smaller than 3 x 3, outside the map, or normals of the wrong
// type/size.
HeightFieldResult IntegrateHeightField(const SurfaceMap& map, const FisheyeCamera& camera,
                                       const cv::Rect& roi, const cv::Mat& normals,
                                       const HeightFieldOptions& options = {},
                                       const cv::Mat& initial_height = cv::Mat());

}  // namespace gs360
