#pragma once
// Frame sources: one interface over the camera backends gs360 can read frames from.
//
//   libcamera:<index>|<id>   libcamera camera (CSI sensors, UVC through libcamera); compiled only
//                            when libcamera is found (see HaveLibcameraSupport()).
//   v4l2:/dev/videoN | v4l2:N   a UVC / V4L2 camera through OpenCV's V4L2 backend.
//   replay:/path/to/folder   images of a folder in file-name order (tests, re-runs on recorded
//   data). <scheme>:...             any scheme registered with RegisterFrameSourceFactory (the
//   virtual
//                            rig registers "sim:" from sim/, which may depend on capture/).
//
// A URI may carry backend options after '?', as key=value pairs separated by '&', e.g.
// "replay:/data/run1?fps=30&loop=1". Every backend rejects option keys it does not know.
//
// Timestamps are std::chrono::steady_clock time points (CLOCK_MONOTONIC on Linux), the clock the
// G-code streamer uses for the `ok` of the sync dwell, so that CapturePress can discard frames
// exposed before the machine stopped. Errors opening or running a source throw FrameSourceError
// naming the URI (and the file or device); expected outcomes (no frame within a timeout) are
// status values. No libcamera or V4L2 header is included here.
//
// Thread safety: a FrameSource has one consumer; call its methods from one thread at a time. The
// registry functions are thread-safe.

#include <array>
#include <chrono>
#include <cstdint>
#include <functional>
#include <initializer_list>
#include <map>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

#include <opencv2/core.hpp>

namespace gs360 {

// One camera frame.
struct Frame {
  // 8-bit, 3-channel BGR (CV_8UC3), owned by the Frame (never a view into a driver buffer).
  cv::Mat image;
  // steady_clock time at which the exposure ended (for rolling-shutter sensors: the end of the
  // first row's exposure), either measured by the driver and mapped onto steady_clock or, where
  // the backend has no driver timestamp, the host time the frame was received (later than the
  // true exposure end, never earlier).
  std::chrono::steady_clock::time_point timestamp{};
  // Exposure duration if known (0 if unknown, e.g. replayed files). The exposure started at
  // ExposureStart() = timestamp - exposure.
  std::chrono::microseconds exposure{0};
  // Frame counter of the source, increasing; a gap means the source dropped frames.
  std::uint64_t sequence = 0;

  std::chrono::steady_clock::time_point ExposureStart() const { return timestamp - exposure; }
};

// Photometric settings of a live camera. Calibration needs them locked: with auto exposure or
// auto white balance the colour-to-slope mapping drifts from frame to frame.
struct CameraControls {
  // Exposure time in microseconds, > 0 and <= 10 s.
  double exposure_us = 10000.0;
  // Sensor analogue gain. libcamera: a multiplier (1.0 = unity). v4l2: written as the device's raw
  // V4L2 gain control value (UVC cameras use device-specific units, often 0..255). >= 0.
  double analogue_gain = 1.0;
  // White-balance gains {red, blue} relative to green, > 0. libcamera only (OpenCV's V4L2 backend
  // has no per-channel gains; with lock the camera keeps its current white balance).
  std::array<double, 2> colour_gains{1.0, 1.0};
  // true: auto exposure, auto gain and auto white balance off, the values above applied.
  // false: the camera's automatic algorithms run (previews only, never for calibration).
  bool lock = true;
  // Requested frame size in pixels; a live source that cannot deliver exactly this size throws.
  int width = 640;
  int height = 480;

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

enum class FrameSourceErrc {
  kBadUri,         // malformed URI or option value
  kUnknownScheme,  // no factory registered for the URI's scheme
  kNotCompiled,    // the backend exists but gs360 was compiled without it
  kNoDevice,       // the camera / device / folder does not exist
  kDeviceBusy,     // the camera exists but cannot be acquired
  kUnsupported,    // the camera cannot deliver the requested size / format / controls
  kBadImage,       // a file could not be decoded, or frames differ in size
  kDisconnected,   // a running camera vanished
  kIo,             // any other backend failure
};

std::string_view ToString(FrameSourceErrc code);

class FrameSourceError : public std::runtime_error {
 public:
  // what() is "<uri>: <detail>".
  FrameSourceError(FrameSourceErrc code, const std::string& uri, const std::string& detail);

  FrameSourceErrc code() const noexcept { return code_; }
  const std::string& uri() const noexcept { return uri_; }

 private:
  FrameSourceErrc code_;
  std::string uri_;
};

class FrameSource {
 public:
  virtual ~FrameSource();

  // Begins frame delivery (a live camera starts streaming). Calling Start() on a started source
  // does nothing. Throws FrameSourceError if the device fails to start.
  virtual void Start() = 0;
  // Ends frame delivery; frames not yet consumed are discarded. Idempotent; the source can be
  // started again.
  virtual void Stop() = 0;
  // The next frame in delivery order, waiting at most `timeout`; std::nullopt if none arrived in
  // time (or, for a finite source such as a replay without loop, at its end). Throws
  // std::logic_error if the source is not started, FrameSourceError on device or file errors.
  virtual std::optional<Frame> Next(std::chrono::milliseconds timeout) = 0;
  // One line for logs and status: backend, device, size, settings.
  virtual std::string Describe() const = 0;
  // true for cameras (frames are produced in real time whether consumed or not), false for
  // sources that produce frames on demand (replay).
  virtual bool IsLive() const = 0;
};

// A parsed "scheme:target?key=value&key=value" URI. The scheme is lower-case letters, digits,
// '+', '-', '.', starting with a letter. The target is everything between ':' and the first '?'.
struct FrameSourceUri {
  std::string uri;  // as given
  std::string scheme;
  std::string target;
  std::map<std::string, std::string> options;

  // The option's value, if present.
  std::optional<std::string> Option(const std::string& key) const;
  // Numeric / boolean options ("1", "0", "true", "false"); throw FrameSourceError(kBadUri)
  // naming the option if the value does not parse.
  std::optional<double> DoubleOption(const std::string& key) const;
  std::optional<bool> BoolOption(const std::string& key) const;
  // Throws FrameSourceError(kBadUri) naming the first option whose key is not in `allowed`.
  void RequireKnownOptions(std::initializer_list<std::string_view> allowed) const;
};

// Throws FrameSourceError(kBadUri) for a URI without a valid "scheme:" prefix, an option without
// '=', an empty or repeated option key.
FrameSourceUri ParseFrameSourceUri(const std::string& uri);

// Creates a source for a parsed URI. It should throw FrameSourceError naming uri.uri when the
// device / folder does not exist, and may return a source that is not yet started.
using FrameSourceFactory =
    std::function<std::unique_ptr<FrameSource>(const FrameSourceUri&, const CameraControls&)>;

// Registers the factory for `scheme` (e.g. "sim"), replacing any previous one (the built-in
// schemes too). Returns true if a factory was replaced. Throws std::invalid_argument for an
// invalid scheme name or an empty factory.
bool RegisterFrameSourceFactory(const std::string& scheme, FrameSourceFactory factory);
// Removes a scheme; returns false if it was not registered.
bool UnregisterFrameSourceFactory(const std::string& scheme);
// Registered schemes, sorted (built-ins: "libcamera", "replay", "socket", "v4l2").
std::vector<std::string> FrameSourceSchemes();

// Opens the source named by `uri` with `controls` (checked first: std::invalid_argument if
// invalid). Throws FrameSourceError naming the URI: kBadUri, kUnknownScheme (the message lists the
// known schemes), kNotCompiled ("gs360 was compiled without libcamera support"), kNoDevice, ...
// The returned source is not started.
std::unique_ptr<FrameSource> OpenFrameSource(const std::string& uri,
                                             const CameraControls& controls);

// Which optional backends this build contains.
bool HaveLibcameraSupport();
bool HaveV4l2Support();

}  // namespace gs360
