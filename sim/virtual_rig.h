#pragma once
// The whole virtual rig in one object: a GRBL-speaking virtual CNC on a pseudo-terminal and the
// tactile camera served on a Unix socket, rendering the ball where the CNC truly is at each
// frame's time. Production code reaches it only through its pty path and "socket:" frame URI,
// exactly as it reaches real hardware. For tests, the demo and benchmarks.

#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <deque>
#include <filesystem>
#include <memory>
#include <mutex>
#include <random>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

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
  // ServedFrame records kept (the oldest are dropped beyond this; 0 keeps none). ~250 bytes each.
  std::size_t frame_log_capacity = 1u << 16;
  void Check() const;
};

// Pixels whose values a ServedFrame keeps: enough to recognise a frame, or the rounded mean of
// consecutive frames, by content alone (camera noise makes every frame's values unique).
inline constexpr int kFingerprintPixels = 64;

// One frame the rig's camera served, in serving order: ground truth for checking captures
// (cli/sim_bridge.h, CheckCapturesAgainstTruth).
struct ServedFrame {
  std::uint64_t sequence = 0;                         // Frame::sequence
  std::chrono::steady_clock::time_point timestamp{};  // exposure end, as served (Frame::timestamp)
  std::chrono::microseconds exposure{0};              // Frame::exposure
  // The tool's true position (machine frame, mm) the frame was rendered at (exposure end).
  Eigen::Vector3d machine_position = Eigen::Vector3d::Zero();
  // B, G, R of the image at FingerprintPixels(width, height), pixel by pixel.
  std::array<std::uint8_t, 3 * kFingerprintPixels> fingerprint{};
  // Served damaged (CorruptNextFrames): no capture may count it as a press frame.
  bool corrupted = false;
};

// The kFingerprintPixels pixels (x, y) a ServedFrame keeps for a width x height image: a
// golden-angle spiral over the central disc (radius 0.4 min(width, height)), where the gel is.
// Throws std::invalid_argument for a non-positive size.
std::vector<cv::Point> FingerprintPixels(int width, int height);
// The values of `image` (CV_8UC3) at those pixels, as in ServedFrame::fingerprint. Throws
// std::invalid_argument for another type or an empty image.
std::array<std::uint8_t, 3 * kFingerprintPixels> FrameFingerprint(const cv::Mat& image);

class VirtualRig {
 public:
  // Builds the rig (including the camera's static background, whose build time is measured by
  // bench/bench_sim_camera: docs/benchmarks.md, "Virtual rig"), opens the pty and the frame
  // socket.
  explicit VirtualRig(const VirtualRigOptions& options);
  ~VirtualRig();
  VirtualRig(const VirtualRig&) = delete;
  VirtualRig& operator=(const VirtualRig&) = delete;

  std::string PtyPath() const { return cnc_->PtyPath(); }
  std::string FrameUri() const { return "socket:" + socket_path_.string(); }
  VirtualCnc& cnc() { return *cnc_; }
  const VirtualCnc& cnc() const { return *cnc_; }
  TactileCamera& camera() { return *camera_; }
  std::shared_ptr<const SimRig> rig() const { return rig_; }
  const VirtualRigOptions& options() const { return options_; }

  // The frames served so far, oldest first: the latest options().frame_log_capacity of them.
  // Thread-safe.
  std::vector<ServedFrame> ServedFrames() const;

  // --- Camera faults (thread-safe; they add to what is pending) ---
  // The next n frames are never delivered (a USB hiccup, a full buffer): the frame after them is
  // served in their place, its sequence number showing the gap.
  void DropNextFrames(int n);
  // The next n frames are served damaged: at random, a band of garbage rows (a corrupt transfer)
  // or a black frame (a sensor timeout). Logged with ServedFrame::corrupted.
  void CorruptNextFrames(int n);
  // Camera faults injected so far.
  int FramesDropped() const { return frames_dropped_.load(); }
  int FramesCorrupted() const { return frames_corrupted_.load(); }

 private:
  Frame NextFrame();
  bool DamageIfDue(cv::Mat* image);

  VirtualRigOptions options_;
  std::shared_ptr<const SimRig> rig_;
  std::unique_ptr<TactileCamera> camera_;
  std::unique_ptr<VirtualCnc> cnc_;
  std::filesystem::path socket_path_;
  std::chrono::steady_clock::time_point clock_start_;
  std::uint64_t frame_index_ = 0;
  std::atomic<int> drop_pending_{0}, corrupt_pending_{0};
  std::atomic<int> frames_dropped_{0}, frames_corrupted_{0};
  std::mt19937_64 fault_rng_{12345};  // NextFrame's thread only
  mutable std::mutex log_mutex_;
  std::deque<ServedFrame> served_;
  std::unique_ptr<FrameServer> server_;
};

}  // namespace gs360
