#include "cli/report.h"

#include "base/format.h"
#include "cli/progress.h"

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
  for (const std::string& line :
       PlanAdvice(plan.dropped, static_cast<int>(plan.probes.size()), plan.candidates)) {
    std::fprintf(out, "  advice: %s\n", line.c_str());
  }
  constexpr std::size_t kShown = 5;  // the largest; the rest are patches of a few candidates
  for (std::size_t i = 0; i < plan.coverage_gaps.size() && i < kShown; ++i) {
    std::fprintf(out, "  not probed: %s\n", plan.coverage_gaps[i].Describe().c_str());
  }
  if (plan.coverage_gaps.size() > kShown) {
    std::fprintf(out, "  not probed: %zu more places, smaller\n",
                 plan.coverage_gaps.size() - kShown);
  }
}

}  // namespace gs360::cli
