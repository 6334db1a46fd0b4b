#include "capture/capture_press.h"

#include <stdexcept>
#include <string>

#include <opencv2/imgproc.hpp>

namespace gs360 {
namespace {

using Clock = std::chrono::steady_clock;

std::string Describe(const cv::Mat& m) {
  return std::to_string(m.cols) + "x" + std::to_string(m.rows) + " type " +
         std::to_string(m.type());
}

}  // namespace

void PressCaptureOptions::Check() const {
  if (frames_to_average < 1 || frames_to_average > 1000) {
    throw std::invalid_argument("PressCaptureOptions.frames_to_average must be in [1, 1000], got " +
                                std::to_string(frames_to_average));
  }
  if (timeout.count() <= 0) {
    throw std::invalid_argument("PressCaptureOptions.timeout must be > 0 ms, got " +
                                std::to_string(timeout.count()));
  }
  if (max_stale_frames < 0) {
    throw std::invalid_argument("PressCaptureOptions.max_stale_frames must be >= 0, got " +
                                std::to_string(max_stale_frames));
  }
}

std::string_view ToString(PressCaptureStatus status) {
  switch (status) {
    case PressCaptureStatus::kOk:
      return "ok";
    case PressCaptureStatus::kTimeout:
      return "timeout";
    case PressCaptureStatus::kTooManyStale:
      return "too many stale frames";
  }
  return "unknown";
}

PressCaptureResult CapturePress(FrameSource& source, Clock::time_point sync_ok,
                                const PressCaptureOptions& options) {
  options.Check();
  const Clock::time_point deadline = Clock::now() + options.timeout;
  PressCaptureResult result;
  // Sums of 8-bit values in float are exact up to 2^24 / 255 > 65000 frames.
  cv::Mat sum;

  while (result.frames_used < options.frames_to_average) {
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
    if (left.count() <= 0) {
      result.status = PressCaptureStatus::kTimeout;
      return result;
    }
    std::optional<Frame> frame = source.Next(left);
    if (!frame) {
      result.status = PressCaptureStatus::kTimeout;
      return result;
    }
    if (frame->ExposureStart() <= sync_ok) {
      ++result.stale_dropped;
      if (result.stale_dropped > options.max_stale_frames) {
        result.status = PressCaptureStatus::kTooManyStale;
        return result;
      }
      continue;
    }
    if (frame->image.type() != CV_8UC3 || frame->image.empty()) {
      throw std::runtime_error("CapturePress: frame #" + std::to_string(frame->sequence) +
                               " from " + source.Describe() + " is " + Describe(frame->image) +
                               ", expected non-empty CV_8UC3");
    }
    if (result.frames_used == 0) {
      sum = cv::Mat::zeros(frame->image.size(), CV_32FC3);
      result.first_timestamp = frame->timestamp;
      result.first_sequence = frame->sequence;
    } else if (frame->image.size() != sum.size()) {
      throw std::runtime_error("CapturePress: frame #" + std::to_string(frame->sequence) +
                               " from " + source.Describe() + " is " + Describe(frame->image) +
                               " but the first fresh frame is " + std::to_string(sum.cols) + "x" +
                               std::to_string(sum.rows));
    }
    cv::accumulate(frame->image, sum);
    result.last_timestamp = frame->timestamp;
    result.last_sequence = frame->sequence;
    ++result.frames_used;
  }

  // convertTo rounds to nearest (ties to even) and saturates.
  sum.convertTo(result.image, CV_8U, 1.0 / options.frames_to_average);
  result.status = PressCaptureStatus::kOk;
  return result;
}

void ReferenceSchedule::Check() const {
  if (every_m_probes < 0) {
    throw std::invalid_argument("ReferenceSchedule.every_m_probes must be >= 0, got " +
                                std::to_string(every_m_probes));
  }
}

bool ReferenceSchedule::NeedsReference(std::int64_t probes_done,
                                       std::optional<std::int64_t> last_reference_at) const {
  Check();
  if (probes_done < 0) {
    throw std::invalid_argument(
        "ReferenceSchedule::NeedsReference: probes_done must be >= 0, got " +
        std::to_string(probes_done));
  }
  if (!last_reference_at) return true;
  if (*last_reference_at < 0 || *last_reference_at > probes_done) {
    throw std::invalid_argument(
        "ReferenceSchedule::NeedsReference: last_reference_at must be in [0, probes_done = " +
        std::to_string(probes_done) + "], got " + std::to_string(*last_reference_at));
  }
  return every_m_probes > 0 && probes_done - *last_reference_at >= every_m_probes;
}

}  // namespace gs360
