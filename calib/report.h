#pragma once
// The calibration's human-readable outputs: a text table of the validation (for the terminal)
// and a self-contained HTML page (inline SVG charts, images as PNG data URIs; no network).

#include <Eigen/Core>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "calib/train.h"
#include "calib/validate.h"

namespace gs360 {

struct ReportInputs {
  std::string title;              // e.g. "gs360 calibration: run 3 (cylinder)"
  nlohmann::json validation;      // validation.json (calib/validate.cc layout, + "pose")
  nlohmann::json stages;          // array of {stage, input_hash, cached, seconds, metrics}
  std::vector<TrainEpoch> curve;  // training curve (may be empty)
  std::vector<ValidationExample> examples;
  // Per evaluated probe: contact point (sensor frame, mm) and its mean depth error (mm).
  std::vector<std::pair<Eigen::Vector3d, double>> probe_errors;
  double gel_height_mm = 30.0;
  // Parts of the surface the plan left unprobed: objects with z_min_mm, z_max_mm,
  // azimuth_min_deg, azimuth_max_deg (max < min: across +-180), all_around, text; hatched on the
  // error map.
  nlohmann::json coverage_gaps = nlohmann::json::array();
  // Top of the error map's colour scale (mm): larger errors get the top colour.
  double error_map_clamp_mm = 0.1;
};

// Text table (fixed width, <= 100 columns): per truth, rows = bands, columns = mean / p95 depth
// error of both integrators, median normal error, peak error; plus the pose line if present.
// Columns: pixels, mean mm (default method), mean mm (the other), p95 mm, median normal deg and
// peak error mm (default method). Rows: every known band in validate.cc's order (then unknown
// ones); "-" for a null / missing value. Truths in the "truths" order. Never throws.
std::string FormatValidationTable(const nlohmann::json& validation);

// The intrinsics stage's metrics as text: the lens (fx, fy, cx, cy in px), where it came from,
// the RMS reprojection error over the images used, and one line per checkerboard image (its
// corners and RMS, or why it was rejected). Empty when `metrics` has no intrinsics. Never
// throws.
std::string FormatIntrinsics(const nlohmann::json& metrics);

// The accuracy targets against the validation's best truth (physical when present, else rigid)
// and default integrator: mean depth error <= 0.030 mm, the > 50 deg band <= 0.050 mm, peak
// indentation error <= 0.050 mm, median normal error <= 3 deg, and with a physical truth the
// camera pose within 0.05 mm and 0.05 deg. An array of {"name", "value", "comparison" ("<="),
// "target", "unit", "pass", "no_data", "truth"}; a figure the validation lacks has value null
// and pass false, except a band no held-out pixel fell in while the validation has some
// ("no_data": true, "pass": true: the band says nothing, e.g. nothing on a dome is seen past
// 50 deg). Never throws.
nlohmann::json ValidationTargets(const nlohmann::json& validation);

// The error-against-probes curve of a run that stops once converged: the points of `earlier`
// ({"probes", "mean_mm", "band50_mm", "targets_met"} each) then this validation's own, marked
// "this": true (`probes`: the probes it calibrated on). The HTML page draws it from
// validation["convergence"]. Never throws.
nlohmann::json ConvergencePoints(const nlohmann::json& earlier, const nlohmann::json& validation,
                                 std::size_t probes);

// Plain warnings about a model that is not good enough, each saying what to do, as an array of
// {"code", "message"}: "targets" (which ValidationTargets fail, by how much), "few_probes" (a
// target fails and fewer than kFewProbes probes trained the model), "overfit" (at the best epoch
// the validation loss is more than kOverfitRatio times the training loss), "empty_band" (a band
// of the default truth and integrator that no held-out probe fell in: its figures say nothing).
// `probes`: the probes with contact in the dataset. Never throws.
// Text for the terminal: one line per target (value, target, pass or FAIL), then "warning: ..."
// per warning in validation["warnings"]. Never throws.
std::string FormatTargetsAndWarnings(const nlohmann::json& validation);
inline constexpr std::size_t kFewProbes = 1000;
inline constexpr double kOverfitRatio = 3.0;
nlohmann::json CalibrationWarnings(const nlohmann::json& validation,
                                   const std::vector<TrainEpoch>& curve, std::size_t probes);

// The HTML page: title, stage table, validation tables, training curve (inline SVG, log-scale
// loss), error map over the sensor (inline SVG scatter: azimuth deg x height mm, colour = mean
// error clamped at error_map_clamp_mm) and the examples (PNG data URIs, one shared colour scale
// per example). All text is HTML-escaped. Never throws for missing optional parts (they are left
// out) or malformed ones (wrong JSON types, empty or mistyped images are skipped); only
// std::bad_alloc can escape.
std::string RenderReportHtml(const ReportInputs& inputs);

}  // namespace gs360
