#pragma once
// The calibration stages run in order on a finished (or partly finished) run's database:
//
//   intrinsics -> impressions -> pose -> surface_map -> render -> dataset -> train -> validate
//   -> export
//
// Each stage is a function of stored inputs and options (calib/stages.h lists what each reads and
// computes its cache key from that list). Its output is stored as an artifact keyed (run, stage,
// key) with its figures as metrics JSON. A stage whose artifact exists is skipped and its output
// loaded (like a build system); `from_stage` forces that stage and every later one to run again,
// `to_stage` stops after one, `only_stage` runs one on cached inputs. Changing an option re-runs
// exactly the stages that read it and the ones downstream.
//
// Production code: this reads only the database and the rig's nominal description. Ground truth
// (the virtual rig) enters only through the optional ValidationTruth, used for reporting.

#include <Eigen/Core>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "calib/stages.h"
#include "calib/validate.h"
#include "geometry/fisheye.h"
#include "geometry/mesh.h"
#include "geometry/rigid3.h"
#include "recon/model_bundle.h"
#include "recon/reconstructor.h"
#include "recon/surface_map.h"
#include "storage/run_database.h"

namespace gs360 {

// What the rig's configuration says (nominal values only).
struct CalibrationInputs {
  std::string sensor;     // description for reports ("cylinder", a mesh path)
  TriangleMesh gel_mesh;  // sensor frame, mm, outward normals
  TriangleMesh fin_mesh;  // sensor frame (may be empty)
  FisheyeIntrinsics nominal_intrinsics;
  Rigid3d nominal_cam_from_sensor;
  Rigid3d machine_from_sensor;
  Eigen::Vector3d tool_offset = Eigen::Vector3d::Zero();  // ball centre = MPos + tool_offset
  double ball_radius = 2.0;
  // Checkerboard images for the intrinsics stage (grey or colour, the camera's size). Empty: the
  // nominal intrinsics are used, and the report says so.
  std::vector<std::filesystem::path> checkerboard_images;
  // Where the plan left the surface unprobed (plan/coverage.h's CoverageGap::ToJson() array),
  // drawn on the report's error map and kept in validation.json. Not a stage input.
  nlohmann::json coverage_gaps = nlohmann::json::array();
  // A run that stops once converged: its earlier checkpoints, {"probes", "mean_mm", "band50_mm",
  // "targets_met"} each, in order. The report draws them with this calibration's own figures as
  // the last point (validation.json "convergence"). Not a stage input.
  nlohmann::json convergence = nlohmann::json::array();
};

struct StageReport {
  std::string stage;
  std::string input_hash;
  bool cached = false;
  double seconds = 0.0;  // this call's time (loading, when cached)
  nlohmann::json metrics;
};

struct CalibrationResult {
  std::vector<StageReport> stages;
  FisheyeIntrinsics intrinsics;
  Rigid3d cam_from_sensor;
  nlohmann::json validation;  // validation.json
  std::filesystem::path model_path;
  std::filesystem::path onnx_path;
  std::filesystem::path report_path;  // HTML
  std::filesystem::path validation_path;
  double seconds = 0.0;
};

// Progress: stage name and a message (on the calling thread).
using CalibrationLog = std::function<void(const std::string& stage, const std::string& message)>;

// Runs the stages for `run_id` in `db`. Throws std::runtime_error (naming the stage and the
// problem) when a stage cannot produce its output: no captured probes, intrinsics ill-conditioned,
// too few impressions for the pose, a corrupt frame (the message names the frame and probe).
CalibrationResult RunCalibration(RunDatabase& db, std::int64_t run_id,
                                 const CalibrationInputs& inputs, const CalibrationOptions& options,
                                 const ValidationTruth* truth = nullptr,
                                 const CalibrationLog& log = {});

}  // namespace gs360
