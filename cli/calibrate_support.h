#pragma once
// Shared by `gs360 calibrate` and `gs360 demo`: the calibration's inputs from a run's stored
// configuration, and running the stages with progress and a summary on a terminal.

#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <vector>

#include "calib/pipeline.h"
#include "run/calibration_inputs.h"
#include "run/run_config.h"
#include "storage/run_database.h"

namespace gs360::cli {

// Runs the stages, printing one line per stage (cached or timed) and, at the end, the validation
// table and where the outputs went.
CalibrationResult CalibrateAndPrint(RunDatabase& db, std::int64_t run_id,
                                    const CalibrationInputs& inputs,
                                    const CalibrationOptions& options, const ValidationTruth* truth,
                                    std::FILE* out);

}  // namespace gs360::cli
