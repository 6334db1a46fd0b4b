#pragma once
// Capturing one press: K fresh frames after the machine's sync `ok`, averaged.
//
// The sync rule (docs/design.md, "Stream"): the `ok` of the press's `G4 P<settle>` arrives only
// after the ball has stopped, so a frame whose exposure began after that `ok` shows the settled
// press; anything exposed earlier may show the ball still moving. CapturePress therefore discards
// every frame with ExposureStart() <= sync_ok (for sources that do not know the exposure, that is
// timestamp <= sync_ok) and averages the next K frames to cut sensor noise by sqrt(K).
//
// Also: ReferenceSchedule, when to take a no-contact reference frame (at the start of a run and
// every M probes, because the LEDs drift with temperature).

#include <chrono>
#include <cstdint>
#include <optional>
#include <string_view>

#include <opencv2/core.hpp>

#include "capture/frame_source.h"

namespace gs360 {

inline constexpr int kMaxFramesCompared = 50;

struct PressCaptureOptions {
  // K: fresh frames averaged, in [1, 1000].
  int frames_to_average = 3;
  // Deadline for the whole capture (stale frames included), > 0.
  std::chrono::milliseconds timeout{2000};
  // More stale frames than this means the timestamps cannot be trusted (or the sync `ok` is in the
  // future): the capture gives up with kTooManyStale. >= 0.
  int max_stale_frames = 30;
  // Frames that disagree with the others are left out of the average (a transfer error, a
  // glitching sensor), and more are read in their place. Two frames disagree when more than
  // `outlier_fraction` of their pixel values (each channel counted) differ by more than
  // `outlier_dn`: sensor noise never does that to a settled press, a torn or garbled frame does.
  // Needs K >= 2 (K = 1 has nothing to compare with) and keeps every frame read, so K <=
  // kMaxFramesCompared with it on. outlier_dn in [1, 255], outlier_fraction in (0, 1],
  // max_outlier_frames >= 0.
  bool reject_outliers = true;
  int outlier_dn = 40;
  double outlier_fraction = 0.005;
  // Fresh frames beyond K that may be read to replace outliers before giving up (kInconsistent).
  int max_outlier_frames = 3;

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

enum class PressCaptureStatus {
  kOk,
  kTimeout,       // the source delivered fewer than K fresh frames before the deadline (or ended)
  kTooManyStale,  // more than max_stale_frames frames exposed before sync_ok
  kInconsistent,  // no K fresh frames agreed within K + max_outlier_frames
};

std::string_view ToString(PressCaptureStatus status);

struct PressCaptureResult {
  PressCaptureStatus status = PressCaptureStatus::kTimeout;
  // The per-pixel mean of the fresh frames, rounded to the nearest integer (ties to even),
  // CV_8UC3 BGR. Empty unless status == kOk.
  cv::Mat image;
  // Fresh frames received (K when kOk; fewer on kTimeout).
  int frames_used = 0;
  // Frames discarded because they were exposed before sync_ok.
  int stale_dropped = 0;
  // Fresh frames left out because they disagreed with the others (reject_outliers).
  int outliers_rejected = 0;
  // Timestamps and sequence numbers of the first and last frame averaged (valid when kOk; on a
  // failure, of the fresh frames received).
  std::chrono::steady_clock::time_point first_timestamp{};
  std::chrono::steady_clock::time_point last_timestamp{};
  std::uint64_t first_sequence = 0;
  std::uint64_t last_sequence = 0;

  bool ok() const { return status == PressCaptureStatus::kOk; }
};

// Reads frames from a started `source` until K fresh frames (ExposureStart() > sync_ok) that
// agree with each other have arrived, then averages them. Stale frames and outliers are counted
// and dropped. Each Next() call waits at
// most the time left until the deadline (now + options.timeout). Returns a status, not an
// exception, on timeout, too many stale frames or no agreeing K. Throws std::invalid_argument for
// invalid options, std::runtime_error if a frame is not CV_8UC3 or differs in size from the first
// fresh frame (a backend bug), and lets FrameSourceError from the source propagate.
PressCaptureResult CapturePress(FrameSource& source, std::chrono::steady_clock::time_point sync_ok,
                                const PressCaptureOptions& options);

// When to take a no-contact reference frame.
struct ReferenceSchedule {
  // M: a reference is due once this many probes have been done since the last one. 0: only the
  // one at the start of the run. >= 0.
  int every_m_probes = 100;

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;

  // True if a reference frame should be taken before the next probe: none has been taken yet
  // (last_reference_at is nullopt), or every_m_probes > 0 and probes_done - *last_reference_at >=
  // every_m_probes. probes_done counts probes completed in the run; last_reference_at is the value
  // probes_done had when the last reference was taken. Throws std::invalid_argument if
  // probes_done < 0 or last_reference_at is outside [0, probes_done].
  bool NeedsReference(std::int64_t probes_done,
                      std::optional<std::int64_t> last_reference_at) const;
};

}  // namespace gs360
