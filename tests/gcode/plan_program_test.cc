// G-code of a planned probe and of a whole run; the run's G-code timed by EstimateProgram agrees
// with the plan's estimate.

#include <algorithm>
#include <catch2/catch.hpp>
#include <clocale>
#include <cmath>

#include "gcode/probe_program.h"

using namespace gs360;

namespace {

PlannedProbe HandProbe() {
  PlannedProbe p;
  p.approach_machine = Eigen::Vector3d(-150.0, -87.0004, -20.25);
  p.press_machine = Eigen::Vector3d(-150.0, -89.0, -20.25);
  p.retract_machine = p.approach_machine;
  p.travel_machine = {Eigen::Vector3d(-0.0001, -5.5, -3.0)};
  return p;
}

}  // namespace

TEST_CASE("A probe's G-code: travel, approach, press, sync dwell, retract", "[plan]") {
  const PlanOptions o;
  const ProbeProgram prog = MakeProbeProgram(HandProbe(), o);
  CHECK(prog.reference.empty());
  const std::vector<std::string> press{
      "G53 G0 X0.000 Y-5.500 Z-3.000",              // waypoint; -0.0001 prints as 0.000
      "G90 G53 G0 X-150.000 Y-87.000 Z-20.250",     // approach
      "G53 G1 X-150.000 Y-89.000 Z-20.250 F120.0",  // press
      "G4 P0.300"};                                 // the frame's sync point
  CHECK(prog.press == press);
  CHECK(prog.retract == std::vector<std::string>{"G53 G0 X-150.000 Y-87.000 Z-20.250"});

  PlanOptions slow = o;
  slow.retract_feed_mm_per_min = 600.0;
  slow.settle_dwell_s = 0.5;
  slow.reference_dwell_s = 0.25;
  PlannedProbe ref = HandProbe();
  ref.reference_before = true;
  ref.travel_machine.clear();
  const ProbeProgram r = MakeProbeProgram(ref, slow);
  CHECK(r.reference ==
        std::vector<std::string>{"G90 G53 G0 X-150.000 Y-87.000 Z-20.250", "G4 P0.250"});
  CHECK(r.press ==
        std::vector<std::string>{"G53 G1 X-150.000 Y-89.000 Z-20.250 F120.0", "G4 P0.500"});
  CHECK(r.retract == std::vector<std::string>{"G53 G1 X-150.000 Y-87.000 Z-20.250 F600.0"});
  // Locale-independent.
  const char* old = std::setlocale(LC_NUMERIC, "de_DE.UTF-8");
  CHECK(MachineMoveLine({-1.5, 2.25, 0.0}) == "G53 G0 X-1.500 Y2.250 Z0.000");
  if (old) std::setlocale(LC_NUMERIC, "C");
  CHECK_THROWS_AS(MachineMoveLine({std::nan(""), 0, 0}), std::invalid_argument);
}

TEST_CASE("The run's G-code timed by EstimateProgram equals the plan's estimate", "[plan]") {
  PlanOptions o;
  o.probe_count = 150;
  o.reference_every = 30;
  const ProbePlan plan = MakeProbePlan(MakeRigGeometry(), o);
  const std::vector<std::string> lines = RunProgram(plan, o);
  CHECK(lines.front() == "G21");
  // Every line fits GRBL's 80-character line buffer and its 128-byte RX buffer.
  for (const std::string& l : lines) CHECK(l.size() < 80);
  for (JunctionModel model : {JunctionModel::kGrbl, JunctionModel::kStop}) {
    PlanOptions m = o;
    m.junction_model = model;
    const PlanEstimate e = EstimatePlan(plan.probes, plan.park_machine, m);
    const ProgramEstimate g = EstimateProgram(lines, o.start_machine, o.machine, model);
    // Machine time = motion + dwells; the host's time per sync comes on top.
    const double machine = e.travel_s + e.press_s + e.retract_s + e.dwell_s;
    const int refs = static_cast<int>(std::count_if(
        plan.probes.begin(), plan.probes.end(), [](const auto& p) { return p.reference_before; }));
    CHECK(g.syncs == static_cast<int>(plan.probes.size()) + refs);
    CHECK(g.dwell_s == Approx(e.dwell_s + refs * o.reference_dwell_s));
    // Positions are rounded to 0.001 mm in the G-code (a 0.5 um longer press costs 0.25 ms).
    CHECK(g.motion_s + g.dwell_s == Approx(machine + refs * o.reference_dwell_s).epsilon(1e-4));
    CHECK((g.end_position - o.start_machine).norm() < 1e-9);
  }
}
