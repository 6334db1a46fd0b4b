// bench_plan: probe planning at the defaults on each built-in shape.
// Prints, per shape: candidates, kept, drops per reason, planning wall time, estimated hours
// (GRBL junction model, and the stop-at-every-block upper bound), travel vs press/dwell share,
// the nearest-neighbour and sampling-order estimates and the tour's gain, waypoints.
//
//   bench_plan [--probes N] [--kept] [--shape cylinder|cone|spline|all] [--mesh]
//
// --kept: N counts kept probes (the sampler draws only where every filter passes).
// --mesh: plan against the triangle mesh only (no analytic profile): the general code path.

#include <CLI/CLI.hpp>
#include <chrono>
#include <cstdio>
#include <string>
#include <vector>

#include "plan/plan.h"

using namespace gs360;

namespace {

void PrintPlan(const char* label, const ProbePlan& plan, const PlanOptions& options) {
  const PlanEstimate& e = plan.estimate;
  std::printf("  %-10s candidates %d, kept %zu, dropped %d:", label, plan.candidates,
              plan.probes.size(), plan.dropped.Total());
  for (int r = 0; r < kNumDropReasons; ++r) {
    std::printf(" %s %d", std::string(DropReasonName(static_cast<DropReason>(r))).c_str(),
                plan.dropped.counts[r]);
  }
  std::printf("\n");
  std::printf(
      "    planning %.2f s; estimate (%s junctions) %.3f h = %.3f s/probe; "
      "per 10,000 kept probes %.2f h\n",
      plan.planning_seconds, std::string(JunctionModelName(options.junction_model)).c_str(),
      e.Hours(), e.Total() / plan.probes.size(), e.Total() / plan.probes.size() * 10000.0 / 3600.0);
  std::printf(
      "    shares: travel+retract %.1f%% (travel %.0f s, retract %.0f s), press/dwell/host "
      "%.1f%% (press %.0f s, dwell %.0f s, host %.0f s, references %.0f s)\n",
      100.0 * e.TravelShare(), e.travel_s, e.retract_s, 100.0 * e.PressShare(), e.press_s,
      e.dwell_s, e.host_s, e.reference_s);
  std::printf(
      "    sampling order %.3f h, nearest neighbour %.3f h, tour %.3f h: gain %.2fx "
      "(%.2f h saved); travel alone %.0f s -> %.0f s\n",
      plan.sampling_order_estimate.Hours(), plan.nearest_neighbour_s / 3600.0, e.Hours(),
      plan.TourGain(), plan.sampling_order_estimate.Hours() - e.Hours(),
      plan.sampling_order_estimate.travel_s, e.travel_s);
  std::printf("    waypoints %d in %d detoured travels\n", plan.waypoints, plan.detoured_moves);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Probe planning benchmark"};
  int probes = 10000;
  bool kept = false;
  bool mesh_only = false;
  std::string shape_name = "all";
  app.add_option("--probes", probes, "candidates (or kept probes with --kept)");
  app.add_flag("--kept", kept, "count kept probes instead of candidates");
  app.add_flag("--mesh", mesh_only, "plan on the mesh only (no analytic profile)");
  app.add_option("--shape", shape_name, "cylinder, cone, spline or all");
  CLI11_PARSE(app, argc, argv);

  std::vector<SensorShape> shapes;
  if (shape_name == "all") {
    shapes = {SensorShape::kCylinderCap, SensorShape::kCone, SensorShape::kSpline};
  } else {
    shapes = {ParseSensorShape(shape_name)};
  }
  PlanOptions options;
  options.probe_count = probes;
  options.count_is_kept = kept;
  const auto& m = options.machine;
  std::printf(
      "bench_plan: %d %s, seed %llu; machine $110-112 %.0f/%.0f/%.0f mm/min, "
      "$120-122 %.0f/%.0f/%.0f mm/s^2, $11 %.3f mm; press %.1f mm at %.0f mm/min, "
      "dwell %.2f s, host per sync %.2f s\n",
      probes, kept ? "kept probes" : "candidates", static_cast<unsigned long long>(options.seed),
      m.max_rate_mm_per_min.x(), m.max_rate_mm_per_min.y(), m.max_rate_mm_per_min.z(),
      m.acceleration_mm_per_s2.x(), m.acceleration_mm_per_s2.y(), m.acceleration_mm_per_s2.z(),
      m.junction_deviation_mm, options.clearance + options.press_depth,
      options.press_feed_mm_per_min, options.settle_dwell_s,
      std::max(options.capture_time_s, options.status_poll_latency_s) + options.host_latency_s);
  for (SensorShape shape : shapes) {
    RigConfig rig_options;
    rig_options.shape.shape = shape;
    RigGeometry rig = MakeRigGeometry(rig_options);
    if (mesh_only) rig.profile = nullptr;
    std::printf("%s (%s, %d triangles%s)\n", std::string(SensorShapeName(shape)).c_str(),
                MakeProfile(rig_options.shape)->Describe().c_str(), rig.sensor_mesh.NumTriangles(),
                mesh_only ? ", mesh only" : "");
    const ProbePlan plan = MakeProbePlan(rig, options);
    PrintPlan("grbl", plan, options);
    // The same order under the stop-at-every-block upper bound.
    PlanOptions stop = options;
    stop.junction_model = JunctionModel::kStop;
    const PlanEstimate upper = EstimatePlan(plan.probes, plan.park_machine, stop);
    std::printf("    stop-at-every-block bound: %.3f h (+%.2f%% over the GRBL-junction estimate)\n",
                upper.Hours(), 100.0 * (upper.Total() / plan.estimate.Total() - 1.0));
    std::fflush(stdout);
  }
  return 0;
}
