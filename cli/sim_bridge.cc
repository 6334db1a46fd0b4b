#include "cli/sim_bridge.h"

#include <cstdio>
#include <stdexcept>

#include <opencv2/imgcodecs.hpp>

#include "sim/checkerboard.h"
#include "sim/ground_truth.h"

namespace gs360::cli {

SimRigOptions SimRigOptionsFor(const RigConfig& rig, std::uint64_t seed) {
  SimRigOptions sim;
  sim.shape = rig.shape;
  sim.mesh_path = rig.mesh_path;
  sim.fins = rig.fins;
  sim.nominal_intrinsics = rig.camera;
  sim.camera_z = rig.camera_z;
  sim.machine_from_sensor = rig.machine_from_sensor();
  sim.tool_offset = rig.tool_offset;
  sim.ball_radius = rig.ball_radius;
  sim.seed = seed;
  return sim;
}

int WriteSimCheckerboards(const SimRig& rig, const std::filesystem::path& dir, int count,
                          std::uint64_t seed) {
  std::filesystem::create_directories(dir);
  const FisheyeIntrinsics& lens = SimGroundTruth::TrueIntrinsics(rig);
  CheckerboardOptions board;
  CheckerboardPoseOptions pose_options;
  pose_options.count = count;
  const std::vector<Rigid3d> poses = CheckerboardPoses(board, lens, pose_options, seed);
  int written = 0;
  for (std::size_t i = 0; i < poses.size(); ++i) {
    const cv::Mat image = RenderCheckerboard(board, poses[i], lens, seed * 1000 + i);
    char name[32];
    std::snprintf(name, sizeof(name), "board_%02zu.png", i);
    if (!cv::imwrite((dir / name).string(), image)) {
      throw std::runtime_error("cannot write " + (dir / name).string());
    }
    ++written;
  }
  return written;
}

VirtualSetup MakeVirtualSetup(RunConfig config, double time_scale, std::uint64_t seed,
                              const std::filesystem::path& frame_socket,
                              const std::string& symlink) {
  VirtualRigOptions options;
  options.rig = SimRigOptionsFor(config.rig, seed);
  options.camera.sensor.seed = seed;
  options.cnc.time_scale = time_scale;
  options.cnc.symlink_path = symlink;
  // Enough motion history to verify every frame of a 10,000-probe run against the truth.
  options.cnc.history_pieces = 1u << 18;
  options.frame_socket = frame_socket;
  VirtualSetup setup;
  setup.rig = std::make_unique<VirtualRig>(options);
  config.machine.uri = symlink.empty() ? setup.rig->PtyPath() : symlink;
  config.camera.uri = setup.rig->FrameUri();
  setup.config = std::move(config);
  return setup;
}

}  // namespace gs360::cli

namespace gs360::cli {

CaptureTruth CheckCapturesAgainstTruth(const VirtualCnc& cnc, const RunDatabase& db,
                                       std::int64_t run_id, double tolerance_mm) {
  using Clock = std::chrono::steady_clock;
  const double unix_now =
      std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
  const Clock::time_point steady_now = Clock::now();
  auto to_steady = [&](double unix_s) {
    return steady_now + std::chrono::duration_cast<Clock::duration>(
                            std::chrono::duration<double>(unix_s - unix_now));
  };
  CaptureTruth truth;
  for (const CapturedProbe& c : db.ListCapturedProbes(run_id)) {
    ++truth.frames;
    Eigen::Vector3d at_frame, at_sync;
    try {
      at_frame = cnc.TruePosition(to_steady(c.frame_time));
      at_sync = cnc.TruePosition(to_steady(*c.probe.sync_time));
    } catch (const std::out_of_range&) {
      ++truth.unverified;
      continue;
    }
    const double err = std::max((at_frame - c.probe.plan.press_machine).norm(),
                                (at_sync - c.probe.plan.press_machine).norm());
    truth.max_error_mm = std::max(truth.max_error_mm, err);
    if (err > tolerance_mm) ++truth.off_target;
    if (c.probe.machine_position) {
      truth.max_reported_error_mm =
          std::max(truth.max_reported_error_mm, (*c.probe.machine_position - at_frame).norm());
    }
  }
  return truth;
}

}  // namespace gs360::cli
