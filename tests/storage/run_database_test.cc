#include <catch2/catch.hpp>

#include <cmath>
#include <limits>
#include <memory>

#include "storage/run_database.h"
#include "storage/schema.h"
#include "tests/storage/storage_test_util.h"

namespace gs360 {
namespace {

// A clock the test moves by hand.
struct FakeClock {
  std::shared_ptr<double> now = std::make_shared<double>(1000.0);
  std::function<double()> Fn() const {
    auto n = now;
    return [n] { return *n; };
  }
  void Set(double t) const { *now = t; }
};

std::vector<ProbePlanEntry> MakePlan(int n) {
  std::vector<ProbePlanEntry> plan(n);
  for (int i = 0; i < n; ++i) {
    const double a = 0.1 * i;
    plan[i].point_sensor = {5.0 * std::cos(a), 5.0 * std::sin(a), 10.0 + 0.01 * i};
    plan[i].normal_sensor = {std::cos(a), std::sin(a), 0.0};
    plan[i].approach_machine = {100.0 + i / 3.0, 50.0 - i / 7.0, 20.0 + 1.0 / (i + 1)};
    plan[i].press_machine = plan[i].approach_machine - Eigen::Vector3d(0.1, 0.2, 3.3);
    plan[i].retract_machine = plan[i].approach_machine + Eigen::Vector3d(0, 0, 5.0 / 3.0);
  }
  return plan;
}

CaptureReport Report(double sync_time, const Eigen::Vector3d& mpos = {1.5, -2.25, 3.125}) {
  return {mpos, sync_time, sync_time + 0.05};
}

TEST_CASE("a run and its plan round-trip exactly", "[storage][db]") {
  test::TempDir dir;
  FakeClock clock;
  RunDatabaseOptions options;
  options.clock = clock.Fn();
  RunDatabase db(dir / "rig.gs360db", options);
  CHECK(db.schema_version() == kSchemaVersion);

  const std::string config = R"({"probes": 12, "shape": "cylinder", "depth_mm": 0.5})";
  const std::int64_t run = db.CreateRun(config, "0123456789abcdef", "first");
  const std::vector<ProbePlanEntry> plan = MakePlan(12);
  const std::vector<std::int64_t> ids = db.InsertPlan(run, plan);
  REQUIRE(ids.size() == 12);

  const std::optional<RunRecord> rec = db.GetRun(run);
  REQUIRE(rec);
  CHECK(rec->name == "first");
  CHECK(rec->config_json == config);
  CHECK(rec->mesh_hash == "0123456789abcdef");
  CHECK(rec->state == RunState::kCreated);
  CHECK(rec->created_at == 1000.0);
  CHECK_FALSE(rec->started_at);

  const std::vector<ProbeRecord> probes = db.ListProbes(run);
  REQUIRE(probes.size() == 12);
  for (int i = 0; i < 12; ++i) {
    CAPTURE(i);
    CHECK(probes[i].id == ids[i]);
    CHECK(probes[i].plan_index == i);
    CHECK(probes[i].state == ProbeState::kPlanned);
    CHECK(probes[i].attempts == 0);
    CHECK_FALSE(probes[i].machine_position);
    // Doubles are stored as IEEE doubles: bit-exact.
    CHECK(probes[i].plan.point_sensor == plan[i].point_sensor);
    CHECK(probes[i].plan.normal_sensor == plan[i].normal_sensor);
    CHECK(probes[i].plan.approach_machine == plan[i].approach_machine);
    CHECK(probes[i].plan.press_machine == plan[i].press_machine);
    CHECK(probes[i].plan.retract_machine == plan[i].retract_machine);
  }
  CHECK(db.GetProbeByIndex(run, 7)->id == ids[7]);
  CHECK_FALSE(db.GetProbeByIndex(run, 12));
  const ProbeCounts counts = db.CountProbes(run);
  CHECK(counts.total == 12);
  CHECK(counts.planned == 12);

  SECTION("a second plan for the same run is refused and changes nothing") {
    try {
      db.InsertPlan(run, plan);
      FAIL("expected StorageError");
    } catch (const StorageError& e) {
      CHECK(e.code() == StorageErrc::kInvalidState);
    }
    CHECK(db.CountProbes(run).total == 12);
  }
  SECTION("a plan with a NaN is refused before anything is written") {
    const std::int64_t run2 = db.CreateRun("{}", "x");
    std::vector<ProbePlanEntry> bad = MakePlan(3);
    bad[2].press_machine.y() = std::numeric_limits<double>::quiet_NaN();
    CHECK_THROWS_WITH(db.InsertPlan(run2, bad),
                      Catch::Contains("plan index 2") && Catch::Contains("press_machine"));
    CHECK(db.CountProbes(run2).total == 0);
  }
  SECTION("config must be JSON; unknown runs are not found") {
    CHECK_THROWS_AS(db.CreateRun("{not json", "x"), std::invalid_argument);
    CHECK(db.ListRuns().size() == 1);
    CHECK_FALSE(db.GetRun(run + 100));
    try {
      db.InsertPlan(run + 100, plan);
      FAIL("expected StorageError");
    } catch (const StorageError& e) {
      CHECK(e.code() == StorageErrc::kNotFound);
    }
  }
  SECTION("everything survives closing and reopening the file") {
    const std::filesystem::path path = db.path();
    db = RunDatabase(dir / "other.gs360db");  // closes the first connection
    RunDatabase again(path);
    CHECK(again.ListRuns().size() == 1);
    CHECK(again.ListProbes(run).size() == 12);
    CHECK(again.ListProbes(run)[11].plan.retract_machine == plan[11].retract_machine);
  }
}

TEST_CASE("CommitCapture stores the frame, the position and the state together", "[storage][db]") {
  test::TempDir dir;
  FakeClock clock;
  RunDatabaseOptions options;
  options.clock = clock.Fn();
  RunDatabase db(dir / "rig.gs360db", options);
  const std::int64_t run = db.CreateRun("{}", "h");
  const std::vector<std::int64_t> ids = db.InsertPlan(run, MakePlan(4));

  const cv::Mat image = test::NoisyFrame(11, 160, 120);
  clock.Set(2000.0);
  const Eigen::Vector3d mpos(12.5, -3.75, 40.0625);
  const std::int64_t frame = db.CommitCapture(ids[1], image, {mpos, 1999.0, 1999.25});

  const ProbeRecord p = *db.GetProbe(ids[1]);
  CHECK(p.state == ProbeState::kCaptured);
  CHECK(p.attempts == 1);
  REQUIRE(p.machine_position);
  CHECK(*p.machine_position == mpos);
  CHECK(p.sync_time == 1999.0);
  CHECK(p.captured_at == 2000.0);
  CHECK(db.GetRun(run)->updated_at == 2000.0);

  const FrameInfo info = *db.GetFrameInfo(frame);
  CHECK(info.kind == FrameKind::kPress);
  CHECK(info.probe_id == ids[1]);
  CHECK(info.run_id == run);
  CHECK(info.timestamp == 1999.25);
  CHECK(info.width == 160);
  CHECK(info.height == 120);
  CHECK(info.channels == 3);
  CHECK(info.bit_depth == 8);
  CHECK(info.checksum == BlobChecksum(db.LoadFramePng(frame)));
  CHECK(test::SameImage(db.LoadFrame(frame), image));

  const std::vector<CapturedProbe> captured = db.ListCapturedProbes(run);
  REQUIRE(captured.size() == 1);
  CHECK(captured[0].probe.id == ids[1]);
  CHECK(captured[0].frame_id == frame);
  CHECK(captured[0].frame_time == 1999.25);

  SECTION("a captured probe is never captured again") {
    try {
      db.CommitCapture(ids[1], image, Report(2100));
      FAIL("expected StorageError");
    } catch (const StorageError& e) {
      CHECK(e.code() == StorageErrc::kInvalidState);
      CHECK_THAT(e.what(), Catch::Contains("already captured"));
    }
    CHECK_THROWS_AS(db.MarkProbeFailed(ids[1], "x"), StorageError);
    CHECK_THROWS_AS(db.MarkProbeSkipped(ids[1], "x"), StorageError);
    CHECK(db.GetProbe(ids[1])->attempts == 1);
    CHECK(db.ListFrames(run, FrameKind::kPress).size() == 1);
  }
  SECTION("bad reports are refused before anything is written") {
    CHECK_THROWS_WITH(db.CommitCapture(ids[2], image, {mpos, 10.0, 9.0}),
                      Catch::Contains("before sync_time"));
    CHECK_THROWS_AS(
        db.CommitCapture(ids[2], image, Report(5, {0, std::numeric_limits<double>::infinity(), 0})),
        std::invalid_argument);
    CHECK_THROWS_AS(db.CommitCapture(ids[2], cv::Mat(), Report(5)), std::invalid_argument);
    CHECK(db.GetProbe(ids[2])->state == ProbeState::kPlanned);
    CHECK(db.ListFrames(run, FrameKind::kPress).size() == 1);
  }
  SECTION("unknown probes are not found") {
    try {
      db.CommitCapture(ids[3] + 50, image, Report(5));
      FAIL("expected StorageError");
    } catch (const StorageError& e) {
      CHECK(e.code() == StorageErrc::kNotFound);
    }
  }
  SECTION("16-bit frames are stored and loaded exactly") {
    const cv::Mat deep = test::NoisyFrame(12, 80, 60, CV_16UC3, 0.4);
    const std::int64_t f = db.CommitCapture(ids[0], deep, Report(3000));
    CHECK(db.GetFrameInfo(f)->bit_depth == 16);
    CHECK(test::SameImage(db.LoadFrame(f), deep));
  }
  SECTION("a frame encoded ahead of time commits the same way") {
    const EncodedFrame encoded = EncodeFrame(image, {.compression_level = 9});
    const std::int64_t f = db.CommitCapture(ids[2], encoded, Report(3000));
    CHECK(db.LoadFramePng(f) == encoded.png);
    CHECK(test::SameImage(db.LoadFrame(f), image));
  }
}

TEST_CASE("failed and skipped probes, and the order a resume follows", "[storage][db]") {
  test::TempDir dir;
  RunDatabase db(dir / "rig.gs360db");
  const std::int64_t run = db.CreateRun("{}", "h");
  const std::vector<std::int64_t> ids = db.InsertPlan(run, MakePlan(6));
  const cv::Mat image = test::NoisyFrame(1, 32, 24);

  db.CommitCapture(ids[0], image, Report(1));
  db.MarkProbeFailed(ids[1], "no sync ok within 30 s");
  db.MarkProbeSkipped(ids[2], "unreachable");
  db.MarkProbeFailed(ids[4], "camera timeout");
  db.MarkProbeFailed(ids[4], "camera timeout again");

  const ProbeRecord failed = *db.GetProbe(ids[1]);
  CHECK(failed.state == ProbeState::kFailed);
  CHECK(failed.attempts == 1);
  CHECK(failed.last_error == "no sync ok within 30 s");
  const ProbeRecord skipped = *db.GetProbe(ids[2]);
  CHECK(skipped.state == ProbeState::kSkipped);
  CHECK(skipped.attempts == 0);
  CHECK(skipped.skip_reason == "unreachable");
  CHECK(db.GetProbe(ids[4])->attempts == 2);

  ProbeCounts c = db.CountProbes(run);
  CHECK(c.total == 6);
  CHECK(c.captured == 1);
  CHECK(c.failed == 2);
  CHECK(c.skipped == 1);
  CHECK(c.planned == 2);

  // Without retries the first never-tried probe comes next; with retries, the failed one first.
  CHECK(db.NextPendingProbe(run, 1)->plan_index == 3);
  CHECK(db.NextPendingProbe(run, 2)->plan_index == 1);
  CHECK(db.NextPendingProbe(run, 3)->plan_index == 1);
  CHECK(db.ListProbes(run, ProbeState::kFailed).size() == 2);
  // A probe whose capture is being committed elsewhere is passed over, planned or failed.
  CHECK(db.NextPendingProbe(run, 1, ids[3])->plan_index == 5);
  CHECK(db.NextPendingProbe(run, 2, ids[1])->plan_index == 3);

  // A retry that succeeds counts both attempts and keeps the last error for the record.
  db.CommitCapture(ids[1], image, Report(2));
  CHECK(db.GetProbe(ids[1])->attempts == 2);
  CHECK(db.GetProbe(ids[1])->last_error == "no sync ok within 30 s");
  CHECK(db.NextPendingProbe(run, 2)->plan_index == 3);
  CHECK_THROWS_AS(db.CommitCapture(ids[2], image, Report(3)), StorageError);  // skipped

  db.CommitCapture(ids[3], image, Report(3));
  db.CommitCapture(ids[5], image, Report(4));
  CHECK(db.NextPendingProbe(run, 3)->plan_index == 4);
  CHECK_FALSE(db.NextPendingProbe(run, 2));
  CHECK(db.ListCapturedProbes(run).size() == 4);

  // A failure a second press cannot change: never pending again, whatever max_attempts says.
  db.MarkProbeFailed(ids[4], "no impression", false);
  CHECK(db.GetProbe(ids[4])->attempts == 3);
  CHECK_FALSE(db.GetProbe(ids[4])->retry);
  CHECK(db.GetProbe(ids[0])->retry);
  CHECK_FALSE(db.NextPendingProbe(run, 10));
  CHECK(db.CountProbes(run).failed == 1);

  // A run ending early skips what is open (planned or failed), never a captured probe.
  const std::int64_t other = db.CreateRun("{}", "h");
  const std::vector<std::int64_t> more = db.InsertPlan(other, MakePlan(5));
  db.CommitCapture(more[0], image, Report(5));
  db.MarkProbeFailed(more[1], "camera timeout");
  db.MarkProbeSkipped(more[2], "unreachable");
  CHECK(db.SkipOpenProbes(other, "converged") == 3);
  CHECK(db.GetProbe(more[0])->state == ProbeState::kCaptured);
  CHECK(db.GetProbe(more[1])->skip_reason == "converged");
  CHECK(db.GetProbe(more[2])->skip_reason == "unreachable");
  CHECK(db.GetProbe(more[4])->state == ProbeState::kSkipped);
  CHECK_FALSE(db.NextPendingProbe(other, 9));
  CHECK(db.SkipOpenProbes(other, "converged") == 0);
  CHECK(db.CountProbes(run).captured == 4);  // the other run is untouched
  CHECK_THROWS_AS(db.SkipOpenProbes(999, "converged"), StorageError);
}

TEST_CASE("run states, elapsed time and the run log", "[storage][db]") {
  test::TempDir dir;
  FakeClock clock;
  RunDatabaseOptions options;
  options.clock = clock.Fn();
  RunDatabase db(dir / "rig.gs360db", options);
  const std::int64_t run = db.CreateRun("{}", "h");
  const std::vector<std::int64_t> ids = db.InsertPlan(run, MakePlan(3));

  clock.Set(1100);
  db.SetRunState(run, RunState::kRunning);
  CHECK(db.GetRun(run)->started_at == 1100);
  clock.Set(1130);
  CHECK(db.GetRunStatus(run).elapsed_s == Approx(30));
  clock.Set(1150);
  db.SetRunState(run, RunState::kPaused);
  clock.Set(1400);
  CHECK(db.GetRunStatus(run).elapsed_s == Approx(50));  // paused time does not count
  db.SetRunState(run, RunState::kRunning);
  db.SetRunState(run, RunState::kRunning);  // same state: no-op
  CHECK(db.GetRun(run)->started_at == 1100);
  clock.Set(1410);
  db.CommitCapture(ids[0], test::NoisyFrame(1, 16, 16), Report(1409));
  // The daemon died at ~1410; it is noticed at 5000: the run was active until its last commit.
  clock.Set(5000);
  db.SetRunState(run, RunState::kInterrupted);
  CHECK(db.GetRun(run)->active_s == Approx(60));
  CHECK(db.GetRunStatus(run).elapsed_s == Approx(60));
  db.SetRunState(run, RunState::kRunning);
  clock.Set(5020);
  db.SetRunState(run, RunState::kDone);
  const RunRecord done = *db.GetRun(run);
  CHECK(done.active_s == Approx(80));
  CHECK(done.finished_at == 5020);
  CHECK_FALSE(done.running_since);

  for (RunState s :
       {RunState::kRunning, RunState::kPaused, RunState::kCancelled, RunState::kCreated}) {
    CAPTURE(ToString(s));
    try {
      db.SetRunState(run, s);
      FAIL("expected StorageError");
    } catch (const StorageError& e) {
      CHECK(e.code() == StorageErrc::kInvalidState);
      CHECK_THAT(e.what(), Catch::Contains("done"));
    }
  }
  CHECK(db.GetRun(run)->state == RunState::kDone);

  const std::int64_t other = db.CreateRun("{}", "h");
  CHECK_THROWS_AS(db.SetRunState(other, RunState::kPaused), StorageError);
  CHECK_THROWS_AS(db.SetRunState(other + 1, RunState::kRunning), StorageError);

  // State changes are logged in order, with the run's id.
  std::vector<std::string> messages;
  for (const EventRecord& e : db.ListEvents(run)) messages.push_back(e.message);
  const std::vector<std::string> expected = {"run created",
                                             "plan inserted: 3 probes",
                                             "run state created -> running",
                                             "run state running -> paused",
                                             "run state paused -> running",
                                             "run state running -> interrupted",
                                             "run state interrupted -> running",
                                             "run state running -> done"};
  CHECK(messages == expected);
}

TEST_CASE("events: append, page through, JSON payloads", "[storage][db]") {
  test::TempDir dir;
  FakeClock clock;
  RunDatabaseOptions options;
  options.clock = clock.Fn();
  RunDatabase db(dir / "rig.gs360db", options);
  const std::int64_t run = db.CreateRun("{}", "h");
  const std::int64_t first = db.ListEvents(run).back().id;
  clock.Set(1234.5);
  const std::int64_t a = db.AppendEvent(run, EventLevel::kWarning, "alarm 2", R"({"alarm": 2})");
  const std::int64_t b = db.AppendEvent(std::nullopt, EventLevel::kError, "usb unplugged");
  const std::int64_t c = db.AppendEvent(run, EventLevel::kDebug, "status");
  CHECK(a < b);
  CHECK(b < c);

  const std::vector<EventRecord> mine = db.ListEvents(run, first);
  REQUIRE(mine.size() == 2);
  CHECK(mine[0].id == a);
  CHECK(mine[0].level == EventLevel::kWarning);
  CHECK(mine[0].data_json == R"({"alarm": 2})");
  CHECK(mine[0].timestamp == 1234.5);
  CHECK(mine[1].id == c);
  CHECK(mine[1].data_json.empty());
  const std::vector<EventRecord> all = db.ListEvents(std::nullopt, a);
  REQUIRE(all.size() == 2);
  CHECK_FALSE(all[0].run_id);
  CHECK(all[0].message == "usb unplugged");
  CHECK(db.ListEvents(std::nullopt, 0, 1).size() == 1);

  CHECK_THROWS_AS(db.AppendEvent(run, EventLevel::kInfo, "x", "{bad"), std::invalid_argument);
  CHECK_THROWS_AS(db.AppendEvent(run + 9, EventLevel::kInfo, "x"), StorageError);
  CHECK(db.ListEvents(std::nullopt, c).empty());
}

TEST_CASE("reference frames and the nearest one in time", "[storage][db]") {
  test::TempDir dir;
  RunDatabase db(dir / "rig.gs360db");
  const std::int64_t run = db.CreateRun("{}", "h");
  const std::int64_t other = db.CreateRun("{}", "h");
  CHECK_FALSE(db.NearestReferenceFrame(run, 10));

  const cv::Mat r1 = test::NoisyFrame(1, 48, 32), r2 = test::NoisyFrame(2, 48, 32);
  const std::int64_t f20 = db.AddReferenceFrame(run, r2, 20.0);
  const std::int64_t f10 = db.AddReferenceFrame(run, r1, 10.0);
  const std::int64_t f30 = db.AddReferenceFrame(run, test::NoisyFrame(3, 48, 32), 30.0);
  db.AddReferenceFrame(other, test::NoisyFrame(4, 48, 32), 14.0);

  CHECK(db.NearestReferenceFrame(run, 14)->id == f10);
  CHECK(db.NearestReferenceFrame(run, 15)->id == f10);  // a tie goes to the earlier one
  CHECK(db.NearestReferenceFrame(run, 15.5)->id == f20);
  CHECK(db.NearestReferenceFrame(run, 20)->id == f20);
  CHECK(db.NearestReferenceFrame(run, -5)->id == f10);
  CHECK(db.NearestReferenceFrame(run, 99)->id == f30);
  CHECK(test::SameImage(db.LoadFrame(f10), r1));
  CHECK_FALSE(db.GetFrameInfo(f10)->probe_id);

  const std::vector<FrameInfo> refs = db.ListFrames(run, FrameKind::kReference);
  REQUIRE(refs.size() == 3);
  CHECK(refs[0].id == f10);
  CHECK(refs[2].id == f30);
  CHECK(db.LatestFrame(run)->id == f30);
  CHECK(db.LatestFrame(run, FrameKind::kReference)->id == f30);
  CHECK_FALSE(db.LatestFrame(run, FrameKind::kPress));
  CHECK(db.GetRunStatus(run).reference_frames == 3);
  CHECK_THROWS_AS(db.AddReferenceFrame(run + 10, r1, 1.0), StorageError);
}

TEST_CASE("GetRunStatus gathers counts, time and the latest frame", "[storage][db]") {
  test::TempDir dir;
  RunDatabase db(dir / "rig.gs360db");
  const std::int64_t run = db.CreateRun("{}", "h");
  const std::vector<std::int64_t> ids = db.InsertPlan(run, MakePlan(5));
  db.AddReferenceFrame(run, test::NoisyFrame(0, 20, 20), 1.0);
  db.CommitCapture(ids[0], test::NoisyFrame(1, 20, 20), Report(2));
  const std::int64_t latest = db.CommitCapture(ids[1], test::NoisyFrame(2, 20, 20), Report(3));
  db.MarkProbeFailed(ids[2], "x");
  db.MarkProbeSkipped(ids[3], "y");

  const RunStatus st = db.GetRunStatus(run);
  CHECK(st.run.id == run);
  CHECK(st.probes.total == 5);
  CHECK(st.probes.captured == 2);
  CHECK(st.probes.failed == 1);
  CHECK(st.probes.skipped == 1);
  CHECK(st.probes.planned == 1);
  CHECK(st.reference_frames == 1);
  REQUIRE(st.latest_frame);
  CHECK(st.latest_frame->id == latest);
  CHECK(st.elapsed_s == 0);
  try {
    db.GetRunStatus(run + 1);
    FAIL("expected StorageError");
  } catch (const StorageError& e) {
    CHECK(e.code() == StorageErrc::kNotFound);
  }
}

TEST_CASE("artifacts are keyed by run, stage and input hash", "[storage][db]") {
  test::TempDir dir;
  RunDatabase db(dir / "rig.gs360db");
  const std::int64_t run = db.CreateRun("{}", "h");
  const std::vector<std::uint8_t> blob = {1, 2, 3, 4, 5, 250};
  const std::int64_t id = db.PutArtifact(run, "pose", "aaaa", blob, R"({"rms_px": 0.4})");

  const std::optional<ArtifactRecord> got = db.GetArtifact(run, "pose", "aaaa");
  REQUIRE(got);
  CHECK(got->id == id);
  CHECK(got->blob == blob);
  CHECK(got->metrics_json == R"({"rms_px": 0.4})");
  CHECK(got->checksum == BlobChecksum(blob));
  CHECK_FALSE(db.GetArtifact(run, "pose", "bbbb"));
  CHECK_FALSE(db.GetArtifact(run, "render", "aaaa"));

  // Putting the same key again replaces it in place.
  const std::vector<std::uint8_t> blob2 = {9, 9};
  CHECK(db.PutArtifact(run, "pose", "aaaa", blob2) == id);
  CHECK(db.GetArtifact(run, "pose", "aaaa")->blob == blob2);
  CHECK(db.GetArtifact(run, "pose", "aaaa")->metrics_json == "{}");

  // Empty blobs are allowed.
  db.PutArtifact(run, "surface_map", "cccc", {});
  CHECK(db.GetArtifact(run, "surface_map", "cccc")->blob.empty());

  const std::vector<ArtifactRecord> list = db.ListArtifacts(run);
  REQUIRE(list.size() == 2);
  CHECK(list[0].stage == "pose");
  CHECK(list[0].blob.empty());  // listings carry no blobs
  CHECK(list[0].size == 2);

  CHECK_THROWS_AS(db.PutArtifact(run, "pose", "x", blob, "nope"), std::invalid_argument);
  CHECK_THROWS_AS(db.PutArtifact(run, "", "x", blob), std::invalid_argument);
  CHECK_THROWS_AS(db.PutArtifact(run + 1, "pose", "x", blob), StorageError);
}

TEST_CASE("models: stored once per name and version, checksum verified", "[storage][db]") {
  test::TempDir dir;
  RunDatabase db(dir / "rig.gs360db");
  const std::int64_t run = db.CreateRun("{}", "h");
  std::vector<std::uint8_t> bundle(5000);
  for (std::size_t i = 0; i < bundle.size(); ++i) bundle[i] = static_cast<std::uint8_t>(i * 31);
  const std::int64_t id = db.PutModel("gs360-mlp", "1.0.0", bundle, R"({"rmse_mm": 0.02})", run);
  db.PutModel("gs360-mlp", "1.1.0", bundle);

  const std::optional<ModelRecord> m = db.GetModel("gs360-mlp", "1.0.0");
  REQUIRE(m);
  CHECK(m->id == id);
  CHECK(m->run_id == run);
  CHECK(m->blob == bundle);
  CHECK(m->size == 5000);
  CHECK(m->metadata_json == R"({"rmse_mm": 0.02})");
  CHECK_FALSE(db.GetModel("gs360-mlp", "2.0.0"));
  CHECK_FALSE(db.GetModel("gs360-mlp", "1.1.0")->run_id);

  try {
    db.PutModel("gs360-mlp", "1.0.0", bundle);
    FAIL("expected StorageError");
  } catch (const StorageError& e) {
    CHECK(e.code() == StorageErrc::kConflict);
    CHECK_THAT(e.what(), Catch::Contains("1.0.0") && Catch::Contains("already exists"));
  }
  const std::vector<ModelRecord> list = db.ListModels();
  REQUIRE(list.size() == 2);
  CHECK(list[1].version == "1.1.0");
  CHECK(list[1].blob.empty());
}

TEST_CASE("last_error is kept until the run runs again, and DeleteRun removes a run whole",
          "[storage][db]") {
  test::TempDir dir;
  RunDatabase db(dir / "rig.gs360db");
  const std::int64_t run = db.CreateRun("{}", "h");
  const std::int64_t other = db.CreateRun("{}", "h");
  const std::vector<std::int64_t> ids = db.InsertPlan(run, MakePlan(3));
  db.InsertPlan(other, MakePlan(2));
  db.SetRunState(run, RunState::kRunning);
  db.CommitCapture(ids[0], test::NoisyFrame(3, 64, 48), Report(10.0));
  db.AddReferenceFrame(run, test::NoisyFrame(4, 64, 48), 9.0);
  db.PutArtifact(run, "pose", "k", std::vector<std::uint8_t>{1, 2, 3});
  const std::vector<std::uint8_t> bundle(100, 7);
  db.PutModel("m", "1", bundle, "{}", run);

  db.SetRunState(run, RunState::kInterrupted);
  db.SetRunError(run, "ALARM:1 (hard limit)");
  CHECK(db.GetRun(run)->last_error == "ALARM:1 (hard limit)");
  const auto events = db.ListEvents(run);
  REQUIRE_FALSE(events.empty());
  CHECK(events.back().level == EventLevel::kError);
  // The state change's event says what changed in its data.
  bool saw_state = false;
  for (const EventRecord& e : events) {
    if (e.data_json.find(R"("state":"interrupted")") != std::string::npos) saw_state = true;
  }
  CHECK(saw_state);

  // A running run cannot be deleted; then running again clears the error.
  db.SetRunState(run, RunState::kRunning);
  CHECK(db.GetRun(run)->last_error.empty());
  try {
    db.DeleteRun(run);
    FAIL("expected StorageError");
  } catch (const StorageError& e) {
    CHECK(e.code() == StorageErrc::kInvalidState);
  }
  db.SetRunState(run, RunState::kPaused);
  db.DeleteRun(run);
  CHECK_FALSE(db.GetRun(run));
  CHECK(db.ListProbes(run).empty());
  CHECK(db.ListFrames(run, FrameKind::kReference).empty());
  CHECK(db.ListArtifacts(run).empty());
  CHECK(db.ListEvents(run).empty());
  // The model survives, detached; the other run is untouched.
  REQUIRE(db.GetModel("m", "1"));
  CHECK_FALSE(db.GetModel("m", "1")->run_id);
  CHECK(db.CountProbes(other).total == 2);
  try {
    db.DeleteRun(run);
    FAIL("expected StorageError");
  } catch (const StorageError& e) {
    CHECK(e.code() == StorageErrc::kNotFound);
  }
  // Ids are never given out twice, even the newest's after it is deleted.
  db.DeleteRun(other);
  CHECK(db.ListRuns().empty());
  const std::int64_t next = db.CreateRun("{}", "h");
  CHECK(next > other);
  CHECK_THROWS_AS(db.SetRunState(other, RunState::kRunning), StorageError);
}

TEST_CASE("the commanded path round-trips and a homing cycle is marked until the next motion",
          "[storage][db]") {
  test::TempDir dir;
  RunDatabase db(dir / "rig.gs360db");
  const std::int64_t run = db.CreateRun("{}", "h");
  CHECK(db.GetRun(run)->commanded_path.empty());
  CHECK_FALSE(db.GetRun(run)->homing_sent);
  const std::vector<Eigen::Vector3d> path = {{-1.0, -2.5, -3.25}, {-140.125, -88.0, -32.9375}};
  db.SetCommandedPath(run, path);
  CHECK(db.GetRun(run)->commanded_path == path);
  db.MarkHomingSent(run);
  CHECK(db.GetRun(run)->homing_sent);
  CHECK(db.GetRun(run)->commanded_path == path);  // the path the cycle started from is kept
  db.SetCommandedPath(run, std::vector<Eigen::Vector3d>{{-1.0, -1.0, -1.0}});
  CHECK_FALSE(db.GetRun(run)->homing_sent);
  const std::vector<Eigen::Vector3d> bad = {{0.0, std::nan(""), 0.0}};
  CHECK_THROWS_AS(db.SetCommandedPath(run, bad), std::invalid_argument);
  CHECK_THROWS_AS(db.MarkHomingSent(run + 1), StorageError);
}

TEST_CASE("RunDatabaseOptions::Check names the field and the value", "[storage][db]") {
  CHECK_NOTHROW(RunDatabaseOptions{}.Check());
  RunDatabaseOptions o;
  o.busy_timeout_ms = -5;
  CHECK_THROWS_WITH(o.Check(), Catch::Contains("busy_timeout_ms") && Catch::Contains("-5"));
  o = {};
  o.max_page_count = -1;
  CHECK_THROWS_WITH(o.Check(), Catch::Contains("max_page_count"));
  o = {};
  o.png.compression_level = 12;
  CHECK_THROWS_WITH(o.Check(), Catch::Contains("compression_level") && Catch::Contains("12"));
  test::TempDir dir;
  CHECK_THROWS_AS(RunDatabase(dir / "x.gs360db", o), std::invalid_argument);
  CHECK_FALSE(std::filesystem::exists(dir / "x.gs360db"));
}

TEST_CASE("the file is in WAL mode and carries gs360's id and schema version", "[storage][db]") {
  test::TempDir dir;
  const auto path = dir / "rig.gs360db";
  {
    RunDatabase db(path);
    db.CreateRun("{}", "h");
    test::RawDb raw(path);
    CHECK(raw.Text("PRAGMA journal_mode") == "wal");
    CHECK(raw.Int("PRAGMA application_id") == kApplicationId);
    CHECK(raw.Int("PRAGMA user_version") == kSchemaVersion);
    CHECK(raw.Int("PRAGMA page_size") == 16384);
    // Foreign keys hold: no probe may point at a missing run (checked with enforcement on).
    raw.Exec("PRAGMA foreign_keys = ON");
    CHECK_THROWS(
        raw.Exec("INSERT INTO probes (run_id, plan_index, point_x, point_y, point_z, "
                 "normal_x, normal_y, normal_z, approach_x, approach_y, approach_z, "
                 "press_x, press_y, press_z, retract_x, retract_y, retract_z) "
                 "VALUES (77, 0, 0,0,0, 0,0,1, 0,0,0, 0,0,0, 0,0,0)"));
    // The schema refuses a captured probe without its reported position.
    CHECK_THROWS(
        raw.Exec("INSERT INTO probes (run_id, plan_index, point_x, point_y, point_z, "
                 "normal_x, normal_y, normal_z, approach_x, approach_y, approach_z, "
                 "press_x, press_y, press_z, retract_x, retract_y, retract_z, state) "
                 "VALUES (1, 0, 0,0,0, 0,0,1, 0,0,0, 0,0,0, 0,0,0, 'captured')"));
  }
  // A second RunDatabase on the same file sees the same data.
  RunDatabase a(path), b(path);
  a.CreateRun("{}", "second");
  CHECK(b.ListRuns().size() == 2);
  CHECK(a.IntegrityCheck().empty());
}

}  // namespace
}  // namespace gs360
