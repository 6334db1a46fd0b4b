#pragma once
// The plan summary of `gs360 bench acquisition`.

#include <cstdio>

#include "plan/plan.h"
#include "storage/run_database.h"

namespace gs360::cli {

void PrintPlanSummary(std::FILE* out, const ProbePlan& plan);

}  // namespace gs360::cli
