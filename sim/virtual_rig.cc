#include "sim/virtual_rig.h"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <numbers>
#include <stdexcept>
#include <string>
#include <thread>

#include "sim/ground_truth.h"

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

std::vector<cv::Point> FingerprintPixels(int width, int height) {
  if (width <= 0 || height <= 0) {
    throw std::invalid_argument("FingerprintPixels: size must be positive, got " +
                                std::to_string(width) + "x" + std::to_string(height));
  }
  const double radius = 0.4 * std::min(width, height);
  const double golden_angle = std::numbers::pi * (3.0 - std::sqrt(5.0));
  std::vector<cv::Point> pixels;
  pixels.reserve(kFingerprintPixels);
  for (int i = 0; i < kFingerprintPixels; ++i) {
    const double r = radius * std::sqrt((i + 0.5) / kFingerprintPixels);
    const double a = golden_angle * i;
    const int x =
        std::clamp(static_cast<int>(std::lround(0.5 * width + r * std::cos(a))), 0, width - 1);
    const int y =
        std::clamp(static_cast<int>(std::lround(0.5 * height + r * std::sin(a))), 0, height - 1);
    pixels.emplace_back(x, y);
  }
  return pixels;
}

std::array<std::uint8_t, 3 * kFingerprintPixels> FrameFingerprint(const cv::Mat& image) {
  if (image.empty() || image.type() != CV_8UC3) {
    throw std::invalid_argument("FrameFingerprint: expected a non-empty CV_8UC3 image");
  }
  std::array<std::uint8_t, 3 * kFingerprintPixels> out{};
  const std::vector<cv::Point> pixels = FingerprintPixels(image.cols, image.rows);
  for (int i = 0; i < kFingerprintPixels; ++i) {
    const cv::Vec3b& bgr = image.at<cv::Vec3b>(pixels[i]);
    for (int c = 0; c < 3; ++c) out[3 * i + c] = bgr[c];
  }
  return out;
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
  auto k = static_cast<std::uint64_t>(std::floor(since / period_s)) + 1;
  if (const int drop = drop_pending_.exchange(0); drop > 0) {
    k += static_cast<std::uint64_t>(drop);  // those frames are exposed, never delivered
    frames_dropped_ += drop;
  }
  const auto end = clock_start_ + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                      std::chrono::duration<double>(k * period_s));
  std::this_thread::sleep_until(end);
  Frame frame;
  frame.image = camera_->Render(end);
  frame.timestamp = end;
  frame.exposure = std::chrono::microseconds(static_cast<long long>(exposure_s * 1e6));
  frame.sequence = k;
  ++frame_index_;
  const bool corrupted = DamageIfDue(&frame.image);
  if (options_.frame_log_capacity > 0) {
    ServedFrame record;
    record.sequence = frame.sequence;
    record.timestamp = frame.timestamp;
    record.exposure = frame.exposure;
    record.machine_position = *SimGroundTruth::LastFrame(*camera_).machine_position;
    record.fingerprint = FrameFingerprint(frame.image);
    record.corrupted = corrupted;
    std::lock_guard<std::mutex> lock(log_mutex_);
    served_.push_back(record);
    while (served_.size() > options_.frame_log_capacity) served_.pop_front();
  }
  return frame;
}

bool VirtualRig::DamageIfDue(cv::Mat* image) {
  int pending = corrupt_pending_.load();
  while (pending > 0 && !corrupt_pending_.compare_exchange_weak(pending, pending - 1)) {
  }
  if (pending <= 0) return false;
  ++frames_corrupted_;
  if (fault_rng_() % 4 == 0) {
    image->setTo(cv::Scalar::all(0));
    return true;
  }
  // 2-15 % of the rows, anywhere: noise as a broken transfer leaves it.
  const int rows = std::max(1, image->rows * (2 + static_cast<int>(fault_rng_() % 14)) / 100);
  const int from =
      static_cast<int>(fault_rng_() % static_cast<std::uint64_t>(image->rows - rows + 1));
  for (int r = from; r < from + rows; ++r) {
    auto* p = image->ptr<std::uint8_t>(r);
    for (std::size_t i = 0; i < image->cols * image->elemSize(); ++i) {
      p[i] = static_cast<std::uint8_t>(fault_rng_());
    }
  }
  return true;
}

void VirtualRig::DropNextFrames(int n) {
  if (n < 0)
    throw std::invalid_argument("VirtualRig::DropNextFrames: n must be >= 0, got " +
                                std::to_string(n));
  drop_pending_ += n;
}

void VirtualRig::CorruptNextFrames(int n) {
  if (n < 0)
    throw std::invalid_argument("VirtualRig::CorruptNextFrames: n must be >= 0, got " +
                                std::to_string(n));
  corrupt_pending_ += n;
}

std::vector<ServedFrame> VirtualRig::ServedFrames() const {
  std::lock_guard<std::mutex> lock(log_mutex_);
  return {served_.begin(), served_.end()};
}

}  // namespace gs360
