#include "cli/report.h"

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
}

void PrintRunStatus(std::FILE* out, const RunStatus& s) {
  const auto& c = s.probes;
  std::fprintf(out,
               "run %lld %-12s %s  probes %lld/%lld captured, %lld failed, %lld skipped, %lld "
               "planned  elapsed %s  references %lld\n",
               static_cast<long long>(s.run.id), std::string(ToString(s.run.state)).c_str(),
               s.run.name.c_str(), static_cast<long long>(c.captured),
               static_cast<long long>(c.total), static_cast<long long>(c.failed),
               static_cast<long long>(c.skipped), static_cast<long long>(c.planned),
               FormatDuration(s.elapsed_s).c_str(), static_cast<long long>(s.reference_frames));
}

}  // namespace gs360::cli
