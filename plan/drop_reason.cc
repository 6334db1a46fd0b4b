#include "plan/drop_reason.h"

namespace gs360 {

std::string_view DropReasonName(DropReason reason) {
  switch (reason) {
    case DropReason::kFov:
      return "fov";
    case DropReason::kViewAngle:
      return "view_angle";
    case DropReason::kFin:
      return "fin";
    case DropReason::kGel:
      return "gel";
    case DropReason::kReach:
      return "reach";
    case DropReason::kTravel:
      return "travel";
  }
  return "unknown";
}

int DropCounts::Total() const {
  int t = 0;
  for (int c : counts) t += c;
  return t;
}

}  // namespace gs360
