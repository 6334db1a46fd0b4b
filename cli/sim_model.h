#pragma once
// A model calibrated on the virtual rig without a CNC: presses rendered straight from the
// rig's camera at planned points (as a finished acquisition leaves them in a database), then the
// calibration stages. For tests, the demo and benchmarks of run-time reconstruction only.

#include <cstdint>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "sim/rig_model.h"

namespace gs360::cli {

struct SimModelOptions {
  int probes = 60;                     // presses rendered and calibrated
  std::vector<int> hidden = {16, 16};  // MLP hidden layers
  int epochs = 3;
  double press_depth_mm = 1.0;
  std::uint64_t seed = 7;
  int threads = 2;
  void Check() const;  // throws std::invalid_argument naming the field
};

// Press points (sensor frame) on the default rig's gel, clear of the fins, and the ball centres
// that press them `depth_mm` deep.
struct SimPress {
  Eigen::Vector3d point_sensor;
  Eigen::Vector3d normal_sensor;
  Eigen::Vector3d ball_sensor;
};
std::vector<SimPress> SimPresses(const SimRig& rig, int count, double depth_mm, std::uint64_t seed);

// Where a benchmark keeps its calibrated model between runs: `cache` if given, else
// $XDG_CACHE_HOME/gs360, ~/.cache/gs360 or the temporary directory's gs360-cache, then `name`.
std::filesystem::path SimModelCacheDir(const std::string& cache, const std::string& name);

// Calibrates a model in `dir` (a database and the calibration's exports; reused when its files
// are there and the options are the same: the stage cache) and returns the bundle's path. Throws
// what RunCalibration throws.
std::filesystem::path MakeSimModel(const std::filesystem::path& dir,
                                   const SimModelOptions& options);

}  // namespace gs360::cli
