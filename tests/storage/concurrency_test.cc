// Status readers on their own connections, on other threads, while the writer commits.

#include <catch2/catch.hpp>

#include <atomic>
#include <exception>
#include <thread>

#include "storage/run_database.h"
#include "tests/storage/storage_test_util.h"

namespace gs360 {
namespace {

TEST_CASE("readers on other connections see monotonic progress and never block the writer",
          "[storage][concurrency]") {
  test::TempDir dir;
  const auto path = dir / "rig.gs360db";
  RunDatabase writer(path);
  const std::int64_t run = writer.CreateRun("{}", "h");
  constexpr int kProbes = 120;
  const std::vector<std::int64_t> ids =
      writer.InsertPlan(run, std::vector<ProbePlanEntry>(kProbes));
  writer.SetRunState(run, RunState::kRunning);

  std::atomic<bool> done{false};
  std::atomic<int> polls{0}, regressions{0}, frames_checked{0};
  std::exception_ptr reader_error;
  std::thread reader([&] {
    try {
      RunDatabase db(path, {.read_only = true});
      std::int64_t last = 0;
      while (!done.load()) {
        const RunStatus st = db.GetRunStatus(run);
        if (st.probes.captured < last) ++regressions;
        // The snapshot is consistent: the latest frame belongs to a probe counted as captured.
        if (st.latest_frame) {
          const std::optional<ProbeRecord> p = db.GetProbe(*st.latest_frame->probe_id);
          if (!p || p->state != ProbeState::kCaptured) ++regressions;
          if (!db.LoadFrame(st.latest_frame->id).empty()) ++frames_checked;
        }
        last = st.probes.captured;
        ++polls;
      }
    } catch (...) {
      reader_error = std::current_exception();
    }
  });

  for (int i = 0; i < kProbes; ++i) {
    writer.CommitCapture(ids[i], test::NoisyFrame(i, 64, 48), {{0, 0, 0}, 10.0 * i, 10.0 * i + 1});
    if (i % 10 == 0) std::this_thread::yield();
  }
  done = true;
  reader.join();
  if (reader_error) std::rethrow_exception(reader_error);

  CHECK(regressions == 0);
  CHECK(polls > 0);
  CHECK(frames_checked > 0);
  RunDatabase late_reader(path, {.read_only = true});
  CHECK(late_reader.GetRunStatus(run).probes.captured == kProbes);
}

}  // namespace
}  // namespace gs360
