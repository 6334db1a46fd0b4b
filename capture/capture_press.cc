#include "capture/capture_press.h"

#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include <opencv2/imgproc.hpp>

namespace gs360 {
namespace {

using Clock = std::chrono::steady_clock;

std::string Describe(const cv::Mat& m) {
  return std::to_string(m.cols) + "x" + std::to_string(m.rows) + " type " +
         std::to_string(m.type());
}

bool Disagree(const cv::Mat& a, const cv::Mat& b, const PressCaptureOptions& options) {
  cv::Mat diff;
  cv::absdiff(a, b, diff);
  const cv::Mat values = diff.reshape(1);
  const int limit =
      static_cast<int>(options.outlier_fraction * static_cast<double>(values.total()));
  return cv::countNonZero(values > options.outlier_dn) > limit;
}

// Indices (ascending) of the frames that agree with the one most others agree with; ties go to
// the earlier frame. With one frame or no outlier check, all of them.
std::vector<std::size_t> AgreeingFrames(const std::vector<Frame>& frames,
                                        const PressCaptureOptions& options) {
  const std::size_t n = frames.size();
  std::vector<std::size_t> all(n);
  for (std::size_t i = 0; i < n; ++i) all[i] = i;
  if (!options.reject_outliers || n < 2) return all;
  // The usual case, every frame agreeing with the first: n - 1 comparisons, not n (n - 1) / 2.
  bool all_agree = true;
  for (std::size_t i = 1; i < n && all_agree; ++i) {
    all_agree = !Disagree(frames[0].image, frames[i].image, options);
  }
  if (all_agree) return all;
  std::vector<std::vector<bool>> agree(n, std::vector<bool>(n, true));
  std::vector<int> partners(n, 0);
  for (std::size_t i = 0; i < n; ++i) {
    for (std::size_t j = i + 1; j < n; ++j) {
      agree[i][j] = agree[j][i] = !Disagree(frames[i].image, frames[j].image, options);
      if (agree[i][j]) ++partners[i], ++partners[j];
    }
  }
  std::size_t anchor = 0;
  for (std::size_t i = 1; i < n; ++i) {
    if (partners[i] > partners[anchor]) anchor = i;
  }
  std::vector<std::size_t> kept;
  for (std::size_t i = 0; i < n; ++i) {
    if (agree[anchor][i]) kept.push_back(i);
  }
  return kept;
}

// Reads the next fresh frame into `fresh`; a status when there is none to be had.
std::optional<PressCaptureStatus> ReadFresh(FrameSource& source, Clock::time_point sync_ok,
                                            Clock::time_point deadline,
                                            const PressCaptureOptions& options,
                                            PressCaptureResult* result, std::vector<Frame>* fresh) {
  for (;;) {
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
    if (left.count() <= 0) return PressCaptureStatus::kTimeout;
    std::optional<Frame> frame = source.Next(left);
    if (!frame) return PressCaptureStatus::kTimeout;
    if (frame->ExposureStart() <= sync_ok) {
      if (++result->stale_dropped > options.max_stale_frames) {
        return PressCaptureStatus::kTooManyStale;
      }
      continue;
    }
    if (frame->image.type() != CV_8UC3 || frame->image.empty()) {
      throw std::runtime_error("CapturePress: frame #" + std::to_string(frame->sequence) +
                               " from " + source.Describe() + " is " + Describe(frame->image) +
                               ", expected non-empty CV_8UC3");
    }
    if (!fresh->empty() && frame->image.size() != fresh->front().image.size()) {
      throw std::runtime_error("CapturePress: frame #" + std::to_string(frame->sequence) +
                               " from " + source.Describe() + " is " + Describe(frame->image) +
                               " but the first fresh frame is " +
                               std::to_string(fresh->front().image.cols) + "x" +
                               std::to_string(fresh->front().image.rows));
    }
    if (fresh->empty()) {
      result->first_timestamp = frame->timestamp;
      result->first_sequence = frame->sequence;
    }
    result->last_timestamp = frame->timestamp;
    result->last_sequence = frame->sequence;
    fresh->push_back(std::move(*frame));
    return std::nullopt;
  }
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
  if (outlier_dn < 1 || outlier_dn > 255) {
    throw std::invalid_argument("PressCaptureOptions.outlier_dn must be in [1, 255], got " +
                                std::to_string(outlier_dn));
  }
  if (!(outlier_fraction > 0.0 && outlier_fraction <= 1.0)) {
    throw std::invalid_argument("PressCaptureOptions.outlier_fraction must be in (0, 1], got " +
                                std::to_string(outlier_fraction));
  }
  if (reject_outliers && frames_to_average > kMaxFramesCompared) {
    throw std::invalid_argument(
        "PressCaptureOptions.frames_to_average must be <= " + std::to_string(kMaxFramesCompared) +
        " with reject_outliers (every frame is kept to compare), got " +
        std::to_string(frames_to_average));
  }
  if (max_outlier_frames < 0) {
    throw std::invalid_argument("PressCaptureOptions.max_outlier_frames must be >= 0, got " +
                                std::to_string(max_outlier_frames));
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
    case PressCaptureStatus::kInconsistent:
      return "frames disagree";
  }
  return "unknown";
}

PressCaptureResult CapturePress(FrameSource& source, Clock::time_point sync_ok,
                                const PressCaptureOptions& options) {
  options.Check();
  const Clock::time_point deadline = Clock::now() + options.timeout;
  const auto k = static_cast<std::size_t>(options.frames_to_average);
  const std::size_t most = k + static_cast<std::size_t>(options.max_outlier_frames);
  PressCaptureResult result;
  std::vector<Frame> fresh;
  std::vector<std::size_t> kept;
  while (kept.size() < k) {
    if (fresh.size() >= most) {
      result.status = PressCaptureStatus::kInconsistent;
      result.frames_used = static_cast<int>(fresh.size());
      return result;
    }
    if (auto failed = ReadFresh(source, sync_ok, deadline, options, &result, &fresh)) {
      result.status = *failed;
      result.frames_used = static_cast<int>(fresh.size());
      return result;
    }
    if (fresh.size() >= k) kept = AgreeingFrames(fresh, options);
  }
  kept.resize(k);  // the earliest K that agree
  // Sums of 8-bit values in float are exact up to 2^24 / 255 > 65000 frames.
  cv::Mat sum = cv::Mat::zeros(fresh.front().image.size(), CV_32FC3);
  for (std::size_t i : kept) cv::accumulate(fresh[i].image, sum);
  // convertTo rounds to nearest (ties to even) and saturates.
  sum.convertTo(result.image, CV_8U, 1.0 / options.frames_to_average);
  result.frames_used = options.frames_to_average;
  result.outliers_rejected = static_cast<int>(fresh.size() - kept.size());
  result.first_timestamp = fresh[kept.front()].timestamp;
  result.first_sequence = fresh[kept.front()].sequence;
  result.last_timestamp = fresh[kept.back()].timestamp;
  result.last_sequence = fresh[kept.back()].sequence;
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
