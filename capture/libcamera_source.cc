// libcamera backend, compiled only when libcamera is found (GS360_HAVE_LIBCAMERA). Written against
// libcamera 0.0.3 (Debian 12): Camera::generateConfiguration / configure / createRequest /
// queueRequest, FrameBufferAllocator, Signal<Request*> requestCompleted, ControlList::get
// returning std::optional.
#include "capture/libcamera_source.h"

#include <sys/mman.h>
#include <time.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <map>
#include <mutex>
#include <sstream>
#include <utility>
#include <vector>

#include <libcamera/libcamera.h>
#include <spdlog/spdlog.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace gs360 {
namespace {

namespace lc = libcamera;
using Clock = std::chrono::steady_clock;

// Completed frames held for the consumer; when one more completes, the oldest is recycled.
constexpr std::size_t kMaxPendingFrames = 2;

// libcamera permits one CameraManager per process: share it between sources.
std::shared_ptr<lc::CameraManager> AcquireCameraManager(const std::string& uri) {
  static std::mutex mutex;
  static std::weak_ptr<lc::CameraManager> shared;
  std::lock_guard lock(mutex);
  if (auto manager = shared.lock()) return manager;
  // ~CameraManager() stops it.
  auto manager = std::make_shared<lc::CameraManager>();
  const int ret = manager->start();
  if (ret != 0) {
    throw FrameSourceError(
        FrameSourceErrc::kIo, uri,
        "libcamera CameraManager failed to start: " + std::string(std::strerror(-ret)));
  }
  shared = manager;
  return manager;
}

std::int64_t ClockNs(clockid_t id) {
  timespec ts{};
  ::clock_gettime(id, &ts);
  return static_cast<std::int64_t>(ts.tv_sec) * 1000000000 + ts.tv_nsec;
}

// Maps a libcamera sensor timestamp (ns) onto steady_clock; see libcamera_source.h.
Clock::time_point MapSensorTimestamp(std::int64_t sensor_ns, Clock::time_point received) {
  constexpr std::int64_t kWindowNs = 10'000'000'000;
  const std::int64_t monotonic = ClockNs(CLOCK_MONOTONIC);
  if (sensor_ns > 0 && sensor_ns <= monotonic && monotonic - sensor_ns < kWindowNs) {
    return Clock::time_point(std::chrono::nanoseconds(sensor_ns));
  }
  const std::int64_t boottime = ClockNs(CLOCK_BOOTTIME);
  if (sensor_ns > 0 && sensor_ns <= boottime && boottime - sensor_ns < kWindowNs) {
    return Clock::time_point(std::chrono::nanoseconds(sensor_ns - (boottime - monotonic)));
  }
  return received;
}

const std::vector<lc::PixelFormat>& PreferredFormats() {
  static const std::vector<lc::PixelFormat> formats = {
      lc::formats::RGB888, lc::formats::BGR888, lc::formats::XRGB8888, lc::formats::XBGR8888,
      lc::formats::YUYV,   lc::formats::NV12,   lc::formats::YUV420,   lc::formats::MJPEG};
  return formats;
}

bool IsConvertible(const lc::PixelFormat& format) {
  const auto& formats = PreferredFormats();
  return std::find(formats.begin(), formats.end(), format) != formats.end();
}

struct MappedPlane {
  const std::uint8_t* data = nullptr;
  std::size_t length = 0;
};

class LibcameraFrameSource : public FrameSource {
 public:
  LibcameraFrameSource(const FrameSourceUri& uri, const CameraControls& controls)
      : uri_(uri.uri), controls_(controls) {
    std::optional<double> buffers = uri.DoubleOption("buffers");
    if (buffers && (*buffers < 2 || *buffers > 16 || std::floor(*buffers) != *buffers)) {
      throw FrameSourceError(
          FrameSourceErrc::kBadUri, uri_,
          "option 'buffers' must be an integer in [2, 16], got " + *uri.Option("buffers"));
    }
    try {
      Open(uri.target, buffers ? static_cast<unsigned>(*buffers) : 0u);
    } catch (...) {
      Close();
      throw;
    }
  }

  ~LibcameraFrameSource() override { Close(); }

  void Start() override {
    if (started_) return;
    ThrowIfDisconnected();
    const int ret = camera_->start(&controls_list_);
    if (ret != 0) {
      throw FrameSourceError(FrameSourceErrc::kIo, uri_,
                             "cannot start camera '" + camera_->id() + "': " + std::strerror(-ret));
    }
    {
      std::lock_guard lock(mutex_);
      started_ = true;
    }
    for (auto& request : requests_) {
      request->reuse(lc::Request::ReuseBuffers);
      Queue(request.get());
    }
  }

  void Stop() override {
    if (!started_) return;
    {
      std::lock_guard lock(mutex_);
      started_ = false;  // from now on the completion handler ignores and recycles nothing
    }
    // Completes every queued request as cancelled (the signal runs before stop() returns).
    camera_->stop();
    std::lock_guard lock(mutex_);
    completed_.clear();
  }

  std::optional<Frame> Next(std::chrono::milliseconds timeout) override {
    if (!started_) {
      throw std::logic_error("LibcameraFrameSource::Next() before Start() (" + uri_ + ")");
    }
    const Clock::time_point deadline = Clock::now() + timeout;
    while (true) {
      Completed completed;
      {
        std::unique_lock lock(mutex_);
        cv_.wait_until(lock, deadline, [&] { return !completed_.empty() || disconnected_; });
        if (disconnected_) {
          throw FrameSourceError(FrameSourceErrc::kDisconnected, uri_,
                                 "camera '" + camera_id_ + "' disconnected");
        }
        if (completed_.empty()) return std::nullopt;
        completed = completed_.front();
        completed_.pop_front();
      }
      lc::Request* request = completed.request;
      std::optional<Frame> frame;
      std::optional<FrameSourceError> error;
      try {
        frame = ToFrame(*request, completed.received);
      } catch (const FrameSourceError& e) {
        error = e;
      }
      request->reuse(lc::Request::ReuseBuffers);
      Queue(request);
      if (error) throw *error;
      if (frame) return frame;
      // A frame the driver flagged as corrupt: skipped (a sequence gap), keep waiting.
      ++dropped_;
    }
  }

  std::string Describe() const override {
    std::ostringstream out;
    out << "libcamera '" << camera_id_ << "': " << size_.width << "x" << size_.height << " "
        << pixel_format_.toString() << ", " << buffer_count_ << " buffers";
    if (controls_.lock) {
      out << ", exposure " << controls_.exposure_us << " us, gain " << controls_.analogue_gain
          << ", colour gains " << controls_.colour_gains[0] << "/" << controls_.colour_gains[1]
          << ", locked";
    } else {
      out << ", automatic exposure and white balance";
    }
    const std::uint64_t dropped = dropped_;
    if (dropped > 0) out << ", " << dropped << " frames dropped (unread or erroneous)";
    return out.str();
  }

  bool IsLive() const override { return true; }

 private:
  struct Completed {
    lc::Request* request = nullptr;
    Clock::time_point received{};
  };

  void Open(const std::string& target, unsigned buffers) {
    if (target.empty()) {
      throw FrameSourceError(FrameSourceErrc::kBadUri, uri_,
                             "empty camera (expected 'libcamera:<index>' or 'libcamera:<id>')");
    }
    manager_ = AcquireCameraManager(uri_);
    const std::vector<std::shared_ptr<lc::Camera>> cameras = manager_->cameras();
    std::string ids;
    for (const auto& c : cameras) ids += (ids.empty() ? "'" : ", '") + c->id() + "'";
    if (cameras.empty()) {
      throw FrameSourceError(FrameSourceErrc::kNoDevice, uri_,
                             "no camera found: libcamera " + lc::CameraManager::version() +
                                 " lists 0 cameras (is the camera connected and enabled?)");
    }
    if (target.find_first_not_of("0123456789") == std::string::npos) {
      const std::size_t index = target.size() > 6 ? cameras.size() : std::stoul(target);
      if (index >= cameras.size()) {
        throw FrameSourceError(FrameSourceErrc::kNoDevice, uri_,
                               "no camera with index " + target + ": libcamera lists " +
                                   std::to_string(cameras.size()) + " camera(s): " + ids);
      }
      camera_ = cameras[index];
    } else {
      camera_ = manager_->get(target);
      if (!camera_) {
        throw FrameSourceError(FrameSourceErrc::kNoDevice, uri_,
                               "no camera with id '" + target + "'; libcamera lists: " + ids);
      }
    }
    camera_id_ = camera_->id();
    if (camera_->acquire() != 0) {
      camera_.reset();
      throw FrameSourceError(FrameSourceErrc::kDeviceBusy, uri_,
                             "camera '" + camera_id_ + "' is in use by another process");
    }
    acquired_ = true;
    camera_->disconnected.connect(this, &LibcameraFrameSource::OnDisconnected);

    Configure(buffers);
    AllocateAndMap();
    BuildControls();

    for (std::size_t i = 0; i < buffers_->size(); ++i) {
      std::unique_ptr<lc::Request> request = camera_->createRequest(i);
      if (!request) {
        throw FrameSourceError(FrameSourceErrc::kIo, uri_, "cannot create a libcamera request");
      }
      if (request->addBuffer(stream_, (*buffers_)[i].get()) != 0) {
        throw FrameSourceError(FrameSourceErrc::kIo, uri_,
                               "cannot attach a frame buffer to a libcamera request");
      }
      requests_.push_back(std::move(request));
    }
    camera_->requestCompleted.connect(this, &LibcameraFrameSource::OnRequestCompleted);
    connected_ = true;
  }

  void Configure(unsigned buffers) {
    config_ = camera_->generateConfiguration({lc::StreamRole::Viewfinder});
    if (!config_ || config_->size() != 1) {
      throw FrameSourceError(FrameSourceErrc::kUnsupported, uri_,
                             "camera '" + camera_id_ + "' offers no viewfinder stream");
    }
    lc::StreamConfiguration& cfg = config_->at(0);
    const std::vector<lc::PixelFormat> offered = cfg.formats().pixelformats();
    std::optional<lc::PixelFormat> chosen;
    for (const lc::PixelFormat& f : PreferredFormats()) {
      if (std::find(offered.begin(), offered.end(), f) != offered.end()) {
        chosen = f;
        break;
      }
    }
    if (!chosen) {
      std::string list;
      for (const auto& f : offered) list += (list.empty() ? "" : ", ") + f.toString();
      throw FrameSourceError(
          FrameSourceErrc::kUnsupported, uri_,
          "camera '" + camera_id_ + "' offers no pixel format gs360 converts (" + list + ")");
    }
    cfg.pixelFormat = *chosen;
    cfg.size =
        lc::Size(static_cast<unsigned>(controls_.width), static_cast<unsigned>(controls_.height));
    if (buffers > 0) cfg.bufferCount = buffers;
    const lc::CameraConfiguration::Status status = config_->validate();
    if (status == lc::CameraConfiguration::Invalid) {
      throw FrameSourceError(
          FrameSourceErrc::kUnsupported, uri_,
          "camera '" + camera_id_ + "' rejects the configuration " + cfg.toString());
    }
    if (cfg.size.width != static_cast<unsigned>(controls_.width) ||
        cfg.size.height != static_cast<unsigned>(controls_.height)) {
      throw FrameSourceError(
          FrameSourceErrc::kUnsupported, uri_,
          "camera '" + camera_id_ + "' cannot deliver " + std::to_string(controls_.width) + "x" +
              std::to_string(controls_.height) + " (nearest: " + cfg.size.toString() + ")");
    }
    if (!IsConvertible(cfg.pixelFormat)) {
      throw FrameSourceError(FrameSourceErrc::kUnsupported, uri_,
                             "camera '" + camera_id_ + "' adjusted the pixel format to " +
                                 cfg.pixelFormat.toString() + ", which gs360 does not convert");
    }
    const int ret = camera_->configure(config_.get());
    if (ret != 0) {
      throw FrameSourceError(FrameSourceErrc::kIo, uri_,
                             "cannot configure camera '" + camera_id_ + "' as " + cfg.toString() +
                                 ": " + std::strerror(-ret));
    }
    stream_ = cfg.stream();
    size_ = cfg.size;
    stride_ = cfg.stride;
    pixel_format_ = cfg.pixelFormat;
  }

  void AllocateAndMap() {
    allocator_ = std::make_unique<lc::FrameBufferAllocator>(camera_);
    const int count = allocator_->allocate(stream_);
    if (count <= 0) {
      throw FrameSourceError(FrameSourceErrc::kIo, uri_,
                             "cannot allocate frame buffers for camera '" + camera_id_ + "'");
    }
    buffers_ = &allocator_->buffers(stream_);
    buffer_count_ = buffers_->size();
    for (const auto& buffer : *buffers_) {
      // Planes of one buffer often share a dmabuf at different offsets: map each fd once.
      std::map<int, std::size_t> extent;
      for (const lc::FrameBuffer::Plane& plane : buffer->planes()) {
        if (plane.offset == lc::FrameBuffer::Plane::kInvalidOffset) {
          throw FrameSourceError(FrameSourceErrc::kIo, uri_, "frame buffer plane without offset");
        }
        std::size_t& e = extent[plane.fd.get()];
        e = std::max<std::size_t>(e, std::size_t{plane.offset} + plane.length);
      }
      std::map<int, const std::uint8_t*> base;
      for (const auto& [fd, length] : extent) {
        void* address = ::mmap(nullptr, length, PROT_READ, MAP_SHARED, fd, 0);
        if (address == MAP_FAILED) {
          throw FrameSourceError(
              FrameSourceErrc::kIo, uri_,
              std::string("cannot mmap a frame buffer: ") + std::strerror(errno));
        }
        mappings_.emplace_back(address, length);
        base[fd] = static_cast<const std::uint8_t*>(address);
      }
      std::vector<MappedPlane>& planes = mapped_[buffer.get()];
      for (const lc::FrameBuffer::Plane& plane : buffer->planes()) {
        planes.push_back({base[plane.fd.get()] + plane.offset, plane.length});
      }
    }
  }

  void BuildControls() {
    const lc::ControlInfoMap& info = camera_->controls();
    controls_list_ = lc::ControlList(info);
    std::vector<std::string> skipped;
    auto supported = [&](const lc::ControlId& id) {
      if (info.find(&id) != info.end()) return true;
      skipped.push_back(id.name());
      return false;
    };
    if (supported(lc::controls::AeEnable))
      controls_list_.set(lc::controls::AeEnable, !controls_.lock);
    if (supported(lc::controls::AwbEnable)) {
      controls_list_.set(lc::controls::AwbEnable, !controls_.lock);
    }
    if (controls_.lock) {
      if (supported(lc::controls::ExposureTime)) {
        controls_list_.set(lc::controls::ExposureTime,
                           static_cast<std::int32_t>(std::llround(controls_.exposure_us)));
      }
      if (supported(lc::controls::AnalogueGain)) {
        controls_list_.set(lc::controls::AnalogueGain, static_cast<float>(controls_.analogue_gain));
      }
      if (supported(lc::controls::ColourGains)) {
        controls_list_.set(lc::controls::ColourGains,
                           {static_cast<float>(controls_.colour_gains[0]),
                            static_cast<float>(controls_.colour_gains[1])});
      }
    }
    if (!skipped.empty()) {
      std::string list;
      for (const auto& s : skipped) list += (list.empty() ? "" : ", ") + s;
      spdlog::warn("{}: camera '{}' does not support the control(s) {}; not applied", uri_,
                   camera_id_, list);
    }
  }

  void Queue(lc::Request* request) {
    // Request::reuse() clears the controls: apply them again (ControlList::merge would assert
    // that both lists share one id map).
    for (const auto& [id, value] : controls_list_) request->controls().set(id, value);
    const int ret = camera_->queueRequest(request);
    if (ret != 0 && started_) {
      spdlog::error("{}: cannot queue a request on camera '{}': {}", uri_, camera_id_,
                    std::strerror(-ret));
    }
  }

  // Runs in libcamera's internal thread.
  void OnRequestCompleted(lc::Request* request) {
    if (request->status() == lc::Request::RequestCancelled) return;
    lc::Request* recycle = nullptr;
    {
      std::lock_guard lock(mutex_);
      if (!started_) return;
      completed_.push_back({request, Clock::now()});
      if (completed_.size() > kMaxPendingFrames) {
        recycle = completed_.front().request;
        completed_.pop_front();
        ++dropped_;
      }
    }
    cv_.notify_one();
    if (recycle) {
      recycle->reuse(lc::Request::ReuseBuffers);
      Queue(recycle);
    }
  }

  void OnDisconnected() {
    {
      std::lock_guard lock(mutex_);
      disconnected_ = true;
    }
    cv_.notify_all();
  }

  void ThrowIfDisconnected() {
    std::lock_guard lock(mutex_);
    if (disconnected_) {
      throw FrameSourceError(FrameSourceErrc::kDisconnected, uri_,
                             "camera '" + camera_id_ + "' disconnected");
    }
  }

  // nullopt for a frame the driver flagged as erroneous.
  std::optional<Frame> ToFrame(lc::Request& request, Clock::time_point received) const {
    const lc::FrameBuffer* buffer = request.findBuffer(stream_);
    if (!buffer) throw FrameSourceError(FrameSourceErrc::kIo, uri_, "request without buffer");
    if (buffer->metadata().status != lc::FrameMetadata::FrameSuccess) {
      spdlog::warn("{}: camera '{}' flagged frame {} as erroneous; skipped", uri_, camera_id_,
                   buffer->metadata().sequence);
      return std::nullopt;
    }
    const std::vector<MappedPlane>& planes = mapped_.at(buffer);
    Frame frame;
    frame.image = ConvertToBgr(planes, buffer->metadata());
    const lc::ControlList& metadata = request.metadata();
    const std::int64_t sensor_ns =
        metadata.get(lc::controls::SensorTimestamp)
            .value_or(static_cast<std::int64_t>(buffer->metadata().timestamp));
    const std::int32_t exposure_us =
        metadata.get(lc::controls::ExposureTime)
            .value_or(static_cast<std::int32_t>(std::llround(controls_.exposure_us)));
    frame.exposure = std::chrono::microseconds(exposure_us);
    frame.timestamp = MapSensorTimestamp(sensor_ns, received);
    if (frame.timestamp != received) frame.timestamp += frame.exposure;
    frame.sequence = buffer->metadata().sequence;
    return frame;
  }

  cv::Mat ConvertToBgr(const std::vector<MappedPlane>& planes,
                       const lc::FrameMetadata& metadata) const {
    const int w = static_cast<int>(size_.width);
    const int h = static_cast<int>(size_.height);
    const std::size_t stride = stride_;
    auto need = [&](std::size_t plane, std::size_t bytes) {
      if (plane >= planes.size() || planes[plane].length < bytes) {
        throw FrameSourceError(FrameSourceErrc::kIo, uri_,
                               "frame buffer plane " + std::to_string(plane) + " is smaller than " +
                                   pixel_format_.toString() + " " + std::to_string(w) + "x" +
                                   std::to_string(h) + " needs");
      }
      return const_cast<std::uint8_t*>(planes[plane].data);
    };
    cv::Mat out;
    if (pixel_format_ == lc::formats::RGB888 || pixel_format_ == lc::formats::BGR888) {
      // DRM naming: RGB888 is stored B, G, R in memory, i.e. OpenCV's BGR.
      cv::Mat view(h, w, CV_8UC3, need(0, stride * static_cast<std::size_t>(h)), stride);
      if (pixel_format_ == lc::formats::RGB888) {
        out = view.clone();
      } else {
        cv::cvtColor(view, out, cv::COLOR_RGB2BGR);
      }
    } else if (pixel_format_ == lc::formats::XRGB8888 || pixel_format_ == lc::formats::XBGR8888) {
      cv::Mat view(h, w, CV_8UC4, need(0, stride * static_cast<std::size_t>(h)), stride);
      cv::cvtColor(
          view, out,
          pixel_format_ == lc::formats::XRGB8888 ? cv::COLOR_BGRA2BGR : cv::COLOR_RGBA2BGR);
    } else if (pixel_format_ == lc::formats::YUYV) {
      cv::Mat view(h, w, CV_8UC2, need(0, stride * static_cast<std::size_t>(h)), stride);
      cv::cvtColor(view, out, cv::COLOR_YUV2BGR_YUYV);
    } else if (pixel_format_ == lc::formats::NV12 || pixel_format_ == lc::formats::YUV420) {
      const bool nv12 = pixel_format_ == lc::formats::NV12;
      const std::size_t luma = stride * static_cast<std::size_t>(h);
      const std::size_t chroma_stride = nv12 ? stride : stride / 2;
      const std::size_t chroma_rows = static_cast<std::size_t>(h / 2);
      const std::size_t chroma = chroma_stride * chroma_rows;
      const std::size_t chroma_planes = nv12 ? 1 : 2;
      const std::uint8_t* y = nullptr;
      const std::uint8_t* u = nullptr;
      const std::uint8_t* v = nullptr;
      if (planes.size() == 1) {  // one plane: Y, then U (or UV), then V
        y = need(0, luma + chroma_planes * chroma);
        u = y + luma;
      } else if (planes.size() == 2 || nv12) {  // Y | U (or UV), then V
        y = need(0, luma);
        u = need(1, chroma_planes * chroma);
      } else {  // Y | U | V
        y = need(0, luma);
        u = need(1, chroma);
        v = need(2, chroma);
      }
      if (!nv12 && !v) v = u + chroma;
      // Repack into OpenCV's contiguous (h * 3/2) x w layout.
      cv::Mat packed(h * 3 / 2, w, CV_8UC1);
      std::uint8_t* dst = packed.data;
      for (int r = 0; r < h; ++r, dst += w)
        std::memcpy(dst, y + r * stride, static_cast<std::size_t>(w));
      const std::size_t chroma_row_bytes =
          nv12 ? static_cast<std::size_t>(w) : static_cast<std::size_t>(w / 2);
      for (std::size_t r = 0; r < chroma_rows; ++r, dst += chroma_row_bytes) {
        std::memcpy(dst, u + r * chroma_stride, chroma_row_bytes);
      }
      if (!nv12) {
        for (std::size_t r = 0; r < chroma_rows; ++r, dst += chroma_row_bytes) {
          std::memcpy(dst, v + r * chroma_stride, chroma_row_bytes);
        }
      }
      cv::cvtColor(packed, out, nv12 ? cv::COLOR_YUV2BGR_NV12 : cv::COLOR_YUV2BGR_I420);
    } else if (pixel_format_ == lc::formats::MJPEG) {
      const std::size_t bytes =
          metadata.planes().size() > 0 ? metadata.planes()[0].bytesused : planes.at(0).length;
      cv::Mat encoded(1, static_cast<int>(bytes), CV_8UC1, need(0, bytes));
      out = cv::imdecode(encoded, cv::IMREAD_COLOR);
      if (out.empty()) {
        throw FrameSourceError(
            FrameSourceErrc::kIo, uri_,
            "camera '" + camera_id_ + "' sent a JPEG frame that does not decode");
      }
    }
    if (out.size() != cv::Size(w, h)) {
      throw FrameSourceError(FrameSourceErrc::kIo, uri_,
                             "camera '" + camera_id_ + "' sent a frame of unexpected size");
    }
    return out;
  }

  void Close() {
    if (camera_ && started_) Stop();
    if (camera_ && connected_) camera_->requestCompleted.disconnect(this);
    if (camera_ && acquired_) camera_->disconnected.disconnect(this);
    connected_ = false;
    requests_.clear();
    for (auto& [address, length] : mappings_) ::munmap(address, length);
    mappings_.clear();
    mapped_.clear();
    if (allocator_ && stream_) allocator_->free(stream_);
    allocator_.reset();
    buffers_ = nullptr;
    if (camera_ && acquired_) camera_->release();
    acquired_ = false;
    config_.reset();
    camera_.reset();
    manager_.reset();
  }

  std::string uri_;
  CameraControls controls_;
  std::shared_ptr<lc::CameraManager> manager_;
  std::shared_ptr<lc::Camera> camera_;
  std::string camera_id_;
  bool acquired_ = false;
  bool connected_ = false;
  std::unique_ptr<lc::CameraConfiguration> config_;
  lc::Stream* stream_ = nullptr;
  lc::Size size_;
  unsigned stride_ = 0;
  lc::PixelFormat pixel_format_;
  std::unique_ptr<lc::FrameBufferAllocator> allocator_;
  const std::vector<std::unique_ptr<lc::FrameBuffer>>* buffers_ = nullptr;
  std::size_t buffer_count_ = 0;
  std::vector<std::pair<void*, std::size_t>> mappings_;
  std::map<const lc::FrameBuffer*, std::vector<MappedPlane>> mapped_;
  lc::ControlList controls_list_;
  std::vector<std::unique_ptr<lc::Request>> requests_;

  std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<Completed> completed_;         // guarded by mutex_
  std::atomic<bool> started_ = false;       // written by the consumer under mutex_ (Start / Stop)
  bool disconnected_ = false;               // guarded by mutex_
  std::atomic<std::uint64_t> dropped_ = 0;  // frames recycled or skipped unread
};

}  // namespace

std::unique_ptr<FrameSource> OpenLibcameraFrameSource(const FrameSourceUri& uri,
                                                      const CameraControls& controls) {
  uri.RequireKnownOptions({"buffers"});
  return std::make_unique<LibcameraFrameSource>(uri, controls);
}

}  // namespace gs360
