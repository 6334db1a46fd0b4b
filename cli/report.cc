#include "cli/report.h"

#include "base/format.h"
#include "cli/progress.h"
#include "cli/run_view.h"

namespace gs360::cli {

void PrintPlanSummary(std::FILE* out, const ProbePlan& plan) {
  std::fprintf(out, "plan: %zu probes kept of %d candidates (planned in %.2f s)\n",
               plan.probes.size(), plan.candidates, plan.planning_seconds);
  std::fprintf(out, "  dropped:");
  for (int r = 0; r < kNumDropReasons; ++r) {
    std::fprintf(out, " %s %d", std::string(DropReasonName(static_cast<DropReason>(r))).c_str(),
                 plan.dropped.counts[static_cast<std::size_t>(r)]);
  }
  std::fprintf(out,
               "\n  estimate: %s (travel %.0f%%, press/dwell/capture %.0f%%), tour %.2fx faster "
               "than sampling order, %d detoured travels\n",
               FormatDuration(plan.estimate.Total()).c_str(), 100.0 * plan.estimate.TravelShare(),
               100.0 * plan.estimate.PressShare(), plan.TourGain(), plan.detoured_moves);
  for (const std::string& line : PlanAdvice(plan)) {
    std::fprintf(out, "  advice: %s\n", line.c_str());
  }
  PrintCoverageGaps(out, CoverageGapsJson(plan.coverage_gaps));
}

}  // namespace gs360::cli
