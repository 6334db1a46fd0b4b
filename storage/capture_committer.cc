#include "storage/capture_committer.h"

#include <exception>
#include <utility>

#include <spdlog/spdlog.h>

namespace gs360 {

CaptureCommitter::CaptureCommitter(const std::filesystem::path& database,
                                   RunDatabaseOptions options)
    : db_(database, std::move(options)) {}

CaptureCommitter::~CaptureCommitter() {
  try {
    Wait();
  } catch (const std::exception& e) {
    spdlog::error("a capture commit failed while shutting down: {}", e.what());
  }
}

void CaptureCommitter::Submit(std::int64_t probe_id, cv::Mat frame, const CaptureReport& report) {
  Wait();
  // std::async's future joins the worker when waited on: Wait() orders every use of db_.
  pending_ = std::async(std::launch::async, [this, probe_id, frame = std::move(frame), report] {
    db_.CommitCapture(probe_id, frame, report);
  });
  in_flight_ = probe_id;
}

void CaptureCommitter::Wait() {
  if (!pending_.valid()) return;
  in_flight_.reset();
  pending_.get();  // get() leaves the future invalid, also when it throws
}

}  // namespace gs360
