#pragma once
// The stress suite's cases, one list per stage (stress.h StressCases joins them), and small
// helpers the case files share. Internal to stress/.

#include <string>
#include <vector>

#include "stress/stress.h"

namespace gs360::stress {

std::vector<StressCase> PoseCases();         // pose_cases.cc
std::vector<StressCase> IntrinsicsCases();   // intrinsics_cases.cc
std::vector<StressCase> FrameCases();        // frame_cases.cc
std::vector<StressCase> IntegrationCases();  // integration_cases.cc
std::vector<StressCase> GeometryCases();     // geometry_cases.cc
std::vector<StressCase> MlpCases();          // mlp_cases.cc

// printf into a std::string.
std::string Format(const char* format, ...) __attribute__((format(printf, 1, 2)));

}  // namespace gs360::stress
