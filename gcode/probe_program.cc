#include "gcode/probe_program.h"

#include <stdexcept>

#include "base/format.h"
#include "gcode/grbl_client.h"

namespace gs360 {

std::vector<std::string> ProgramPreamble() {
  return {"G21", "G90"};
}

std::string MachineMoveLine(const Eigen::Vector3d& target, double feed_mm_per_min) {
  if (!target.allFinite()) throw std::invalid_argument("MachineMoveLine: target is not finite");
  if (!std::isfinite(feed_mm_per_min)) {
    throw std::invalid_argument("MachineMoveLine: feed is not finite");
  }
  std::string s = feed_mm_per_min > 0.0 ? "G53 G1" : "G53 G0";
  s.append(" X").append(FormatFixed(target.x(), 3));
  s.append(" Y").append(FormatFixed(target.y(), 3));
  s.append(" Z").append(FormatFixed(target.z(), 3));
  if (feed_mm_per_min > 0.0) s.append(" F").append(FormatFixed(feed_mm_per_min, 1));
  return s;
}

std::vector<std::string> TravelLines(const std::vector<Eigen::Vector3d>& waypoints) {
  std::vector<std::string> lines;
  lines.reserve(waypoints.size());
  for (const Eigen::Vector3d& w : waypoints) lines.push_back(MachineMoveLine(w));
  return lines;
}

ProbeProgram MakeProbeProgram(const PlannedProbe& probe, const PlanOptions& options) {
  PressMotion motion;
  motion.approach = probe.approach_machine;
  motion.press = probe.press_machine;
  motion.press_feed_mm_min = options.press_feed_mm_per_min;
  motion.dwell_s = options.settle_dwell_s;
  motion.retract_feed_mm_min = options.retract_feed_mm_per_min;
  motion.machine_coordinates = true;
  const PressGcode g = MakePressGcode(motion);

  ProbeProgram program;
  std::vector<std::string> to_approach = TravelLines(probe.travel_machine);
  to_approach.push_back(g.approach);
  if (probe.reference_before) {
    program.reference = std::move(to_approach);
    program.reference.push_back(
        std::string("G4 P").append(FormatFixed(options.reference_dwell_s, 3)));
  } else {
    program.press = std::move(to_approach);
  }
  program.press.push_back(g.press);
  program.press.push_back(g.dwell);
  if (!probe.retract_machine.isApprox(probe.approach_machine, 0.0)) {
    // The planner always retracts to the approach point; honour a different stored retract.
    program.retract.push_back(
        MachineMoveLine(probe.retract_machine, options.retract_feed_mm_per_min));
  } else {
    program.retract.push_back(g.retract);
  }
  return program;
}

std::vector<std::string> ParkLines(const ProbePlan& plan) {
  return TravelLines(plan.park_machine);
}

std::vector<std::string> RunProgram(const ProbePlan& plan, const PlanOptions& options) {
  std::vector<std::string> lines = ProgramPreamble();
  for (const PlannedProbe& p : plan.probes) {
    const ProbeProgram prog = MakeProbeProgram(p, options);
    lines.insert(lines.end(), prog.reference.begin(), prog.reference.end());
    lines.insert(lines.end(), prog.press.begin(), prog.press.end());
    lines.insert(lines.end(), prog.retract.begin(), prog.retract.end());
  }
  const auto park = ParkLines(plan);
  lines.insert(lines.end(), park.begin(), park.end());
  return lines;
}

}  // namespace gs360
