// Pose estimation (calib/pose.h) and probe rendering (calib/render.h) on the virtual rig.
// Usage: bench_pose [--shape cylinder|cone|spline] [--probes N] [--depth MM] [--seed S]
//                   [--calibrated-intrinsics] [--render-only] [--weighted]
//
// 1. RenderProbe speed: N_render = 10,000 probes of the rig's default plan-like sampling through
//    the true surface map, on 1 and 2 threads.
// 2. Pose: N probes at random visible points of the sensor (seeded), each pressed `depth` mm with
//    the simulated camera (elastic gel, lighting, noise), impression = FindImpression(press,
//    reference). Reports the centroid bias (observed centroid vs the true projection of the
//    contact point, and vs the centroid of the true rigid imprint), then the pose error against
//    SimGroundTruth::TrueCamFromSensor of the paper's estimate, the refinement without and with
//    the bias model. Intrinsics: the TRUE ones, or (--calibrated-intrinsics) the output of
//    CalibrateIntrinsics on 20 simulated checkerboard images.

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <memory>
#include <numbers>
#include <optional>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>

#include "calib/impression_centroid.h"
#include "calib/intrinsics.h"
#include "calib/pose.h"
#include "calib/render.h"
#include "capture/impression.h"
#include "recon/surface_map.h"
#include "sim/checkerboard.h"
#include "sim/ground_truth.h"
#include "sim/rig_model.h"
#include "sim/tactile_camera.h"

namespace {

using gs360::PoseObservation;
using Clock = std::chrono::steady_clock;
constexpr double kRadToDeg = 180.0 / std::numbers::pi;

double Seconds(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

struct Probe {
  Eigen::Vector3d point, normal;
};

// Random visible points of the sensor as the nominal camera sees them (a stand-in for the plan).
std::vector<Probe> SampleProbes(const gs360::SimRig& rig, int count, std::uint64_t seed) {
  const gs360::FisheyeCamera nominal(rig.nominal_intrinsics());
  const gs360::Rigid3d cam_from_sensor = rig.nominal_cam_from_sensor();
  const gs360::SurfaceMap map =
      gs360::SurfaceMap::Build(nominal, cam_from_sensor, rig.gel_bvh(), &rig.fin_bvh());
  const gs360::Rigid3d sensor_from_cam = cam_from_sensor.Inverse();
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<int> du(0, map.width() - 1), dv(0, map.height() - 1);
  std::vector<Probe> probes;
  while (static_cast<int>(probes.size()) < count) {
    const int u = du(rng), v = dv(rng);
    if (!map.visible(u, v) || map.view_angle(u, v) > 70.0 / kRadToDeg) continue;
    probes.push_back({sensor_from_cam * map.point0(u, v),
                      sensor_from_cam.RotateDirection(map.normal0(u, v)).normalized()});
  }
  return probes;
}

struct Capture {
  std::vector<PoseObservation> observations;
  std::vector<Eigen::Vector2d> true_projection, true_rigid_centroid;
  std::vector<Eigen::Vector2d> weighted, hull;  // FindImpression's and the hull centroid
  int missed = 0;
  double seconds = 0.0;
};

Capture CaptureProbes(std::shared_ptr<const gs360::SimRig> rig, const std::vector<Probe>& probes,
                      double depth, int threads, bool use_hull) {
  const auto start = Clock::now();
  const double r = rig->ball_radius();
  const gs360::FisheyeCamera true_camera = gs360::SimGroundTruth::TrueCamera(*rig);
  const gs360::Rigid3d true_pose = gs360::SimGroundTruth::TrueCamFromSensor(*rig);
  const gs360::SurfaceMap true_map =
      gs360::SurfaceMap::Build(true_camera, true_pose, rig->gel_bvh(), &rig->fin_bvh());
  std::vector<std::optional<PoseObservation>> obs(probes.size());
  std::vector<Eigen::Vector2d> proj(probes.size()), rigid(probes.size());
  std::vector<Eigen::Vector2d> weighted(probes.size()), hull(probes.size());
  auto work = [&](int t) {
    gs360::TactileCameraOptions options;
    options.threads = 1;
    gs360::TactileCamera camera(rig, options);
    const cv::Mat reference = camera.RenderReference(1000000 + t);
    for (std::size_t i = t; i < probes.size(); i += threads) {
      const Probe& p = probes[i];
      const Eigen::Vector3d ball = p.point + p.normal * (r - depth);
      const cv::Mat press = camera.RenderAtBall(ball, i);
      const auto imp = gs360::FindImpression(press, reference);
      const auto region = gs360::FindImpressionRegion(press, reference);
      if (!imp || !region) continue;
      weighted[i] = imp->centroid;
      hull[i] = region->centroid;
      PoseObservation o;
      o.probe_index = static_cast<int>(i);
      o.contact_point_sensor = p.point;
      o.contact_normal_sensor = p.normal;
      o.ball_center_sensor = ball;
      o.centroid_px = use_hull ? region->centroid : imp->centroid;
      obs[i] = o;
      proj[i] = true_camera.ProjectUnchecked(true_pose * p.point);
      rigid[i] = gs360::RenderProbe(true_map, true_camera, true_pose * ball, r).contact_centroid;
    }
  };
  std::vector<std::thread> pool;
  for (int t = 1; t < threads; ++t) pool.emplace_back(work, t);
  work(0);
  for (auto& th : pool) th.join();
  Capture c;
  for (std::size_t i = 0; i < probes.size(); ++i) {
    if (!obs[i]) {
      ++c.missed;
      continue;
    }
    c.observations.push_back(*obs[i]);
    c.true_projection.push_back(proj[i]);
    c.true_rigid_centroid.push_back(rigid[i]);
    c.weighted.push_back(weighted[i]);
    c.hull.push_back(hull[i]);
  }
  c.seconds = Seconds(start);
  return c;
}

void PrintBias(const char* name, const std::vector<Eigen::Vector2d>& observed,
               const std::vector<Eigen::Vector2d>& ref) {
  std::vector<double> norms;
  Eigen::Vector2d mean = Eigen::Vector2d::Zero();
  int n = 0;
  for (std::size_t i = 0; i < ref.size(); ++i) {
    if (!ref[i].allFinite()) continue;
    const Eigen::Vector2d e = observed[i] - ref[i];
    norms.push_back(e.norm());
    mean += e;
    ++n;
  }
  std::sort(norms.begin(), norms.end());
  double rms = 0.0;
  for (double v : norms) rms += v * v;
  rms = std::sqrt(rms / std::max(1, n));
  std::printf("  %-40s median %.3f px, rms %.3f px, p95 %.3f px, mean (%.3f, %.3f) px\n", name,
              norms[norms.size() / 2], rms, norms[norms.size() * 95 / 100], mean.x() / n,
              mean.y() / n);
}

void PrintPose(const char* name, const gs360::Rigid3d& est, const gs360::Rigid3d& truth) {
  // Error of the camera centre (sensor frame) and of the orientation.
  const Eigen::Vector3d c_est = est.Inverse().translation, c_true = truth.Inverse().translation;
  std::printf("  %-30s centre error %.4f mm, rotation error %.4f deg\n", name,
              (c_est - c_true).norm(), gs360::RotationDifferenceRad(est, truth) * kRadToDeg);
}

gs360::FisheyeIntrinsics CalibratedIntrinsics(const gs360::SimRig& rig) {
  const gs360::FisheyeIntrinsics& truth = gs360::SimGroundTruth::TrueIntrinsics(rig);
  gs360::CheckerboardOptions board;
  gs360::CheckerboardPoseOptions pose_options;
  pose_options.count = 20;
  std::vector<cv::Mat> images;
  std::uint64_t k = 0;
  for (const auto& pose : gs360::CheckerboardPoses(board, truth, pose_options, 5)) {
    images.push_back(gs360::RenderCheckerboard(board, pose, truth, 100 + k++));
  }
  const auto result = gs360::CalibrateIntrinsics(images, rig.nominal_intrinsics());
  std::printf("  intrinsics stage: rms %.3f px, max ray error vs truth %.4f deg\n", result.rms_px,
              gs360::MaxRayAngleDifference(result.intrinsics, truth, 4) * kRadToDeg);
  return result.intrinsics;
}

void BenchRender(const gs360::SimRig& rig) {
  const gs360::FisheyeCamera camera = gs360::SimGroundTruth::TrueCamera(rig);
  const gs360::Rigid3d pose = gs360::SimGroundTruth::TrueCamFromSensor(rig);
  const auto t_map = Clock::now();
  const gs360::SurfaceMap map =
      gs360::SurfaceMap::Build(camera, pose, rig.gel_bvh(), &rig.fin_bvh());
  const double map_s = Seconds(t_map);
  const std::vector<Probe> probes = SampleProbes(rig, 10000, 77);
  for (int threads : {1, 2}) {
    std::vector<long> pixels(threads, 0), contact(threads, 0);
    const auto start = Clock::now();
    auto work = [&](int t) {
      for (std::size_t i = t; i < probes.size(); i += threads) {
        const Eigen::Vector3d ball = probes[i].point + probes[i].normal * (rig.ball_radius() - 1.0);
        const gs360::ProbeRender pr =
            gs360::RenderProbe(map, camera, pose * ball, rig.ball_radius());
        pixels[t] += pr.roi.area();
        contact[t] += pr.contact_pixels;
      }
    };
    std::vector<std::thread> pool;
    for (int t = 1; t < threads; ++t) pool.emplace_back(work, t);
    work(0);
    for (auto& th : pool) th.join();
    const double s = Seconds(start);
    long px = 0, cp = 0;
    for (int t = 0; t < threads; ++t) {
      px += pixels[t];
      cp += contact[t];
    }
    std::printf(
        "  RenderProbe: 10000 probes (1 mm) on %d thread(s): %.3f s (%.1f us/probe), "
        "mean box %.0f px, mean contact %.0f px\n",
        threads, s, 1e6 * s / 10000.0 * threads, px / 1e4, cp / 1e4);
  }
  std::printf("  (surface map build: %.3f s)\n", map_s);
}

struct Args {
  std::string shape = "cylinder";
  int probes = 2000;
  double depth = 1.0;
  std::uint64_t seed = 1;
  bool calibrated = false, render_only = false, weighted = false;
};

// Accepts what gs360::ParseSensorShape accepts; its message otherwise.
CLI::Validator SensorShapeCheck() {
  return CLI::Validator(
      [](const std::string& name) {
        try {
          gs360::ParseSensorShape(name);
          return std::string();
        } catch (const std::exception& e) {
          return std::string(e.what());
        }
      },
      "cylinder|cone|spline");
}

void AddOptions(CLI::App& app, Args& args) {
  app.option_defaults()->always_capture_default();
  app.add_option("--shape", args.shape, "sensor shape of the virtual rig")
      ->check(SensorShapeCheck());
  app.add_option("--probes", args.probes, "probes pressed for the pose estimate")
      ->check(CLI::PositiveNumber);
  app.add_option("--depth", args.depth, "press depth, mm");
  app.add_option("--seed", args.seed, "seed of the probe sampling and of the pose estimate");
  app.add_flag("--calibrated-intrinsics", args.calibrated,
               "use intrinsics calibrated on 20 simulated checkerboards, not the true ones");
  app.add_flag("--render-only", args.render_only, "only the RenderProbe speed, no pose");
  app.add_flag("--weighted", args.weighted,
               "estimate the pose from the weighted centroids instead of the hull ones");
}

int Run(const Args& args) {
  try {
    const std::string& shape = args.shape;
    const int probes = args.probes;
    const double depth = args.depth;
    const std::uint64_t seed = args.seed;
    const bool calibrated = args.calibrated, use_hull = !args.weighted;
    gs360::SimRigOptions rig_options;
    rig_options.rig.shape.shape = gs360::ParseSensorShape(shape);
    auto rig = std::make_shared<gs360::SimRig>(rig_options);
    std::printf("bench_pose: %s, %d probes, press %.2f mm, seed %llu\n", shape.c_str(), probes,
                depth, static_cast<unsigned long long>(seed));
    BenchRender(*rig);
    if (args.render_only) return 0;

    const Capture cap = CaptureProbes(rig, SampleProbes(*rig, probes, seed), depth, 2, use_hull);
    std::printf("  captured %zu impressions (%d without one) in %.1f s\n", cap.observations.size(),
                cap.missed, cap.seconds);
    std::printf("  centroid bias (observed - truth through the true camera):\n");
    PrintBias("weighted - projected contact point", cap.weighted, cap.true_projection);
    PrintBias("weighted - rigid imprint centroid", cap.weighted, cap.true_rigid_centroid);
    PrintBias("hull - projected contact point", cap.hull, cap.true_projection);
    PrintBias("hull - rigid imprint centroid", cap.hull, cap.true_rigid_centroid);
    std::printf("  pose from the %s centroids\n", use_hull ? "hull" : "weighted");

    const gs360::Rigid3d truth = gs360::SimGroundTruth::TrueCamFromSensor(*rig);
    const gs360::FisheyeCamera camera(calibrated ? CalibratedIntrinsics(*rig)
                                                 : gs360::SimGroundTruth::TrueIntrinsics(*rig));
    PrintPose("nominal (CAD)", rig->nominal_cam_from_sensor(), truth);
    gs360::PoseOptions options;
    options.ball_radius_mm = rig->ball_radius();
    options.seed = seed;
    const gs360::PoseScene scene{&rig->gel_bvh(), &rig->fin_bvh()};
    options.model_bias = false;
    const auto plain = gs360::EstimateCamFromSensor(camera, cap.observations,
                                                    rig->nominal_cam_from_sensor(), options, scene);
    options.model_bias = true;
    const auto biased = gs360::EstimateCamFromSensor(
        camera, cap.observations, rig->nominal_cam_from_sensor(), options, scene);
    PrintPose("paper (RANSAC PnP, 100)", biased.paper_cam_from_sensor, truth);
    std::printf("    paper rms %.3f px, %d inliers\n", biased.paper_rms_px, biased.paper_inliers);
    PrintPose("refined, no bias model", plain.cam_from_sensor, truth);
    std::printf("    rms %.3f px, %d inliers, %d outliers, %.2f s\n", plain.rms_px, plain.inliers,
                plain.outliers, plain.seconds);
    PrintPose("refined, bias model", biased.cam_from_sensor, truth);
    std::printf("    rms %.3f px, %d inliers, %d outliers, mean bias %.3f px, %d rounds, %.2f s\n",
                biased.rms_px, biased.inliers, biased.outliers, biased.mean_bias_px,
                biased.bias_rounds, biased.seconds);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_pose: %s\n", e.what());
    return 1;
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  Args args;
  CLI::App app(
      "bench_pose: RenderProbe speed and camera pose from simulated impressions (RANSAC PnP vs "
      "the refinement with the bias model) on the virtual rig");
  AddOptions(app, args);
  CLI11_PARSE(app, argc, argv);
  return Run(args);
}
