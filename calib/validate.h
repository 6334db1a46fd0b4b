#pragma once
// Calibration stage 7, "validate": held-out probes go through the whole run-time reconstruction
// (recon/reconstructor.h: difference -> contact ROI -> MLP slopes -> log-distance gradients ->
// integration -> depth) and are compared with the truth, per pixel of the rendered contact.
//
// Two truths:
//   - "rigid": the rigid-ball render under the calibrated pose (calib/render.h) -- what a real
//     rig can check. Depth error at a pixel = |rho - rho_render| |d.n_render| (point-to-plane
//     distance to the rendered surface), normal error = angle to the ball's normal there.
//   - "physical": an optional ValidationTruth (on the virtual rig: the simulator's deformed gel,
//     implemented outside production code). Depth error = distance from the reconstructed point
//     to the true surface, normal error = angle to the true normal at the closest point.
// Both integrators (plain Poisson, the paper's method with the log-distance formula, and the
// discontinuity-aware default) are evaluated on the same probes and the same MLP slopes.
//
// Breakdown: height band (base / middle / tip: thirds of the gel's height, by the probe's contact
// point), view angle band (the pixel's: < 30, 30-50, > 50 deg), fins (probe's contact point
// within fin_near_mm of a fin plane: "near_fins" / "far_from_fins"). Per band: pixels, mean and
// 95th percentile depth error (mm), median normal error (deg), mean |peak indentation error|
// (mm, per probe: the band of its contact point). validation.json's "probe_peaks" lists every
// evaluated probe's peak per method and truth, its rendered imprint's pixels and view angle.

#include <Eigen/Core>
#include <array>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core/mat.hpp>

#include "calib/render.h"
#include "geometry/rigid3.h"
#include "recon/reconstructor.h"

namespace gs360 {

// The bands of validation.json's "results", in their order: all pixels; by height on the sensor
// (base, middle, tip); by the angle the camera sees the surface at; near or far from a fin.
inline constexpr std::array<const char*, 9> kValidationBands = {
    "all",        "height:base", "height:middle", "height:tip", "view:<30",
    "view:30-50", "view:>50",    "fins:near",     "fins:far"};

// The true surface under one probe (sensor frame, mm). Thread-compatible: one per thread.
class ProbeSurfaceTruth {
 public:
  virtual ~ProbeSurfaceTruth() = default;
  // Distance from x to the true surface; *normal = its outward unit normal at the closest point.
  virtual double Distance(const Eigen::Vector3d& x_sensor, Eigen::Vector3d* normal) const = 0;
  // Largest inward displacement of the surface (mm).
  virtual double PeakIndentation() const = 0;
};

// Ground truth beyond the rigid render (e.g. the virtual rig). ForProbe may be called from
// several threads at once.
class ValidationTruth {
 public:
  virtual ~ValidationTruth() = default;
  virtual std::string Describe() const = 0;
  virtual std::optional<Rigid3d> TrueCamFromSensor() const = 0;
  virtual std::unique_ptr<ProbeSurfaceTruth> ForProbe(const Eigen::Vector3d& ball_center_sensor,
                                                      double ball_radius) const = 0;
};

struct ValidationOptions {
  int max_probes = 400;      // held-out probes evaluated at most (a seeded subset beyond)
  double fin_near_mm = 2.0;  // contact point this close to a fin plane = near the fins
  int examples = 4;          // example reconstructions kept for the report
  int threads = 2;
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("max_probes", self.max_probes);
    visit("fin_near_mm", self.fin_near_mm);
    visit("examples", self.examples);
    visit("threads", self.threads);
  }
  void Check() const;
};

// One held-out probe, as the validation loop needs it.
struct ValidationProbe {
  int plan_index = 0;
  Eigen::Vector3d contact_point_sensor = Eigen::Vector3d::Zero();
  Eigen::Vector3d ball_center_sensor = Eigen::Vector3d::Zero();
  cv::Mat frame;      // CV_8UC3 press frame
  cv::Mat reference;  // CV_8UC3 reference nearest in time
};

struct ValidationExample {
  int plan_index = 0;
  cv::Mat frame_roi;         // CV_8UC3 crop of the press frame
  cv::Mat truth_depth;       // CV_64F indentation (mm) of the rigid render in the roi
  cv::Mat recon_depth;       // CV_64F indentation (mm), the model's default integrator
  std::string recon_method;  // that integrator's name (heightfield, discontinuity, poisson)
  cv::Mat poisson_depth;     // CV_64F indentation (mm), plain Poisson
  cv::Mat physical_depth;    // CV_64F |error| (mm) against the physical truth (empty without one)
};

struct ValidationResult {
  nlohmann::json report;  // validation.json (see validate.cc for the layout)
  std::vector<ValidationExample> examples;
  // Per evaluated probe: (contact point, mean depth error against the best truth, default method)
  // for the error map over the sensor.
  std::vector<std::pair<Eigen::Vector3d, double>> probe_errors;
};

// Loads a probe's frames on demand (from the run database); called from worker threads, at most
// once per probe, with a thread index in [0, threads).
using ValidationProbeLoader = std::function<ValidationProbe(int plan_index, int thread)>;

// `reconstructor` carries the calibrated map, camera, MLP and options. `held_out` are plan
// indices; `gel_height_mm` splits the height bands. `truth` may be null.
ValidationResult Validate(const Reconstructor& reconstructor, const std::vector<int>& held_out,
                          const ValidationProbeLoader& load, double ball_radius,
                          double gel_height_mm, const ValidationTruth* truth,
                          const ValidationOptions& options);

}  // namespace gs360
