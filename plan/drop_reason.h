#pragma once
// Why the planner leaves a candidate point out of a plan (plan/plan.h's filters), and counts
// of them.

#include <array>
#include <string_view>

namespace gs360 {

enum class DropReason { kFov, kViewAngle, kFin, kGel, kReach, kTravel };
inline constexpr int kNumDropReasons = 6;
std::string_view DropReasonName(DropReason reason);  // "fov", "view_angle", "fin", ...

struct DropCounts {
  std::array<int, kNumDropReasons> counts{};
  int& operator[](DropReason r) { return counts[static_cast<int>(r)]; }
  int operator[](DropReason r) const { return counts[static_cast<int>(r)]; }
  int Total() const;
};

}  // namespace gs360
