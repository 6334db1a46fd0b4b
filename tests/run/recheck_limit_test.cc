// The resume re-check's limit (engine.recheck_max_shift_px) against the virtual rig's own
// repeatability: the same press captured twice, each against its own reference frame, with other
// camera noise and LED drift, lands its impression centre how far from the first?

#include <catch2/catch.hpp>

#include <algorithm>
#include <cstdio>
#include <optional>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "capture/impression.h"
#include "cli/sim_bridge.h"
#include "run/run_config.h"
#include "run/run_engine.h"
#include "sim/rig_model.h"
#include "sim/tactile_camera.h"

using namespace gs360;

namespace {

constexpr int kFramesToAverage = 3;  // camera.capture.frames_to_average's default

// The rounded mean of K frames, as CapturePress averages them.
cv::Mat Averaged(TactileCamera& camera, const std::optional<Eigen::Vector3d>& ball,
                 std::uint64_t first_frame, double run_time_s) {
  cv::Mat sum = cv::Mat::zeros(camera.height(), camera.width(), CV_32FC3);
  for (int i = 0; i < kFramesToAverage; ++i) {
    cv::accumulate(camera.RenderAtBall(ball, first_frame + i, run_time_s), sum);
  }
  cv::Mat mean;
  sum.convertTo(mean, CV_8U, 1.0 / kFramesToAverage);
  return mean;
}

struct Capture {
  cv::Mat press, reference;
  std::optional<Impression> impression;
};

struct Shift {
  int plan_index = 0;
  double centroids_px = 0.0;  // distance between the two FindClearImpression centroids
  ImpressionShift measured;   // MeasureImpressionShift
  double distance_px = 0.0;   // what the re-check compares with its limit (ImpressionDistance)
};

struct VirtualRigCamera {
  ProbePlan plan;
  std::shared_ptr<const SimRig> rig;
  std::unique_ptr<TactileCamera> camera;
};

// The e2e test's plan (300 candidates) on the virtual rig of seed 7.
VirtualRigCamera MakeRigCamera() {
  RunConfig config;
  config.plan.probe_count = 300;
  config.plan.reference_every = 25;
  config.machine.uri = "unset";
  config.camera.uri = "unset";
  VirtualRigCamera out;
  out.plan = RunEngine::PlanRun(config).plan;
  out.rig = std::make_shared<const SimRig>(cli::SimRigOptionsFor(config.rig, 7));
  TactileCameraOptions options;
  options.sensor.seed = 7;
  out.camera = std::make_unique<TactileCamera>(out.rig, options);
  return out;
}

// Probe k's press captured as session s would: at run time s * 3 h, its reference 60 s before,
// frames of its own; the sensor moved by `sensor_move` (machine frame, mm) on the bed.
Capture CaptureAt(VirtualRigCamera& v, std::size_t k, int s, double min_peak_dn,
                  const Eigen::Vector3d& sensor_move = Eigen::Vector3d::Zero()) {
  const Eigen::Vector3d ball =
      v.rig->BallCenterSensor(v.plan.probes[k].press_machine - sensor_move);
  const double t = 3.0 * 3600.0 * s + 600.0;
  const std::uint64_t first = (static_cast<std::uint64_t>(s) * v.plan.probes.size() + k) * 8;
  Capture c;
  c.reference = Averaged(*v.camera, std::nullopt, first, t - 60.0);
  c.press = Averaged(*v.camera, ball, first + 4, t);
  c.impression = FindClearImpression(c.press, c.reference, min_peak_dn);
  return c;
}

Shift Compare(int plan_index, const Capture& then, const Capture& now) {
  Shift s;
  s.plan_index = plan_index;
  s.centroids_px = (then.impression->centroid - now.impression->centroid).norm();
  s.measured = MeasureImpressionShift(then.press, then.reference, *then.impression, now.press,
                                      now.reference);
  s.distance_px = ImpressionDistance(s.measured, *then.impression, *now.impression);
  return s;
}

// Every `stride`-th probe, `sessions` captures each; every two whose impressions are both clear.
std::vector<Shift> RepressShifts(VirtualRigCamera& v, int sessions, int stride,
                                 double min_peak_dn) {
  std::vector<Shift> shifts;
  for (std::size_t k = 0; k < v.plan.probes.size(); k += static_cast<std::size_t>(stride)) {
    std::vector<Capture> seen;
    for (int s = 0; s < sessions; ++s) seen.push_back(CaptureAt(v, k, s, min_peak_dn));
    for (int a = 0; a < sessions; ++a) {
      for (int b = a + 1; b < sessions; ++b) {
        if (!seen[a].impression || !seen[b].impression) continue;
        shifts.push_back(Compare(v.plan.probes[k].plan_index, seen[a], seen[b]));
      }
    }
  }
  return shifts;
}

double Quantile(std::vector<double> v, double q) {
  std::sort(v.begin(), v.end());
  return v[static_cast<std::size_t>(q * static_cast<double>(v.size() - 1))];
}

void PrintDistribution(const char* what, const std::vector<double>& px) {
  std::printf("%s: %zu pairs: median %.3f p90 %.3f p99 %.3f p99.9 %.3f max %.3f px\n", what,
              px.size(), Quantile(px, 0.5), Quantile(px, 0.9), Quantile(px, 0.99),
              Quantile(px, 0.999), Quantile(px, 1.0));
}

}  // namespace

TEST_CASE("measure: re-press repeatability on the virtual rig", "[.measure]") {
  const EngineConfig engine;
  VirtualRigCamera v = MakeRigCamera();
  const std::vector<Shift> shifts = RepressShifts(v, 12, 1, engine.recheck_min_peak_dn);
  std::vector<double> centroids, measured, score;
  int at_limit = 0;
  for (const Shift& s : shifts) {
    centroids.push_back(s.centroids_px);
    measured.push_back(s.distance_px);
    score.push_back(s.measured.score);
    at_limit += s.measured.at_search_limit;
  }
  REQUIRE(!shifts.empty());
  PrintDistribution("centroids", centroids);
  PrintDistribution("correlation", measured);
  std::printf("score: min %.3f p0.1 %.3f median %.3f; at search limit %d\n", Quantile(score, 0.0),
              Quantile(score, 0.001), Quantile(score, 0.5), at_limit);
  std::vector<Shift> worst = shifts;
  std::sort(worst.begin(), worst.end(), [](const Shift& a, const Shift& b) {
    return a.measured.px.norm() > b.measured.px.norm();
  });
  for (std::size_t i = 0; i < std::min<std::size_t>(8, worst.size()); ++i) {
    std::printf("  probe %d: correlation %.3f px (score %.3f), centroids %.3f px\n",
                worst[i].plan_index, worst[i].measured.px.norm(), worst[i].measured.score,
                worst[i].centroids_px);
  }
  // A sensor moved sideways on the bed: how many pixels per mm, and the smallest move caught.
  for (const double mm : {0.01, 0.02, 0.05, 0.1, 0.2, 0.6}) {
    for (const Eigen::Vector3d& dir : {Eigen::Vector3d(1, 0, 0), Eigen::Vector3d(0, 1, 0)}) {
      std::vector<double> px, cpx, sc;
      for (std::size_t k = 0; k < v.plan.probes.size(); k += 3) {
        const Capture then = CaptureAt(v, k, 0, engine.recheck_min_peak_dn);
        const Capture now = CaptureAt(v, k, 1, engine.recheck_min_peak_dn, dir * mm);
        if (!then.impression || !now.impression) continue;
        const Shift s = Compare(v.plan.probes[k].plan_index, then, now);
        px.push_back(s.distance_px);
        cpx.push_back(s.centroids_px);
        sc.push_back(s.measured.score);
      }
      std::printf(
          "move %.2f mm %s: %zu probes: correlation min %.2f median %.2f px (%.1f px/mm), "
          "centroids min %.2f median %.2f, score min %.2f\n",
          mm, dir.x() > 0 ? "x" : "y", px.size(), Quantile(px, 0.0), Quantile(px, 0.5),
          Quantile(px, 0.5) / mm, Quantile(cpx, 0.0), Quantile(cpx, 0.5), Quantile(sc, 0.0));
    }
  }
}

TEST_CASE(
    "resume re-check: the shift limit is about 5x the worst re-press repeatability on the virtual "
    "rig, "
    "and a sensor moved 0.3 mm sideways exceeds it",
    "[daemon][recheck]") {
  const EngineConfig engine;
  VirtualRigCamera v = MakeRigCamera();
  // Frames by index, drift by run time: the same figures on every run.
  const std::vector<Shift> shifts = RepressShifts(v, 4, 1, engine.recheck_min_peak_dn);
  REQUIRE(shifts.size() > 1000);
  std::vector<double> px;
  for (const Shift& s : shifts) px.push_back(s.distance_px);
  const double worst = Quantile(px, 1.0);
  INFO("re-press repeatability over " << px.size() << " pairs: median " << Quantile(px, 0.5)
                                      << ", 99.9th " << Quantile(px, 0.999) << ", largest " << worst
                                      << " px; limit " << engine.recheck_max_shift_px);
  // 1.0 px over a worst of 0.20 px: 4.9x (docs/running.md); noise never comes near it.
  CHECK(4.5 * worst <= engine.recheck_max_shift_px);

  // The sensor knocked 0.3 mm along x on the bed: most probes' impressions move past the limit,
  // and the re-check fails on the first that does.
  std::vector<double> moved;
  for (std::size_t k = 0; k < v.plan.probes.size(); k += 3) {
    const Capture then = CaptureAt(v, k, 0, engine.recheck_min_peak_dn);
    const Capture now =
        CaptureAt(v, k, 1, engine.recheck_min_peak_dn, Eigen::Vector3d(0.3, 0.0, 0.0));
    if (then.impression && now.impression) {
      moved.push_back(Compare(v.plan.probes[k].plan_index, then, now).distance_px);
    }
  }
  REQUIRE(moved.size() > 50);
  INFO("moved 0.3 mm: median " << Quantile(moved, 0.5) << " px over " << moved.size() << " probes");
  CHECK(Quantile(moved, 0.5) > 1.5 * engine.recheck_max_shift_px);
}
