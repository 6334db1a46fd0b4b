#include "cli/calibrate_support.h"

#include <algorithm>
#include <chrono>
#include <stdexcept>

#include <nlohmann/json.hpp>

#include "calib/report.h"
#include "cli/progress.h"
#include "gcode/plan.h"
#include "rig/rig_config.h"

namespace gs360::cli {

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

RunConfig StoredRunConfig(const RunDatabase& db, std::int64_t run_id) {
  const auto run = db.GetRun(run_id);
  if (!run) {
    throw std::runtime_error("no run " + std::to_string(run_id) + " in " + db.path().string());
  }
  return RunConfigFromJson(nlohmann::json::parse(run->config_json),
                           db.path().string() + ": run " + std::to_string(run_id));
}

CalibrationResult CalibrateAndPrint(RunDatabase& db, std::int64_t run_id,
                                    const CalibrationInputs& inputs,
                                    const CalibrationOptions& options, const ValidationTruth* truth,
                                    std::FILE* out) {
  const auto t0 = std::chrono::steady_clock::now();
  auto log = [&](const std::string& stage, const std::string& message) {
    const double t = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::fprintf(out, "  [%7.1f s] %-12s %s\n", t, stage.c_str(), message.c_str());
    std::fflush(out);
  };
  CalibrationResult result = RunCalibration(db, run_id, inputs, options, truth, log);
  std::fprintf(out, "\nstages:\n");
  for (const StageReport& s : result.stages) {
    std::fprintf(out, "  %-12s %s %8.2f s  %s\n", s.stage.c_str(), s.cached ? "cached" : "ran   ",
                 s.seconds, s.input_hash.c_str());
  }
  std::fprintf(out, "\n%s", FormatValidationTable(result.validation).c_str());
  std::fprintf(out, "\ncalibration finished in %s\n  model:  %s\n  onnx:   %s\n  report: %s\n",
               FormatDuration(result.seconds).c_str(), result.model_path.string().c_str(),
               result.onnx_path.string().c_str(), result.report_path.string().c_str());
  return result;
}

}  // namespace gs360::cli
