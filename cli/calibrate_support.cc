#include "cli/calibrate_support.h"

#include <chrono>

#include "base/format.h"
#include "calib/report.h"
#include "cli/progress.h"

namespace gs360::cli {

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
  for (const StageReport& s : result.stages) {
    const std::string lens = FormatIntrinsics(s.metrics);
    if (s.stage == "intrinsics" && !lens.empty()) std::fprintf(out, "\n%s", lens.c_str());
  }
  if (result.model_path.empty()) {
    std::fprintf(out, "\ncalibration stopped after %s in %s (no model exported)\n",
                 result.stages.empty() ? "no stage" : result.stages.back().stage.c_str(),
                 FormatDuration(result.seconds).c_str());
    return result;
  }
  std::fprintf(out, "\n%s", FormatValidationTable(result.validation).c_str());
  std::fprintf(out, "\ncalibration finished in %s\n  model:  %s\n  onnx:   %s\n  report: %s\n",
               FormatDuration(result.seconds).c_str(), result.model_path.string().c_str(),
               result.onnx_path.string().c_str(), result.report_path.string().c_str());
  return result;
}

}  // namespace gs360::cli
