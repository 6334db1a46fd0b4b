#include "run/calibration_inputs.h"

#include <algorithm>
#include <stdexcept>

#include <nlohmann/json.hpp>

#include "plan/plan.h"

namespace gs360 {

CalibrationInputs CalibrationInputsFor(const RunConfig& config,
                                       const std::filesystem::path& checkerboard_dir) {
  const RigGeometry geometry = MakeRigGeometry(config.rig);
  CalibrationInputs in;
  in.sensor = config.rig.mesh_path.empty() ? std::string(SensorShapeName(config.rig.shape.shape))
                                           : config.rig.mesh_path;
  in.gel_mesh = geometry.sensor_mesh;
  in.fin_mesh = geometry.fins;
  in.nominal_intrinsics = config.rig.camera;
  in.nominal_cam_from_sensor = config.rig.cam_from_sensor();
  in.machine_from_sensor = config.rig.machine_from_sensor();
  in.tool_offset = config.rig.tool_offset;
  in.ball_radius = config.rig.ball_radius;
  if (!checkerboard_dir.empty()) {
    if (!std::filesystem::is_directory(checkerboard_dir)) {
      throw std::runtime_error("checkerboards: " + checkerboard_dir.string() +
                               " is not a directory");
    }
    for (const auto& entry : std::filesystem::directory_iterator(checkerboard_dir)) {
      std::string ext = entry.path().extension().string();
      std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
      if (ext == ".png" || ext == ".jpg" || ext == ".jpeg" || ext == ".bmp") {
        in.checkerboard_images.push_back(entry.path());
      }
    }
    std::sort(in.checkerboard_images.begin(), in.checkerboard_images.end());
    if (in.checkerboard_images.empty()) {
      throw std::runtime_error("checkerboards: no images (*.png, *.jpg) in " +
                               checkerboard_dir.string());
    }
  }
  return in;
}

CalibrationInputs CalibrationInputsFor(const RunDatabase& db, std::int64_t run_id,
                                       const std::filesystem::path& checkerboard_dir) {
  CalibrationInputs in = CalibrationInputsFor(StoredRunConfig(db, run_id), checkerboard_dir);
  for (const ArtifactRecord& a : db.ListArtifacts(run_id)) {
    if (a.stage != kPlanArtifactStage) continue;
    const nlohmann::json summary = nlohmann::json::parse(a.metrics_json, nullptr, false);
    if (summary.is_object() && summary.contains("coverage_gaps") &&
        summary["coverage_gaps"].is_array()) {
      in.coverage_gaps = summary["coverage_gaps"];
    }
  }
  return in;
}

}  // namespace gs360
