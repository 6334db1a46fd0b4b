#include "sim/virtual_rig.h"

#include <unistd.h>

#include <atomic>
#include <cmath>
#include <stdexcept>
#include <thread>

namespace gs360 {

void VirtualRigOptions::Check() const {
  rig.Check();
  camera.Check();
  cnc.Check();
  if (!(frame_period_s > 0.0)) {
    throw std::invalid_argument("VirtualRigOptions.frame_period_s must be > 0, got " +
                                std::to_string(frame_period_s));
  }
  if (!(exposure_s > 0.0 && exposure_s <= frame_period_s)) {
    throw std::invalid_argument(
        "VirtualRigOptions.exposure_s must be in (0, frame_period_s], got " +
        std::to_string(exposure_s));
  }
  if (!(min_frame_period_s > 0.0)) {
    throw std::invalid_argument("VirtualRigOptions.min_frame_period_s must be > 0, got " +
                                std::to_string(min_frame_period_s));
  }
}

VirtualRig::VirtualRig(const VirtualRigOptions& options) : options_(options) {
  options_.Check();
  rig_ = std::make_shared<SimRig>(options_.rig);
  camera_ = std::make_unique<TactileCamera>(rig_, options_.camera);
  cnc_ = std::make_unique<VirtualCnc>(options_.cnc);
  VirtualCnc* cnc = cnc_.get();
  camera_->SetMachinePositionSource(
      [cnc](std::chrono::steady_clock::time_point t) { return cnc->TruePosition(t); });
  clock_start_ = std::chrono::steady_clock::now();
  camera_->SetRunStart(clock_start_);
  socket_path_ = options_.frame_socket;
  if (socket_path_.empty()) {
    static std::atomic<int> counter{0};
    socket_path_ =
        std::filesystem::temp_directory_path() /
        ("gs360-rig-" + std::to_string(::getpid()) + "-" + std::to_string(counter++) + ".sock");
  }
  server_ = std::make_unique<FrameServer>(socket_path_, [this] { return NextFrame(); });
}

VirtualRig::~VirtualRig() {
  server_.reset();  // no frame is rendered after this
  cnc_->Stop();
}

Frame VirtualRig::NextFrame() {
  // A free-running camera: frame k ends its exposure at clock_start_ + k * period. A request
  // gets the next frame that ends after it, as a real camera's next buffer would.
  const double scale = options_.cnc.time_scale;
  const double period_s =
      scale > 0.0 ? std::max(options_.frame_period_s / scale, options_.min_frame_period_s)
                  : options_.min_frame_period_s;
  const double exposure_s =
      scale > 0.0 ? std::min(options_.exposure_s / scale, period_s) : period_s * 0.5;
  const auto now = std::chrono::steady_clock::now();
  const double since = std::chrono::duration<double>(now - clock_start_).count();
  const auto k = static_cast<std::uint64_t>(std::floor(since / period_s)) + 1;
  const auto end = clock_start_ + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                      std::chrono::duration<double>(k * period_s));
  std::this_thread::sleep_until(end);
  Frame frame;
  frame.image = camera_->Render(end);
  frame.timestamp = end;
  frame.exposure = std::chrono::microseconds(static_cast<long long>(exposure_s * 1e6));
  frame.sequence = k;
  ++frame_index_;
  return frame;
}

}  // namespace gs360
