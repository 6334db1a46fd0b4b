#pragma once
// The whole virtual rig in one object: a GRBL-speaking virtual CNC on a pseudo-terminal and the
// tactile camera served on a Unix socket, rendering the ball where the CNC truly is at each
// frame's time. Production code reaches it only through its pty path and "socket:" frame URI,
// exactly as it reaches real hardware. For tests, the demo and benchmarks.

#include <chrono>
#include <filesystem>
#include <memory>
#include <mutex>
#include <string>

#include "capture/frame_server.h"
#include "sim/rig_model.h"
#include "sim/tactile_camera.h"
#include "sim/virtual_cnc.h"

namespace gs360 {

struct VirtualRigOptions {
  SimRigOptions rig;
  TactileCameraOptions camera;
  VirtualCncOptions cnc;
  // The camera free-runs at this frame period in MACHINE time (scaled by cnc.time_scale; with
  // an instant CNC, min_frame_period_s of wall time).
  double frame_period_s = 1.0 / 30.0;
  double exposure_s = 0.004;           // machine time
  double min_frame_period_s = 0.002;   // wall-time floor for fast time scales
  std::filesystem::path frame_socket;  // empty: a unique path in the temp directory
  void Check() const;
};

class VirtualRig {
 public:
  // Builds the rig (camera background: ~1 s), opens the pty and the frame socket.
  explicit VirtualRig(const VirtualRigOptions& options);
  ~VirtualRig();
  VirtualRig(const VirtualRig&) = delete;
  VirtualRig& operator=(const VirtualRig&) = delete;

  std::string PtyPath() const { return cnc_->PtyPath(); }
  std::string FrameUri() const { return "socket:" + socket_path_.string(); }
  VirtualCnc& cnc() { return *cnc_; }
  TactileCamera& camera() { return *camera_; }
  std::shared_ptr<const SimRig> rig() const { return rig_; }
  const VirtualRigOptions& options() const { return options_; }

  // Ball centre (sensor frame) of every frame served so far is NOT kept; tests that need the
  // truth per frame ask the CNC's TruePosition at the frame's timestamp.

 private:
  Frame NextFrame();

  VirtualRigOptions options_;
  std::shared_ptr<const SimRig> rig_;
  std::unique_ptr<TactileCamera> camera_;
  std::unique_ptr<VirtualCnc> cnc_;
  std::filesystem::path socket_path_;
  std::chrono::steady_clock::time_point clock_start_;
  std::uint64_t frame_index_ = 0;
  std::unique_ptr<FrameServer> server_;
};

}  // namespace gs360
