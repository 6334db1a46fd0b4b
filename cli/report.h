#pragma once
// Human-readable summaries shared by `run` and `demo`.

#include <cstdio>

#include "gcode/plan.h"
#include "storage/run_database.h"

namespace gs360::cli {

void PrintPlanSummary(std::FILE* out, const ProbePlan& plan);
void PrintRunStatus(std::FILE* out, const RunStatus& status);

}  // namespace gs360::cli
