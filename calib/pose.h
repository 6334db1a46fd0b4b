#pragma once
// Calibration stage 3, "pose": cam_from_sensor from the probes' impressions.
//
// Each captured probe gives a 3D point on the gel (the planned contact point, SENSOR frame, mm)
// and the image position of its impression (pixels, e.g. capture/impression.h FindImpression on
// press minus reference). Two estimates are made:
//   1. "paper" (GelSight360, Sec. III-C): `ransac_probes` probes drawn at random (seeded), their
//      centroids undistorted to normalised coordinates (cv::fisheye::undistortPoints), then
//      cv::solvePnPRansac against the contact points, starting from the nominal pose.
//   2. refined: Levenberg-Marquardt on the fisheye reprojection error of the probes seen at most
//      max_view_angle_deg from their normal (Huber weights, then observations whose residual
//      exceeds the outlier bound are dropped and the fit repeated), starting from the paper
//      estimate. A pose that puts an observation outside the lens's valid field counts it as
//      1000 px off (there the projection folds back).
// Oblique imprints: the view angle of a probe is the angle between the camera ray to its contact
// point and the contact normal (at the paper estimate). Seen obliquely, an imprint is a bump
// seen from the side; its far side (normals turned toward the occluding contour) changes colour
// much less than its near side, so the region an impression finder thresholds loses the far side
// and its centre moves toward the near side: little below 50 deg, several times more beyond, on
// cylinder, cone and spline alike (bench/bench_pose_db.cc on the virtual rig's stored runs;
// figures in docs/benchmarks.md, "Calibration", "Pose, session 4"). The rigid bias model below
// cannot predict shading, and on the cone these biased residuals straddle the outlier bound, so
// the robust fit kept a biased subset and missed the rotation target. The refinement therefore
// leaves them out (at least min_view_fraction of the observations are kept: the least oblique
// ones). The bias model's finder centre (model_finder, below) predicts the imprints seen up to
// ~60 deg well enough to keep them, which the bound's default follows (docs/benchmarks.md,
// "Held-out rigs").
// Face-on imprints: a centroid bias shared by the probes of a region of the gel is not seen in the
// residuals when the pose can absorb it. On a dome seen face-on (every contact point about as far
// from the camera, all of them near face-on) a bias along the image radius, the same on every
// probe, is what moving the camera along its axis does, and that is where it goes: one pixel
// toward the image centre moves the camera by about a tenth of a millimetre, on a tall finger as
// on a dome. Impressions lit from one side (face-on ones on every shape: a dome's, a tip's) are
// such a bias when their region is cut at a fraction of the global peak; the impression centre
// (calib/impression_centroid.h) therefore finds the imprint's edge per direction.
// Bias model (model_bias): the centroid of an impression is not the projection of its contact
// point -- the imprint is a disc seen obliquely through a fisheye. With the gel mesh given, each
// refinement round builds the surface map (recon/surface_map.h) for the current pose, renders
// every probe's rigid imprint (calib/render.h) and takes bias_i = centroid of the rendered contact
// - projection of the contact point; the next round fits projection + bias_i to the observed
// centroids. A few rounds converge (the bias changes slowly with the pose).
// The rendered centre (model_finder): the observed centre is where the impression finder puts it,
// which is not the contact region's centroid: the finder blurs the change, cuts each direction at a
// fraction of its own maximum, and the change is largest where the gel's normal turns most (the
// imprint's rim) and least at its middle. So the finder (PoseScene::finder's options) is run on the
// rendered imprint's normal change |n - n0|, blurred as the frames are, and its centre is the
// prediction. The lighting's gain per direction is what the finder divides out; what remains is the
// imprint's shape, its view angle and the lens. Without model_finder, the centroid of the convex
// hull of the rendered contact pixels.
//
// Units and frames: mm, rad; points in the sensor frame; pixels as geometry/fisheye.h. The
// intrinsics are given (stage 1's output) and not refined.
//
// Errors: PoseError (a std::runtime_error) when there are fewer than min_observations usable
// observations or PnP finds no pose; std::invalid_argument for invalid options, non-finite
// observations, or model_bias without a gel mesh.

#include <Eigen/Core>
#include <cstdint>
#include <span>
#include <stdexcept>
#include <vector>

#include "calib/impression_centroid.h"
#include "calib/render.h"
#include "geometry/bvh.h"
#include "geometry/fisheye.h"
#include "geometry/rigid3.h"
#include "recon/surface_map.h"

namespace gs360 {

class PoseError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct PoseObservation {
  int probe_index = -1;                                              // caller's id (reported back)
  Eigen::Vector3d contact_point_sensor = Eigen::Vector3d::Zero();    // planned contact point, mm
  Eigen::Vector3d contact_normal_sensor = Eigen::Vector3d::UnitZ();  // its outward unit normal
  Eigen::Vector3d ball_center_sensor = Eigen::Vector3d::Zero();      // ball centre at the press, mm
  Eigen::Vector2d centroid_px = Eigen::Vector2d::Zero();             // observed impression centre
  double region_px = 0.0;  // the impression region's size (pixels counted in it); 0: unknown
  double weight = 1.0;     // > 0 (e.g. 1 / sigma^2)
};

struct PoseOptions {
  int ransac_probes = 100;           // probes for the paper's PnP (all if fewer are given)
  double ransac_threshold_px = 4.0;  // PnP RANSAC inlier bound (pixels, converted with fx)
  int ransac_iterations = 1000;      // PnP RANSAC iterations
  int max_iterations = 50;           // Levenberg-Marquardt iterations per fit
  double huber_px = 0.5;             // Huber weight knee (px)
  double outlier_px = 2.0;           // refined fit: residuals above max(this, 4 sigma) are out
  // Refined fit: only observations seen at most this far from their normal (deg, (0, 90]; 90 =
  // all). If fewer than max(min_observations, ceil(min_view_fraction * n)) qualify, that many of
  // the least oblique are used instead (min_view_fraction in (0, 1]).
  double max_view_angle_deg = 60.0;
  double min_view_fraction = 0.25;
  // The view bound is released (the fit over every observation is kept instead) when the bounded
  // fit's inlier RMS is more than this many times the unbounded fit's. 0: never; else >= 1.
  double max_bound_rms_ratio = 2.0;
  int min_observations = 6;  // fewer usable observations -> PoseError (>= 6)
  // The refined fit's condition number (PoseResult::condition) above this -> PoseError: the
  // impressions do not determine the pose (>= 1; infinity accepts any).
  double max_condition = 100.0;
  bool model_bias = true;    // needs the gel mesh (PoseScene::gel)
  bool model_finder = true;  // bias model: the finder's centre of the rendered imprint (above)
  int bias_rounds = 3;       // bias model: render / refit rounds (>= 1)
  // Bias model: an observation whose region (region_px) is more than this many times larger,
  // relative to its rendered imprint's contact, than the median observation's is left out (a
  // change spread far beyond one imprint: a faint press among the noise). 0 keeps all; else >= 1.
  double max_region_ratio = 3.0;
  double ball_radius_mm = 2.0;    // the probe ball (> 0)
  ProbeRenderOptions render;      // for the bias model's imprints
  SurfaceMapOptions surface_map;  // for the bias model's surface maps
  std::uint64_t seed = 1;         // draws the paper's probes
  int threads = 2;                // rendering the imprints (1..64)
  // Throws std::invalid_argument naming the field and its value.
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("ransac_probes", self.ransac_probes);
    visit("ransac_threshold_px", self.ransac_threshold_px);
    visit("ransac_iterations", self.ransac_iterations);
    visit("max_iterations", self.max_iterations);
    visit("huber_px", self.huber_px);
    visit("outlier_px", self.outlier_px);
    visit("max_view_angle_deg", self.max_view_angle_deg);
    visit("min_view_fraction", self.min_view_fraction);
    visit("max_bound_rms_ratio", self.max_bound_rms_ratio);
    visit("min_observations", self.min_observations);
    visit("max_condition", self.max_condition);
    visit("model_bias", self.model_bias);
    visit("model_finder", self.model_finder);
    visit("bias_rounds", self.bias_rounds);
    visit("max_region_ratio", self.max_region_ratio);
    visit("ball_radius_mm", self.ball_radius_mm);
    visit("render", self.render);
    visit("surface_map", self.surface_map);
    visit("seed", self.seed);
    visit("threads", self.threads);
  }
  void Check() const;
};

// The sensor's geometry, for the bias model (sensor frame; either may be null when unused), and
// how the observed centres were found (the bias model's model_finder runs the same finder; its
// floors in DN, min_peak_dn and min_threshold_dn, and max_area_fraction do not apply there).
struct PoseScene {
  const Bvh* gel = nullptr;
  const Bvh* fins = nullptr;
  ImpressionCentroidOptions finder;
};

struct PoseResult {
  Rigid3d cam_from_sensor;        // refined (with the bias model if enabled)
  Rigid3d paper_cam_from_sensor;  // the paper's RANSAC PnP on ransac_probes probes
  double rms_px = 0.0;            // refined: RMS residual over the inliers (bias-corrected)
  // How well the refined fit's observations pin the pose down: condition number of their
  // Jacobian with unit-norm columns (1 = ideal; infinite = a direction of the pose unobserved).
  double condition = 0.0;
  double paper_rms_px = 0.0;  // paper: RMS reprojection over its RANSAC inliers
  int paper_inliers = 0;
  int oblique = 0;                   // observations left out of the refinement by the view bound
  double view_bound_deg = 0.0;       // the view-angle bound applied (max_view_angle_deg or more)
  bool view_bound_released = false;  // the bound's fit was replaced by one over all (step 5)
  int inliers = 0, outliers = 0;     // refined fit over the observations within the view bound
  std::vector<int> outlier_probe_indices;  // PoseObservation::probe_index of the outliers
  int bias_rounds = 0;                     // rounds of the bias model done (0 = none)
  double mean_bias_px = 0.0;               // mean |bias_i| of the last round (0 without the model)
  int no_rendered_contact = 0;             // observations whose rendered imprint was empty (bias 0)
  int spread = 0;                          // left out by max_region_ratio
  double seconds = 0.0;
};

// Angle (rad) between the ray from the camera centre to the contact point and the contact
// normal's line (0 = seen face-on, pi/2 = grazing), under `cam_from_sensor`.
double ObservationViewAngle(const PoseObservation& observation, const Rigid3d& cam_from_sensor);

// `camera`: the calibrated intrinsics. `nominal_cam_from_sensor`: the CAD pose (PnP start).
PoseResult EstimateCamFromSensor(const FisheyeCamera& camera,
                                 std::span<const PoseObservation> observations,
                                 const Rigid3d& nominal_cam_from_sensor, const PoseOptions& options,
                                 const PoseScene& scene = {});

// Robust Levenberg-Marquardt refinement alone (used by EstimateCamFromSensor): fits
// camera.ProjectUnchecked(cam_from_sensor * X_i) + offset_i to the observed centroids from
// `initial`, Huber weights, outlier rounds. `offsets` empty = no offsets, else one per
// observation. `inlier` (output, optional) receives one flag per observation.
struct PoseFit {
  Rigid3d cam_from_sensor;
  double rms_px = 0.0;
  double condition = 0.0;  // as PoseResult::condition, over the inliers at the fit
  int inliers = 0;
  std::vector<bool> inlier;
};
PoseFit RefineCamFromSensor(const FisheyeCamera& camera,
                            std::span<const PoseObservation> observations,
                            std::span<const Eigen::Vector2d> offsets, const Rigid3d& initial,
                            const PoseOptions& options);

}  // namespace gs360
