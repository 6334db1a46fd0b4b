// Compiled only when OpenCV's videoio module is available (GS360_HAVE_OPENCV_VIDEOIO).
#include "capture/v4l2_source.h"

#include <sys/stat.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <optional>
#include <sstream>
#include <utility>
#include <vector>

#include <spdlog/spdlog.h>
#include <opencv2/videoio.hpp>

namespace gs360 {
namespace {

using Clock = std::chrono::steady_clock;

std::string FourccString(double value) {
  const auto v = static_cast<std::uint32_t>(value);
  std::string s;
  for (int i = 0; i < 4; ++i) {
    const char c = static_cast<char>((v >> (8 * i)) & 0xff);
    s += (c >= 32 && c < 127) ? c : '?';
  }
  return s;
}

class V4l2FrameSource : public FrameSource {
 public:
  V4l2FrameSource(const FrameSourceUri& uri, std::string device, const CameraControls& controls)
      : uri_(uri), device_(std::move(device)), controls_(controls) {
    fourcc_ = uri_.Option("fourcc");
    if (fourcc_ && fourcc_->size() != 4) {
      throw FrameSourceError(FrameSourceErrc::kBadUri, uri_.uri,
                             "option 'fourcc' must have 4 characters, got '" + *fourcc_ + "'");
    }
    fps_ = uri_.DoubleOption("fps");
    if (fps_ && (*fps_ <= 0.0 || *fps_ > 1000.0)) {
      throw FrameSourceError(FrameSourceErrc::kBadUri, uri_.uri,
                             "option 'fps' must be in (0, 1000], got " + *uri_.Option("fps"));
    }
    const auto buffers = uri_.DoubleOption("buffers");
    if (buffers) {
      if (*buffers < 1 || *buffers > 16 || std::floor(*buffers) != *buffers) {
        throw FrameSourceError(
            FrameSourceErrc::kBadUri, uri_.uri,
            "option 'buffers' must be an integer in [1, 16], got " + *uri_.Option("buffers"));
      }
      buffers_ = static_cast<int>(*buffers);
    }
    wb_temperature_ = uri_.DoubleOption("wb_temperature");
    OpenDevice();
  }

  ~V4l2FrameSource() override { Stop(); }

  void Start() override {
    if (started_) return;
    if (captures_.empty()) OpenDevice();
    started_ = true;
  }

  void Stop() override {
    started_ = false;
    if (!captures_.empty()) {
      captures_.front().release();
      captures_.clear();
    }
  }

  std::optional<Frame> Next(std::chrono::milliseconds timeout) override {
    if (!started_) {
      throw std::logic_error("V4l2FrameSource::Next() before Start() (" + uri_.uri + ")");
    }
    std::vector<int> ready;
    bool any = false;
    try {
      const std::int64_t timeout_ns =
          std::chrono::duration_cast<std::chrono::nanoseconds>(timeout).count();
      any = cv::VideoCapture::waitAny(captures_, ready, std::max<std::int64_t>(timeout_ns, 1));
    } catch (const cv::Exception& e) {
      ThrowIfGone();
      throw FrameSourceError(FrameSourceErrc::kIo, uri_.uri,
                             "waiting for a frame from " + device_ + " failed: " + e.what());
    }
    if (!any || ready.empty()) {
      ThrowIfGone();
      return std::nullopt;
    }
    const Clock::time_point received = Clock::now();
    Frame frame;
    if (!captures_.front().retrieve(frame.image) || frame.image.empty()) {
      ThrowIfGone();
      throw FrameSourceError(FrameSourceErrc::kIo, uri_.uri,
                             "cannot retrieve a frame from " + device_);
    }
    if (frame.image.type() != CV_8UC3) {
      throw FrameSourceError(FrameSourceErrc::kUnsupported, uri_.uri,
                             device_ + " delivered a frame of OpenCV type " +
                                 std::to_string(frame.image.type()) + ", expected 8-bit BGR");
    }
    // CAP_PROP_POS_MSEC is the V4L2 buffer timestamp (CLOCK_MONOTONIC) in milliseconds.
    const double driver_ms = captures_.front().get(cv::CAP_PROP_POS_MSEC);
    frame.timestamp = received;
    if (std::isfinite(driver_ms) && driver_ms > 0.0) {
      const Clock::time_point driver{std::chrono::duration_cast<Clock::duration>(
          std::chrono::duration<double, std::milli>(driver_ms))};
      if (driver <= received && received - driver < std::chrono::seconds(10)) {
        frame.timestamp = driver;
      }
    }
    frame.exposure =
        std::chrono::microseconds(static_cast<std::int64_t>(std::llround(controls_.exposure_us)));
    frame.sequence = sequence_++;
    return frame;
  }

  std::string Describe() const override {
    std::ostringstream out;
    out << "v4l2 " << device_ << ": " << width_ << "x" << height_ << " " << active_fourcc_;
    if (controls_.lock) {
      out << ", exposure " << controls_.exposure_us << " us, gain " << controls_.analogue_gain
          << ", auto exposure/white balance off";
    } else {
      out << ", automatic exposure";
    }
    return out.str();
  }

  bool IsLive() const override { return true; }

 private:
  void ThrowIfGone() const {
    struct stat st {};
    if (::stat(device_.c_str(), &st) != 0) {
      throw FrameSourceError(FrameSourceErrc::kDisconnected, uri_.uri,
                             "device " + device_ + " disappeared (unplugged?)");
    }
  }

  bool Set(int property, double value) { return captures_.front().set(property, value); }

  void OpenDevice() {
    struct stat st {};
    if (::stat(device_.c_str(), &st) != 0) {
      throw FrameSourceError(FrameSourceErrc::kNoDevice, uri_.uri,
                             "no such V4L2 device " + device_ + " (" + std::strerror(errno) + ")");
    }
    if (!S_ISCHR(st.st_mode)) {
      throw FrameSourceError(FrameSourceErrc::kNoDevice, uri_.uri,
                             device_ + " is not a character device (expected /dev/videoN)");
    }
    cv::VideoCapture capture;
    bool opened = false;
    try {
      opened = capture.open(device_, cv::CAP_V4L2);
    } catch (const cv::Exception& e) {
      throw FrameSourceError(FrameSourceErrc::kIo, uri_.uri,
                             "cannot open " + device_ + " as a V4L2 camera: " + e.what());
    }
    if (!opened || !capture.isOpened()) {
      throw FrameSourceError(FrameSourceErrc::kIo, uri_.uri,
                             "cannot open " + device_ +
                                 " as a V4L2 capture device (not a camera, busy, or no "
                                 "permission: is the user in group 'video'?)");
    }
    captures_.assign(1, capture);

    if (fourcc_) {
      const int code =
          cv::VideoWriter::fourcc((*fourcc_)[0], (*fourcc_)[1], (*fourcc_)[2], (*fourcc_)[3]);
      if (!Set(cv::CAP_PROP_FOURCC, code)) Fail("pixel format " + *fourcc_);
    }
    Set(cv::CAP_PROP_FRAME_WIDTH, controls_.width);
    Set(cv::CAP_PROP_FRAME_HEIGHT, controls_.height);
    if (fps_ && !Set(cv::CAP_PROP_FPS, *fps_)) Warn("frame rate " + *uri_.Option("fps"));
    if (buffers_ > 0 && !Set(cv::CAP_PROP_BUFFERSIZE, buffers_)) {
      Warn("buffer count " + std::to_string(buffers_));
    }
    width_ = static_cast<int>(captures_.front().get(cv::CAP_PROP_FRAME_WIDTH));
    height_ = static_cast<int>(captures_.front().get(cv::CAP_PROP_FRAME_HEIGHT));
    active_fourcc_ = FourccString(captures_.front().get(cv::CAP_PROP_FOURCC));
    if (width_ != controls_.width || height_ != controls_.height) {
      const std::string message =
          device_ + " delivers " + std::to_string(width_) + "x" + std::to_string(height_) +
          ", requested " + std::to_string(controls_.width) + "x" + std::to_string(controls_.height);
      captures_.clear();
      throw FrameSourceError(FrameSourceErrc::kUnsupported, uri_.uri, message);
    }

    if (controls_.lock) {
      // Raw V4L2 values: V4L2_EXPOSURE_MANUAL = 1; exposure in 100 us units.
      if (!Set(cv::CAP_PROP_AUTO_EXPOSURE, 1)) Fail("manual exposure (V4L2_EXPOSURE_MANUAL)");
      const double exposure_100us = std::max(1.0, std::round(controls_.exposure_us / 100.0));
      if (!Set(cv::CAP_PROP_EXPOSURE, exposure_100us)) {
        Fail("exposure " + std::to_string(controls_.exposure_us) + " us");
      }
      if (!Set(cv::CAP_PROP_GAIN, controls_.analogue_gain)) {
        Warn("gain " + std::to_string(controls_.analogue_gain));
      }
      if (!Set(cv::CAP_PROP_AUTO_WB, 0)) Warn("auto white balance off");
      if (wb_temperature_ && !Set(cv::CAP_PROP_WB_TEMPERATURE, *wb_temperature_)) {
        Warn("white-balance temperature " + *uri_.Option("wb_temperature"));
      }
    } else {
      Set(cv::CAP_PROP_AUTO_EXPOSURE, 3);  // V4L2_EXPOSURE_APERTURE_PRIORITY
      Set(cv::CAP_PROP_AUTO_WB, 1);
    }
  }

  [[noreturn]] void Fail(const std::string& what) {
    captures_.clear();
    throw FrameSourceError(FrameSourceErrc::kUnsupported, uri_.uri, device_ + " refused " + what);
  }

  void Warn(const std::string& what) const {
    spdlog::warn("{}: {} refused {}", uri_.uri, device_, what);
  }

  FrameSourceUri uri_;
  std::string device_;
  CameraControls controls_;
  std::optional<std::string> fourcc_;
  std::optional<double> fps_;
  int buffers_ = 0;
  std::optional<double> wb_temperature_;
  // One element: cv::VideoCapture::waitAny takes a vector (copies share the device).
  std::vector<cv::VideoCapture> captures_;
  bool started_ = false;
  std::uint64_t sequence_ = 0;
  int width_ = 0;
  int height_ = 0;
  std::string active_fourcc_;
};

}  // namespace

std::unique_ptr<FrameSource> OpenV4l2FrameSource(const FrameSourceUri& uri,
                                                 const CameraControls& controls) {
  uri.RequireKnownOptions({"fourcc", "fps", "buffers", "wb_temperature"});
  if (uri.target.empty()) {
    throw FrameSourceError(FrameSourceErrc::kBadUri, uri.uri,
                           "empty device (expected 'v4l2:/dev/videoN' or 'v4l2:N')");
  }
  std::string device = uri.target;
  if (device.find_first_not_of("0123456789") == std::string::npos) device = "/dev/video" + device;
  return std::make_unique<V4l2FrameSource>(uri, std::move(device), controls);
}

}  // namespace gs360
