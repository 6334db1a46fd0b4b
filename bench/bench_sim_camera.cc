// Simulated tactile camera speed: background build, no-contact frames and press frames (1 mm
// deep at random points of the sensor), per built-in shape, and checkerboard images.
// Usage: bench_sim_camera [frames_per_kind]   (default 200)
//
// Times: wall clock and the rendering thread's CPU time (the CPU time is what a frame costs on
// one core; the wall time also counts waiting for a core on a loaded machine).

#include <algorithm>
#include <cstdio>
#include <ctime>
#include <exception>
#include <limits>
#include <memory>
#include <numbers>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "sim/camera_random.h"
#include "sim/checkerboard.h"
#include "sim/ground_truth.h"
#include "sim/rig_model.h"
#include "sim/tactile_camera.h"

namespace {

double ThreadCpuSeconds() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

struct Summary {
  double mean_ms = 0.0, median_ms = 0.0, p95_ms = 0.0, cpu_mean_ms = 0.0;
};

Summary Summarize(std::vector<double> wall_ms, const std::vector<double>& cpu_ms) {
  Summary s;
  if (wall_ms.empty()) return s;
  for (const double v : wall_ms) s.mean_ms += v / static_cast<double>(wall_ms.size());
  for (const double v : cpu_ms) s.cpu_mean_ms += v / static_cast<double>(cpu_ms.size());
  std::sort(wall_ms.begin(), wall_ms.end());
  s.median_ms = wall_ms[wall_ms.size() / 2];
  s.p95_ms = wall_ms[std::min(wall_ms.size() - 1, wall_ms.size() * 95 / 100)];
  return s;
}

}  // namespace

int main(int argc, char** argv) {
  int frames = 200;
  CLI::App app(
      "bench_sim_camera: simulated tactile camera speed (background, no-contact and press frames "
      "per built-in shape, checkerboards)");
  app.option_defaults()->always_capture_default();
  app.add_option("frames_per_kind", frames, "frames rendered per kind")
      ->transform(CLI::Bound(1, std::numeric_limits<int>::max()).description("raised to >= 1"));
  CLI11_PARSE(app, argc, argv);
  try {
    std::printf("bench_sim_camera: 640x480, %d frames per kind, 1 mm presses\n", frames);
    for (const char* shape : {"cylinder", "cone", "spline"}) {
      gs360::SimRigOptions options;
      options.rig.shape.shape = gs360::ParseSensorShape(shape);
      auto rig = std::make_shared<gs360::SimRig>(options);
      gs360::TactileCamera camera(rig);
      std::printf("\n%s: %d gel triangles; background %.3f s (2 threads)\n", shape,
                  rig->gel_mesh().NumTriangles(), camera.stats().background_seconds);

      std::vector<double> wall, cpu;
      for (int k = 0; k < frames; ++k) {
        const double c0 = ThreadCpuSeconds();
        camera.RenderReference(static_cast<std::uint64_t>(k));
        cpu.push_back((ThreadCpuSeconds() - c0) * 1e3);
        wall.push_back(camera.stats().last_frame_seconds * 1e3);
      }
      const Summary ref = Summarize(wall, cpu);
      std::printf("  no-contact frame: %.2f ms mean, %.2f median, %.2f p95 (wall); %.2f ms CPU\n",
                  ref.mean_ms, ref.median_ms, ref.p95_ms, ref.cpu_mean_ms);

      gs360::SimRandom rng(42);
      wall.clear();
      cpu.clear();
      double roi = 0.0, tris = 0.0, patch_ms = 0.0, roi_ms = 0.0, image_ms = 0.0;
      for (int k = 0; k < frames; ++k) {
        const double t = rng.Uniform(0.05, 0.92);
        const double phi = rng.Uniform(0.0, 2.0 * std::numbers::pi);
        const Eigen::Vector3d ball =
            rig->profile().SurfacePoint(t, phi) +
            (rig->ball_radius() - 1.0) * rig->profile().SurfaceNormal(t, phi);
        const double c0 = ThreadCpuSeconds();
        camera.RenderAtBall(ball, static_cast<std::uint64_t>(k));
        cpu.push_back((ThreadCpuSeconds() - c0) * 1e3);
        const auto& stats = camera.stats();
        wall.push_back(stats.last_frame_seconds * 1e3);
        roi += stats.last_roi_pixels / static_cast<double>(frames);
        tris += stats.last_patch_triangles / static_cast<double>(frames);
        image_ms += stats.last_image_seconds * 1e3 / frames;
        patch_ms += stats.last_patch_seconds * 1e3 / frames;
        roi_ms += stats.last_roi_seconds * 1e3 / frames;
      }
      const Summary press = Summarize(wall, cpu);
      std::printf("  press frame:      %.2f ms mean, %.2f median, %.2f p95 (wall); %.2f ms CPU\n",
                  press.mean_ms, press.median_ms, press.p95_ms, press.cpu_mean_ms);
      std::printf(
          "    mean ROI %.0f px, patch %.0f triangles; image pass %.2f ms, patch %.2f ms, "
          "ROI %.2f ms (wall)\n",
          roi, tris, image_ms, patch_ms, roi_ms);
      std::printf("  10,000 press frames: %.1f s on one core (CPU time)\n",
                  press.cpu_mean_ms * 10.0);
    }

    gs360::SimRigOptions options;
    auto rig = std::make_shared<gs360::SimRig>(options);
    const auto& intrinsics = gs360::SimGroundTruth::TrueIntrinsics(*rig);
    gs360::CheckerboardOptions board;
    const auto poses = gs360::CheckerboardPoses(board, intrinsics, {}, 3);
    const double c0 = ThreadCpuSeconds();
    for (std::size_t k = 0; k < poses.size(); ++k) {
      gs360::RenderCheckerboard(board, poses[k], intrinsics, k);
    }
    std::printf("\ncheckerboard (4x4 supersampling): %.1f ms CPU per image (%zu images)\n",
                (ThreadCpuSeconds() - c0) * 1e3 / static_cast<double>(poses.size()), poses.size());
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_sim_camera: %s\n", e.what());
    return 1;
  }
}
