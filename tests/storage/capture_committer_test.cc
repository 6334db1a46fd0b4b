// Captures committed on the committer's own connection while the run loop writes on its own.

#include <catch2/catch.hpp>

#include <vector>

#include "storage/capture_committer.h"
#include "storage/run_database.h"
#include "tests/storage/storage_test_util.h"

namespace gs360 {
namespace {

CaptureReport At(double t) {
  return {{1, 2, 3}, t, t + 0.05};
}

TEST_CASE("the committer commits every capture once and in order beside the run loop's writes",
          "[storage][concurrency]") {
  test::TempDir dir;
  const auto path = dir / "rig.gs360db";
  RunDatabase db(path);
  const std::int64_t run = db.CreateRun("{}", "h");
  constexpr int kProbes = 40;
  const std::vector<std::int64_t> ids = db.InsertPlan(run, std::vector<ProbePlanEntry>(kProbes));
  std::vector<cv::Mat> frames;
  for (int i = 0; i < kProbes; ++i) frames.push_back(test::NoisyFrame(i, 64, 48));

  CaptureCommitter committer(path);
  int picked = 0;
  for (;;) {
    // What the run loop does between two presses: pick the next probe (never the one being
    // committed), write on its own connection.
    const auto next = db.NextPendingProbe(run, 1, committer.InFlight());
    if (!next) break;
    REQUIRE(next->id == ids[picked]);
    db.AppendEvent(run, EventLevel::kInfo, "probe " + std::to_string(picked));
    const std::vector<Eigen::Vector3d> sent{{0.0, 0.0, static_cast<double>(picked)}};
    db.SetCommandedPath(run, sent);
    committer.Submit(next->id, frames[picked], At(picked));
    CHECK(committer.InFlight() == next->id);
    ++picked;
  }
  committer.Wait();
  CHECK_FALSE(committer.InFlight());
  CHECK(picked == kProbes);

  const std::vector<CapturedProbe> captured = db.ListCapturedProbes(run);
  REQUIRE(captured.size() == kProbes);
  for (int i = 0; i < kProbes; ++i) {
    CHECK(captured[i].probe.id == ids[i]);
    CHECK(captured[i].probe.attempts == 1);
    CHECK(test::SameImage(db.LoadFrame(captured[i].frame_id), frames[i]));
    if (i > 0) CHECK(captured[i].frame_id > captured[i - 1].frame_id);
  }
  CHECK_FALSE(db.NextPendingProbe(run, 1));
}

TEST_CASE("a failed background commit is thrown at the next wait and loses nothing else",
          "[storage][concurrency]") {
  test::TempDir dir;
  const auto path = dir / "rig.gs360db";
  RunDatabase db(path);
  const std::int64_t run = db.CreateRun("{}", "h");
  const std::vector<std::int64_t> ids = db.InsertPlan(run, std::vector<ProbePlanEntry>(3));
  db.MarkProbeSkipped(ids[1], "unreachable");  // committing a capture for it must fail
  const cv::Mat frame = test::NoisyFrame(7, 32, 24);

  CaptureCommitter committer(path);
  committer.Submit(ids[0], frame, At(1));
  committer.Submit(ids[1], frame, At(2));  // waits for the first: it succeeded
  CHECK_THROWS_AS(committer.Wait(), StorageError);
  CHECK_FALSE(committer.InFlight());
  committer.Wait();  // nothing in flight any more: no second throw

  SECTION("the next capture commits as usual") {
    committer.Submit(ids[2], frame, At(3));
    committer.Wait();
    CHECK(db.CountProbes(run).captured == 2);
    CHECK(db.GetProbe(ids[1])->state == ProbeState::kSkipped);
  }
  SECTION("a failure still in flight at destruction is not thrown") {
    {
      CaptureCommitter last(path);
      last.Submit(ids[1], frame, At(4));
    }
    CHECK(db.CountProbes(run).captured == 1);
  }
}

}  // namespace
}  // namespace gs360
