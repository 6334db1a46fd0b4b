#pragma once
// Commits press captures in the background: a probe's PNG encode and its transaction run on a
// worker thread with the committer's own connection, while the caller moves on to the next
// probe. At most one commit is in flight; the next Submit() (or Wait()) waits for it first, so
// captures commit in the order submitted and an error surfaces at most one probe later.
//
// What a kill costs: a capture submitted but not yet committed is simply not in the database, so
// its probe is still pending and is probed again on resume (never twice committed). Callers that
// pick the next probe while a commit is in flight pass InFlight() to
// RunDatabase::NextPendingProbe as `except`.
//
// Threads: Submit, Wait and InFlight are for one thread (the run loop); the worker touches only
// the committer's own connection and the frame handed to it.

#include <cstdint>
#include <filesystem>
#include <future>
#include <optional>

#include <opencv2/core/mat.hpp>

#include "storage/run_database.h"

namespace gs360 {

class CaptureCommitter {
 public:
  // Opens its own connection to `database` (throws StorageError as RunDatabase does).
  explicit CaptureCommitter(const std::filesystem::path& database, RunDatabaseOptions options = {});
  // Waits for the commit in flight; an error it raised is logged, not thrown.
  ~CaptureCommitter();
  CaptureCommitter(const CaptureCommitter&) = delete;
  CaptureCommitter& operator=(const CaptureCommitter&) = delete;

  // Waits for the previous commit (rethrowing its exception: StorageError, std::invalid_argument
  // as RunDatabase::CommitCapture throws them), then starts committing `frame` (shared, not
  // copied: the caller must not write to its pixels afterwards) as probe `probe_id`'s capture.
  void Submit(std::int64_t probe_id, cv::Mat frame, const CaptureReport& report);
  // Waits for the commit in flight, if any; rethrows its exception.
  void Wait();
  // The probe whose commit has been submitted and not yet waited for.
  std::optional<std::int64_t> InFlight() const { return in_flight_; }

 private:
  RunDatabase db_;
  std::future<void> pending_;
  std::optional<std::int64_t> in_flight_;
};

}  // namespace gs360
