// The run engine end to end on the virtual rig, in-process: a clean run, pause / stop / cancel,
// resume (including a moved sensor), and every fault the virtual CNC can inject.

#include <catch2/catch.hpp>

#include <fstream>
#include <set>
#include <thread>

#include "rig_fixture.h"
#include "storage/run_database.h"
#include "storage/storage_error.h"
#include "tests/wait.h"

using namespace gs360;
using gs360::test::AtProbe;
using gs360::test::RigFixture;
using gs360::test::StopAfter;

namespace {

// Every captured probe has exactly one press frame, taken at the press position.
void CheckCommitted(RigFixture& f, std::int64_t run_id) {
  RunDatabaseOptions ro;
  ro.read_only = true;
  RunDatabase db(f.db, ro);
  const auto captured = db.ListCapturedProbes(run_id);
  const auto frames = db.ListFrames(run_id, FrameKind::kPress);
  CHECK(frames.size() == captured.size());
  std::set<std::int64_t> probes;
  for (const auto& fr : frames) {
    REQUIRE(fr.probe_id);
    CHECK(probes.insert(*fr.probe_id).second);  // never two frames for one probe
  }
  CHECK(db.IntegrityCheck().empty());
  const cli::CaptureTruth truth = cli::CheckCapturesAgainstTruth(*f.rig, db, run_id);
  CHECK(truth.frames == static_cast<int>(captured.size()));
  CHECK(truth.off_target == 0);
  CHECK(truth.unverified == 0);
  CHECK(truth.max_reported_error_mm < 0.002);
}

}  // namespace

TEST_CASE("a run captures every planned probe at its press position", "[daemon][run]") {
  RigFixture f("clean", 40, 0.0);
  RunEngine engine(f.db);
  ProbePlan plan;
  const auto run_id = engine.CreateRun(f.config, &plan);
  REQUIRE(plan.probes.size() >= 10);
  const RunReport report = engine.Execute(run_id);
  CHECK(report.outcome == RunOutcome::kDone);
  CHECK(report.counts.captured == static_cast<std::int64_t>(plan.probes.size()));
  CHECK(report.counts.failed == 0);
  CheckCommitted(f, run_id);
  RunDatabase db(f.db);
  CHECK(db.GetRun(run_id)->state == RunState::kDone);
  CHECK(db.ListFrames(run_id, FrameKind::kReference).size() >= 1);
  // A finished run cannot be executed again.
  CHECK_THROWS_WITH(engine.Execute(run_id), Catch::Contains("already done"));
}

TEST_CASE("stop, pause and cancel finish the current probe and leave the run consistent",
          "[daemon][run]") {
  RigFixture f("stop", 40, 0.0);
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  AtProbe(engine, 5, [&] { engine.RequestStop(); });
  RunReport report = engine.Execute(run_id);
  CHECK(report.outcome == RunOutcome::kStopped);
  const auto stopped_at = report.counts.captured;
  CHECK(stopped_at >= 5);
  {
    RunDatabase db(f.db);
    CHECK(db.GetRun(run_id)->state == RunState::kInterrupted);
  }
  CheckCommitted(f, run_id);

  AtProbe(engine, stopped_at + 3, [&] { engine.RequestPause(); });
  report = engine.Execute(run_id);
  CHECK(report.outcome == RunOutcome::kPaused);
  CHECK(report.counts.captured >= stopped_at + 3);
  CheckCommitted(f, run_id);

  AtProbe(engine, report.counts.captured + 2, [&] { engine.RequestCancel(); });
  report = engine.Execute(run_id);
  CHECK(report.outcome == RunOutcome::kCancelled);
  CheckCommitted(f, run_id);
  RunDatabase db(f.db);
  CHECK(db.GetRun(run_id)->state == RunState::kCancelled);
}

TEST_CASE("a finish request ends the run done and skips what is left of the plan",
          "[daemon][run]") {
  RigFixture f("finish", 40, 0.0);
  RunEngine engine(f.db);
  ProbePlan plan;
  const auto run_id = engine.CreateRun(f.config, &plan);
  REQUIRE(plan.probes.size() >= 20);
  AtProbe(engine, 6, [&] { engine.RequestFinish("converged"); });
  const RunReport report = engine.Execute(run_id);
  CHECK(report.outcome == RunOutcome::kDone);
  CHECK(report.message.find("converged") != std::string::npos);
  CHECK(report.counts.captured >= 6);
  CHECK(report.counts.captured < static_cast<std::int64_t>(plan.probes.size()));
  // Nothing is pending: every probe is captured or skipped, none lost.
  CHECK(report.counts.planned == 0);
  CHECK(report.counts.failed == 0);
  CHECK(report.counts.captured + report.counts.skipped ==
        static_cast<std::int64_t>(plan.probes.size()));
  CheckCommitted(f, run_id);
  RunDatabase db(f.db);
  CHECK(db.GetRun(run_id)->state == RunState::kDone);
  for (const ProbeRecord& p : db.ListProbes(run_id)) {
    if (p.state == ProbeState::kSkipped) CHECK(p.skip_reason == "converged");
  }
  // Parked at the plan's start, as a finished run is.
  CHECK((f.rig->cnc().ReportedPosition() - plan.start_machine).norm() < 0.01);
}

TEST_CASE("resume refuses to continue when the sensor moved", "[daemon][run]") {
  RigFixture f("moved", 40, 0.0);
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  StopAfter(engine, run_id, 8);
  const auto before = RunDatabase(f.db).CountProbes(run_id).captured;

  // Knock the sensor 0.6 mm sideways on the machine bed: a second virtual rig, identical but for
  // the mount, stands in for the disturbed one; the run resumes against it.
  const auto moved_dir = test::FreshDir("moved2");
  SimRigOptions shifted = cli::SimRigOptionsFor(f.config.rig, 7);
  shifted.rig.base_in_machine += Eigen::Vector3d(0.6, 0.0, 0.0);
  VirtualRigOptions options;
  options.rig = shifted;
  options.camera.sensor.seed = 7;
  options.cnc.time_scale = 0.0;
  options.frame_socket = moved_dir / "cam2.sock";
  VirtualRig rig(options);
  const RunReport report = engine.Execute(run_id, {rig.PtyPath(), rig.FrameUri()});
  CHECK(report.outcome == RunOutcome::kFailed);
  CHECK_THAT(report.message, Catch::Contains("sensor has moved"));
  CHECK(RunDatabase(f.db).CountProbes(run_id).captured == before);
  CHECK(RunDatabase(f.db).GetRun(run_id)->state == RunState::kInterrupted);

  // Put back where it was, the same run resumes and finishes. The original controller stands
  // where the first session left it, not where the second sent its tool: the user confirms.
  const RunReport asked = engine.Execute(run_id);
  CHECK(asked.outcome == RunOutcome::kAwaiting);
  CHECK_THAT(asked.message, Catch::Contains("last sent to"));
  CHECK(RunDatabase(f.db).GetRun(run_id)->awaiting == "position");
  SessionOverrides confirm;
  confirm.confirm = "position";
  const RunReport ok = engine.Execute(run_id, confirm);
  CHECK(ok.outcome == RunOutcome::kDone);
  CheckCommitted(f, run_id);
  std::error_code ec;
  std::filesystem::remove_all(moved_dir, ec);
}

// ---- faults: the run survives or stops cleanly with a message; nothing committed is lost ----

namespace {

struct FaultRun {
  RunReport first;
  RunReport final;
  std::int64_t committed_before_fault = -1;
};

// Runs with `inject` fired after `after` committed probes; if the run stops, resumes once.
FaultRun RunWithFault(RigFixture& f, std::int64_t after, const std::function<void()>& inject,
                      double sync_timeout_s = 5.0) {
  f.config.engine.sync_timeout_s = sync_timeout_s;
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  FaultRun out;
  AtProbe(engine, after, [&] {
    out.committed_before_fault = RunDatabase(f.db).CountProbes(run_id).captured;
    inject();
  });
  out.first = engine.Execute(run_id);
  CHECK(out.committed_before_fault >= after);
  // Nothing committed before the fault was lost.
  CHECK(out.first.counts.captured >= out.committed_before_fault);
  CheckCommitted(f, run_id);
  out.final = out.first;
  // A run that stops is resumed, and one that asks is resumed as a user would, having checked
  // what it asked about (a failed run may ask on its resume).
  for (int attempt = 0; attempt < 3 && out.final.outcome != RunOutcome::kDone; ++attempt) {
    CHECK_FALSE(out.final.message.empty());
    SessionOverrides overrides;
    overrides.confirm = RunDatabase(f.db).GetRun(run_id)->awaiting;
    out.final = engine.Execute(run_id, overrides);
    CheckCommitted(f, run_id);
  }
  CHECK(out.final.outcome == RunOutcome::kDone);
  CHECK(out.final.counts.planned == 0);
  return out;
}

}  // namespace

TEST_CASE("fault: bytes dropped on the way to the machine", "[daemon][fault]") {
  RigFixture f("drop", 30, 0.0);
  RunWithFault(f, 4, [&] { f.rig->cnc().DropNextBytes(3); });
}

TEST_CASE("fault: garbled bytes on the way to the machine", "[daemon][fault]") {
  RigFixture f("garble", 30, 0.0);
  RunWithFault(f, 4, [&] { f.rig->cnc().GarbleNextBytes(4); });
}

TEST_CASE("fault: garbled replies from the machine", "[daemon][fault]") {
  RigFixture f("garble-reply", 30, 0.0);
  RunWithFault(f, 4, [&] { f.rig->cnc().GarbleNextBytes(6, FaultDirection::kCncToHost); });
}

TEST_CASE("fault: the machine stalls its replies for a while", "[daemon][fault]") {
  RigFixture f("stall", 30, 0.0);
  const FaultRun r =
      RunWithFault(f, 4, [&] { f.rig->cnc().StallReplies(std::chrono::milliseconds(1500)); });
  CHECK(r.first.outcome == RunOutcome::kDone);  // shorter than the sync timeout: just slower
}

namespace {

std::string Events(const RigFixture& f) {
  std::string all;
  for (const EventRecord& e : RunDatabase(f.db).ListEvents(1, 0, 10000)) all += e.message + "\n";
  return all;
}

}  // namespace

// With the default sync timeout (120 s): a lost line or reply must not cost it. Noticed once the
// controller stands idle with the line unanswered; the recovery finds the tool on the path sent.
TEST_CASE("fault: a reply lost on the line is noticed when the controller stands idle",
          "[daemon][fault]") {
  RigFixture f("lost-reply", 30, 0.0);
  const FaultRun r = RunWithFault(
      f, 4, [&] { f.rig->cnc().LoseNextReply(); }, 120.0);
  CHECK(r.first.outcome == RunOutcome::kDone);
  CHECK(r.first.recoveries == 1);
  const std::string events = Events(f);
  INFO(events);
  CHECK_THAT(events, Catch::Contains("unanswered: a line or its reply was lost"));
  CHECK_THAT(events, !Catch::Contains("no reply within"));
}

TEST_CASE("fault: a garbled reply is noticed as lost, not waited for", "[daemon][fault]") {
  RigFixture f("garbled-ok", 30, 0.0);
  // "ok\r\n" made unreadable: what a bit flip in the 'o' or 'k' gives.
  const FaultRun r = RunWithFault(
      f, 4, [&] { f.rig->cnc().LoseNextReply("o\x0b\r\n"); }, 120.0);
  CHECK(r.first.outcome == RunOutcome::kDone);
  const std::string events = Events(f);
  INFO(events);
  // Which line's reply it was (a retract's, sent without waiting, or the sync's) decides whether
  // the unreadable line came before or after the wait began: the message says either.
  CHECK_THAT(events, Catch::Contains("unanswered: a reply was lost (the serial line brought 1 "
                                     "unreadable") ||
                         Catch::Contains("unanswered: a line or its reply was lost"));
  CHECK_THAT(events, !Catch::Contains("no reply within"));
}

TEST_CASE("fault: a feed hold the run did not ask for stops it, and its resume ends the hold",
          "[daemon][fault]") {
  RigFixture f("hold", 30, 0.0);
  const FaultRun r = RunWithFault(
      f, 4, [&] { f.rig->cnc().FeedHoldPin(); }, 120.0);
  CHECK(r.first.outcome == RunOutcome::kFailed);
  CHECK_THAT(r.first.message, Catch::Contains("feed hold") && Catch::Contains("`resume`"));
  CHECK(r.final.outcome == RunOutcome::kDone);
  const std::string events = Events(f);
  INFO(events);
  CHECK_THAT(events, Catch::Contains("stood in a feed hold: a soft reset ended it"));
  CHECK_THAT(events, !Catch::Contains("no reply within"));
}

TEST_CASE("fault: corrupt and dropped camera frames are left out, never averaged into a press",
          "[daemon][fault]") {
  RigFixture f("frames", 60, 0.0);
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  int injected = 0;
  engine.SetProgressCallback([&](const RunProgress& p) {
    if (p.counts.captured >= 3 * (injected + 1) && injected < 8) {
      ++injected;
      f.rig->CorruptNextFrames(1 + injected % 2);
      f.rig->DropNextFrames(injected % 3);
    }
  });
  const RunReport report = engine.Execute(run_id);
  CHECK(report.outcome == RunOutcome::kDone);
  CHECK(injected == 8);
  CHECK(f.rig->FramesCorrupted() >= 8);
  CheckCommitted(f, run_id);  // a press with a damaged frame in it would be unverifiable
  CHECK_THAT(Events(f), Catch::Contains("left out: they disagreed with the others"));
}

TEST_CASE("fault: USB unplug, the controller comes back under another name", "[daemon][fault]") {
  RigFixture f("unplug", 30, 0.0, /*symlink=*/true);
  const std::string before = f.rig->PtyPath();
  UnplugOptions unplug;
  unplug.replug_after = std::chrono::milliseconds(500);
  const FaultRun r = RunWithFault(f, 4, [&] { f.rig->cnc().Unplug(unplug); });
  CHECK(f.rig->PtyPath() != before);
  // Reconnected; the board lost power with the cable, so its position is lost: re-homed and
  // carried on when the tool was clear of the gel, or stopped to ask (without moving) when it
  // may have been in it.
  CHECK((r.first.outcome == RunOutcome::kDone || r.first.outcome == RunOutcome::kAwaiting));
  if (r.first.outcome == RunOutcome::kAwaiting) {
    CHECK_THAT(r.first.message, Catch::Contains("in or near the gel"));
  }
  CHECK(r.first.recoveries >= 1);
}

TEST_CASE("fault: hard-limit alarm in the middle of a move stops the run cleanly",
          "[daemon][fault]") {
  RigFixture f("alarm", 30, 0.0);
  const FaultRun r = RunWithFault(f, 4, [&] { f.rig->cnc().RaiseAlarmDuringNextMove(1, 0.5); });
  CHECK(r.first.outcome == RunOutcome::kFailed);
  CHECK_THAT(r.first.message, Catch::Contains("ALARM:1"));
}

TEST_CASE("fault: an abort resets the controller and loses its position", "[daemon][fault]") {
  RigFixture f("lostpos", 30, 0.0);
  const FaultRun r = RunWithFault(f, 4, [&] {
    f.rig->cnc().LosePositionOnReset(true);
    f.rig->cnc().RaiseAlarmDuringNextMove(3, 0.3);
  });
  CHECK(r.final.outcome == RunOutcome::kDone);
}

// ---- storage faults: a clear error, the run stops resumable, nothing committed is lost ----

namespace {

// Resumes the run with a fresh engine as a user would (confirming what it asks about), at most
// three times; the last session's report.
RunReport ResumeUntilDone(RigFixture& f, std::int64_t run_id) {
  RunEngine engine(f.db);
  RunReport r;
  for (int attempt = 0; attempt < 3 && r.outcome != RunOutcome::kDone; ++attempt) {
    SessionOverrides overrides;
    overrides.confirm = RunDatabase(f.db).GetRun(run_id)->awaiting;
    r = engine.Execute(run_id, overrides);
  }
  return r;
}

}  // namespace

TEST_CASE("storage: a full disk stops the run naming it and the run resumes once there is room",
          "[daemon][storage]") {
  RigFixture f("diskfull", 60, 0.0);
  std::int64_t run_id = 0;
  {
    RunEngine engine(f.db);
    run_id = engine.CreateRun(f.config);
  }
  // The disk fills a few frames into the acquisition: the cap is the file's pages so far plus
  // room for a few press frames (SQLite's PRAGMA max_page_count, as a full disk answers).
  RunDatabaseOptions capped;
  capped.max_page_count = static_cast<std::int64_t>(std::filesystem::file_size(f.db) / 16384) + 100;
  std::string error;
  {
    RunEngine full(f.db, capped);
    try {
      const RunReport r = full.Execute(run_id);
      CHECK(r.outcome != RunOutcome::kDone);
      error = r.message;
    } catch (const StorageError& e) {
      error = e.what();
    }
  }
  INFO(error);
  CHECK_THAT(error, Catch::Contains("disk full"));
  CHECK_THAT(error, Catch::Contains(f.db.filename().string()));
  const std::int64_t before = RunDatabase(f.db).CountProbes(run_id).captured;
  CHECK(before > 0);
  CheckCommitted(f, run_id);
  // Room again: the run resumes where it stopped and finishes.
  const RunReport r = ResumeUntilDone(f, run_id);
  CHECK(r.outcome == RunOutcome::kDone);
  CHECK(r.counts.planned == 0);
  CHECK(r.counts.captured > before);
  CheckCommitted(f, run_id);
}

TEST_CASE("storage: a corrupt database page is an error naming the file and a backup resumes",
          "[daemon][storage]") {
  RigFixture f("corrupt", 40, 0.0);
  std::int64_t run_id = 0;
  {
    RunEngine engine(f.db);
    run_id = engine.CreateRun(f.config);
    StopAfter(engine, run_id, 5);
  }
  const std::int64_t before = RunDatabase(f.db).CountProbes(run_id).captured;
  const std::filesystem::path backup = f.dir / "backup.db";
  std::filesystem::copy_file(f.db, backup);
  {
    // The schema's page (the first, after SQLite's 100-byte header) overwritten with garbage.
    std::fstream file(f.db, std::ios::in | std::ios::out | std::ios::binary);
    file.seekp(100);
    const std::string garbage(4000, '\xa5');
    file.write(garbage.data(), static_cast<std::streamsize>(garbage.size()));
  }
  std::string error;
  try {
    RunEngine engine(f.db);
    const RunReport r = engine.Execute(run_id);
    error = r.message;
    CHECK(r.outcome != RunOutcome::kDone);
  } catch (const std::exception& e) {
    error = e.what();
  }
  INFO(error);
  CHECK_THAT(error, Catch::Contains(f.db.string()));
  CHECK_THAT(error, Catch::Contains("malformed") || Catch::Contains("corrupt") ||
                        Catch::Contains("not a database"));
  // The user restores the backup: the run resumes from it and finishes.
  std::filesystem::copy_file(backup, f.db, std::filesystem::copy_options::overwrite_existing);
  const RunReport r = ResumeUntilDone(f, run_id);
  CHECK(r.outcome == RunOutcome::kDone);
  CHECK(r.counts.captured > before);
  CheckCommitted(f, run_id);
}

TEST_CASE("the engine runs on its own thread and can be stopped from another", "[daemon][run]") {
  RigFixture f("thread", 40, 0.0);
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  engine.Start(run_id);
  CHECK(engine.Running());
  CHECK_THROWS_AS(engine.Start(run_id), std::logic_error);
  test::WaitUntil([&] { return engine.Progress().counts.captured >= 3; }, std::chrono::seconds(30));
  engine.RequestStop();
  const RunReport report = engine.Wait();
  CHECK_FALSE(engine.Running());
  CHECK(report.outcome == RunOutcome::kStopped);
  CHECK(report.counts.captured >= 3);
  CheckCommitted(f, run_id);
}
