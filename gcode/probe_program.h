#pragma once
// The G-code of a planned run, probe by probe, split at the sync points the host waits for.
//
// Every motion line targets machine coordinates (G53, GRBL MPos) so that a work offset left in
// the controller (G54, G92) cannot shift a press; coordinates have 3 decimals, feeds 1, dwells 3,
// formatted locale-independently (base/format.h FormatFixed, gcode/grbl_client.h MakePressGcode).
// A probe:
//
//   reference (only when probe.reference_before):
//     G53 G0 <travel waypoints>...            rapid, pipelined
//     G90 G53 G0 X Y Z                        approach
//     G4 P<reference_dwell_s>                 sync: its ok -> take the no-contact reference frame
//   press:
//     [travel + approach as above, when no reference]
//     G53 G1 X Y Z F<press_feed>              press to full depth
//     G4 P<settle_dwell_s>                    sync: its ok -> take the press frame
//   retract (send only after the frame):
//     G53 G0 X Y Z   (G1 ... F<retract_feed> when retract_feed_mm_per_min > 0)
//
// The retract is followed (pipelined) by the next probe's travel: the motion between two frames
// is retract + travel + approach + press, planned by the firmware as one path, which is exactly
// what EstimatePlan() times.

#include <Eigen/Core>
#include <string>
#include <vector>

#include "plan/plan.h"

namespace gs360 {

struct ProbeProgram {
  std::vector<std::string> reference;  // empty when the probe takes no reference frame
  std::vector<std::string> press;      // ends with the press's G4 (the frame's sync point)
  std::vector<std::string> retract;    // after the frame
};

// "G21" (mm) and "G90" (absolute): sent once before the first probe.
std::vector<std::string> ProgramPreamble();

// "G53 G0 X.. Y.. Z.." (feed <= 0) or "G53 G1 X.. Y.. Z.. F.." (machine coordinates).
std::string MachineMoveLine(const Eigen::Vector3d& target, double feed_mm_per_min = 0.0);

// Rapid moves through `waypoints` (machine frame, in order).
std::vector<std::string> TravelLines(const std::vector<Eigen::Vector3d>& waypoints);

// The lines of one probe. Throws std::invalid_argument for non-finite positions or invalid feeds.
ProbeProgram MakeProbeProgram(const PlannedProbe& probe, const PlanOptions& options);

// Lines back to the start after the last probe's retract (plan.park_machine).
std::vector<std::string> ParkLines(const ProbePlan& plan);

// The whole run as one program (preamble, every probe's reference / press / retract, park): for
// dry runs, other G-code senders, and EstimateProgram().
std::vector<std::string> RunProgram(const ProbePlan& plan, const PlanOptions& options);

}  // namespace gs360
