#pragma once
// Shared by `gs360 calibrate` and `gs360 demo`: the calibration's inputs from a run's stored
// configuration, and running the stages with progress and a summary on a terminal.

#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <vector>

#include "calib/pipeline.h"
#include "daemon/run_config.h"
#include "storage/run_database.h"

namespace gs360::cli {

// The rig's nominal description (mesh, fins, camera, mount, tool) from a run's configuration, and
// the checkerboard images (sorted *.png / *.jpg files of `checkerboard_dir`, if given). Throws
// std::runtime_error naming the directory when it has no images.
CalibrationInputs CalibrationInputsFor(const RunConfig& config,
                                       const std::filesystem::path& checkerboard_dir = {});

// The run's stored configuration. Throws std::runtime_error naming the run and the database.
RunConfig StoredRunConfig(const RunDatabase& db, std::int64_t run_id);

// Runs the stages, printing one line per stage (cached or timed) and, at the end, the validation
// table and where the outputs went.
CalibrationResult CalibrateAndPrint(RunDatabase& db, std::int64_t run_id,
                                    const CalibrationInputs& inputs,
                                    const CalibrationOptions& options, const ValidationTruth* truth,
                                    std::FILE* out);

}  // namespace gs360::cli
