#include "capture/replay_source.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <system_error>
#include <thread>
#include <utility>

#include <opencv2/imgcodecs.hpp>

namespace gs360 {
namespace {

using Clock = std::chrono::steady_clock;

bool IsImageFile(const std::filesystem::path& path) {
  std::string ext = path.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  static const char* const kExtensions[] = {".png", ".jpg",  ".jpeg", ".bmp",
                                            ".tif", ".tiff", ".ppm",  ".pgm"};
  return std::find(std::begin(kExtensions), std::end(kExtensions), ext) != std::end(kExtensions);
}

std::string SizeString(const cv::Size& s) {
  return std::to_string(s.width) + "x" + std::to_string(s.height);
}

}  // namespace

void ReplayOptions::Check() const {
  if (fps && (!std::isfinite(*fps) || *fps <= 0.0 || *fps > 10000.0)) {
    std::ostringstream out;
    out << "ReplayOptions.fps must be in (0, 10000], got " << *fps;
    throw std::invalid_argument(out.str());
  }
}

ReplayFrameSource::ReplayFrameSource(const std::filesystem::path& folder,
                                     const ReplayOptions& options, std::string uri)
    : folder_(folder), options_(options), uri_(std::move(uri)) {
  options_.Check();
  if (uri_.empty()) uri_ = "replay:" + folder_.string();
  std::error_code ec;
  if (!std::filesystem::exists(folder_, ec)) {
    throw FrameSourceError(FrameSourceErrc::kNoDevice, uri_,
                           "replay folder '" + folder_.string() + "' does not exist");
  }
  if (!std::filesystem::is_directory(folder_, ec)) {
    throw FrameSourceError(FrameSourceErrc::kNoDevice, uri_,
                           "replay path '" + folder_.string() + "' is not a folder");
  }
  std::filesystem::directory_iterator it(folder_, ec);
  if (ec) {
    throw FrameSourceError(FrameSourceErrc::kIo, uri_,
                           "cannot list replay folder '" + folder_.string() + "': " + ec.message());
  }
  for (const auto& entry : it) {
    if (entry.is_regular_file(ec) && IsImageFile(entry.path())) files_.push_back(entry.path());
  }
  std::sort(files_.begin(), files_.end(),
            [](const auto& a, const auto& b) { return a.filename() < b.filename(); });
  if (files_.empty()) {
    throw FrameSourceError(FrameSourceErrc::kNoDevice, uri_,
                           "replay folder '" + folder_.string() +
                               "' holds no image (.png, .jpg, .jpeg, .bmp, .tif, .tiff, .ppm, "
                               ".pgm)");
  }
}

void ReplayFrameSource::Start() {
  if (started_) return;
  started_ = true;
  pace_start_ = Clock::now();
  // Timestamps stay strictly increasing across Stop() / Start().
  if (last_timestamp_ && pace_start_ <= *last_timestamp_) {
    pace_start_ = *last_timestamp_ + std::chrono::nanoseconds(1);
  }
  paced_count_ = 0;
}

void ReplayFrameSource::Stop() {
  started_ = false;
}

std::optional<Frame> ReplayFrameSource::Next(std::chrono::milliseconds timeout) {
  if (!started_) throw std::logic_error("ReplayFrameSource::Next() before Start() (" + uri_ + ")");
  if (position_ >= files_.size()) {
    if (!options_.loop) return std::nullopt;
    position_ = 0;
  }

  Clock::time_point stamp;
  if (options_.fps) {
    const auto offset = std::chrono::nanoseconds(
        std::llround(static_cast<double>(paced_count_) * 1e9 / *options_.fps));
    stamp = pace_start_ + offset;
    const Clock::time_point now = Clock::now();
    if (stamp > now + timeout) {
      std::this_thread::sleep_for(timeout);
      return std::nullopt;
    }
    if (stamp > now) std::this_thread::sleep_until(stamp);
  } else {
    stamp = Clock::now();
    if (last_timestamp_ && stamp <= *last_timestamp_) {
      stamp = *last_timestamp_ + std::chrono::nanoseconds(1);
    }
  }

  const std::filesystem::path& file = files_[position_];
  cv::Mat image;
  try {
    image = cv::imread(file.string(), cv::IMREAD_COLOR);
  } catch (const cv::Exception& e) {
    throw FrameSourceError(FrameSourceErrc::kBadImage, uri_,
                           "cannot decode image '" + file.string() + "': " + e.what());
  }
  if (image.empty()) {
    throw FrameSourceError(
        FrameSourceErrc::kBadImage, uri_,
        "cannot read image '" + file.string() + "' (missing, unreadable, corrupt or not an image)");
  }
  if (size_.empty()) {
    size_ = image.size();
  } else if (image.size() != size_) {
    throw FrameSourceError(FrameSourceErrc::kBadImage, uri_,
                           "image '" + file.string() + "' is " + SizeString(image.size()) +
                               " but earlier frames are " + SizeString(size_));
  }

  Frame frame;
  frame.image = std::move(image);
  frame.timestamp = stamp;
  frame.sequence = sequence_++;
  ++position_;
  ++paced_count_;
  last_timestamp_ = stamp;
  return frame;
}

std::string ReplayFrameSource::Describe() const {
  std::ostringstream out;
  out << "replay '" << folder_.string() << "': " << files_.size() << " images, next #" << position_;
  if (options_.fps) {
    out << ", paced at " << *options_.fps << " fps";
  } else {
    out << ", on demand";
  }
  if (options_.loop) out << ", looping";
  return out.str();
}

std::unique_ptr<FrameSource> OpenReplayFrameSource(const FrameSourceUri& uri,
                                                   const CameraControls&) {
  uri.RequireKnownOptions({"fps", "loop"});
  if (uri.target.empty()) {
    throw FrameSourceError(FrameSourceErrc::kBadUri, uri.uri,
                           "empty folder path (expected 'replay:/path/to/folder')");
  }
  ReplayOptions options;
  options.fps = uri.DoubleOption("fps");
  options.loop = uri.BoolOption("loop").value_or(false);
  try {
    options.Check();
  } catch (const std::invalid_argument& e) {
    throw FrameSourceError(FrameSourceErrc::kBadUri, uri.uri, e.what());
  }
  return std::make_unique<ReplayFrameSource>(uri.target, options, uri.uri);
}

}  // namespace gs360
