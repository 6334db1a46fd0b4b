// Safe on a real machine (docs/running.md, "Faults"): the run never trusts a position it has not
// verified, backs out of the gel along the probe's axis, speaks grblHAL's dialect, discards an
// earlier session's bytes, checks the controller's travel, and fails presses that left no mark.
// Each case drives the engine against the virtual CNC on a pty, as a lab's controller would be.

#include <catch2/catch.hpp>

#include <chrono>
#include <set>
#include <string>
#include <thread>

#include "gcode/grbl_client.h"
#include "gcode/probe_program.h"
#include "rig_fixture.h"
#include "storage/frame_codec.h"
#include "storage/run_database.h"
#include "tests/storage/storage_test_util.h"
#include "tests/wait.h"

using namespace gs360;
using namespace std::chrono_literals;
using Catch::Contains;
using gs360::test::AtProbe;
using gs360::test::RigFixture;
using gs360::test::RunEvents;
using gs360::test::StopAfter;

namespace {

// Talks to the virtual controller as a user at a terminal would (jogging by hand): trusts its
// position and sends `lines`, waiting for each; then lets go of the port.
void ByHand(RigFixture& f, const std::vector<std::string>& lines) {
  GrblClientOptions o;
  o.status_poll_interval = 0ms;
  auto client = GrblClient::ForUri(f.rig->PtyPath(), TransportOptions{}, o);
  client->Connect();
  client->MarkPositionTrusted();
  for (const std::string& line : lines) {
    const GrblReply r = client->Send(line).Wait(10s);
    INFO(line << ": " << r.Describe());
    REQUIRE(r.Ok());
  }
  REQUIRE(client->WaitIdle(10s) == GrblWaitResult::kIdle);
}

std::string MoveTo(const Eigen::Vector3d& p) {
  return MachineMoveLine(p);
}

void TweakNoHoming(VirtualRigOptions& o) {
  o.cnc.settings.homing_enable = false;  // $22=0: boots Idle at MPos 0,0,0 wherever it stands
  o.cnc.settings.soft_limits = false;    // GRBL refuses soft limits without homing
}

// What a SIGKILL during probe k's press leaves, after a few probes: the controller finished the
// lines it had, the ball sits 1 mm in the gel, and the database holds the motion last sent.
// Returns probe k.
PlannedProbe KilledMidPress(RigFixture& f, RunEngine& engine, const ProbePlan& plan,
                            std::int64_t run_id) {
  StopAfter(engine, run_id, 3);
  const auto next = RunDatabase(f.db).NextPendingProbe(run_id, 3);
  REQUIRE(next);
  const PlannedProbe& p = plan.probes.at(static_cast<std::size_t>(next->plan_index));
  ByHand(f, {MoveTo(p.approach_machine), MoveTo(p.press_machine)});
  RunDatabase(f.db).SetCommandedPath(
      run_id, std::vector<Eigen::Vector3d>{p.approach_machine, p.press_machine});
  return p;
}

// Every committed probe was pressed once: no attempt was spent on a fault of the machine.
void CheckOneAttemptEach(const RigFixture& f, std::int64_t run_id) {
  RunDatabase db(f.db);
  for (const ProbeRecord& p : db.ListProbes(run_id, ProbeState::kCaptured)) {
    INFO("probe " << p.plan_index);
    CHECK(p.attempts == 1);
  }
}

}  // namespace

TEST_CASE("without homing: a run asks before its first move and after a controller restart",
          "[daemon][safety]") {
  RigFixture f("nohome", 30, 0.0, false, TweakNoHoming);
  f.config.machine.home = false;
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);

  // Nothing says where the tool is: the user checks MPos against the machine and confirms.
  const RunReport first = engine.Execute(run_id);
  REQUIRE(first.outcome == RunOutcome::kAwaiting);
  CHECK_THAT(first.message, Contains("homing is off") && Contains("--confirm position"));
  CHECK(f.rig->cnc().TruePositionNow().norm() < 1e-9);  // not moved
  CHECK(RunDatabase(f.db).GetRun(run_id)->awaiting == "position");
  CHECK(RunDatabase(f.db).GetRun(run_id)->state == RunState::kCreated);

  SessionOverrides confirm;
  confirm.confirm = "position";
  AtProbe(engine, 5, [&] { f.rig->cnc().PowerCycle(); });
  const RunReport restarted = engine.Execute(run_id, confirm);
  // The board came back believing MPos 0,0,0 wherever the tool was (and, having booted while
  // lines were on their way, may have run them from there): the run stops, moving nothing more.
  REQUIRE(restarted.outcome == RunOutcome::kAwaiting);
  CHECK_THAT(restarted.message, (Contains("reports MPos (0.000, 0.000, 0.000)") ||
                                 Contains("restarted and then executed")) &&
                                    Contains("Nothing was moved"));
  const Eigen::Vector3d stood = f.rig->cnc().TruePositionNow();
  const Eigen::Vector3d believed = f.rig->cnc().ReportedPosition();
  CHECK((stood - believed).norm() > 1.0);  // MPos is wrong: any move now would be a crash
  CHECK_THAT(RunEvents(f, run_id), !Contains("$X"));
  CHECK(RunDatabase(f.db).CountProbes(run_id).failed == 0);

  // A confirmation that answers another question is no confirmation.
  SessionOverrides wrong;
  wrong.confirm = "sensor";
  CHECK(engine.Execute(run_id, wrong).outcome == RunOutcome::kAwaiting);
  CHECK((f.rig->cnc().TruePositionNow() - stood).norm() < 1e-9);

  // The user makes MPos true as a lab without homing does: jogs the tool to the machine's origin
  // mark and restarts the board there. Then confirms; the run goes on to the end.
  const Eigen::Vector3d origin = believed - stood;  // where MPos must go for the tool to be at 0
  ByHand(f, {MoveTo(origin + Eigen::Vector3d(0, 0, 40)), MoveTo(origin)});
  f.rig->cnc().PowerCycle();
  const RunReport done = engine.Execute(run_id, confirm);
  CHECK(done.outcome == RunOutcome::kDone);
  CHECK(RunDatabase(f.db).GetRun(run_id)->awaiting.empty());
  const cli::CaptureTruth truth = cli::CheckCapturesAgainstTruth(*f.rig, RunDatabase(f.db), run_id);
  CHECK(truth.off_target == 0);
  CHECK(truth.max_reported_error_mm < 0.002);
}

TEST_CASE("grblHAL's homing lock without homing: asked, unlocked only when confirmed and logged",
          "[daemon][safety]") {
  RigFixture f("hal", 30, 0.0, false,
               [](VirtualRigOptions& o) { o.cnc.firmware = CncFirmware::kGrblHal; });
  f.config.machine.home = false;
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  const RunReport asked = engine.Execute(run_id);
  REQUIRE(asked.outcome == RunOutcome::kAwaiting);
  CHECK_THAT(asked.message,
             Contains("ALARM:11") && Contains("Homing required") && Contains("homing is off"));
  CHECK_THAT(RunEvents(f, run_id), !Contains("$X"));
  // Confirmed: the unlock is said out loud, and grblHAL refuses it until homed (error:46): the
  // message says what to change.
  SessionOverrides confirm;
  confirm.confirm = "position";
  CHECK_THROWS_WITH(engine.Execute(run_id, confirm),
                    Contains("error:46") && Contains("home = true"));
  CHECK_THAT(RunEvents(f, run_id), Contains("unlocking the controller ($X)"));
  CHECK(f.rig->cnc().TruePositionNow().norm() < 1e-9);
  CHECK(RunDatabase(f.db).GetRun(run_id)->state != RunState::kRunning);

  // With homing on, the same controller runs to the end.
  f.config.machine.home = true;
  const auto homed = engine.CreateRun(f.config);
  CHECK(engine.Execute(homed).outcome == RunOutcome::kDone);
}

TEST_CASE("a run killed mid-press backs out along the probe's axis before any travel",
          "[daemon][safety]") {
  RigFixture f("midpress", 30, 0.0);
  RunEngine engine(f.db);
  ProbePlan plan;
  const auto run_id = engine.CreateRun(f.config, &plan);
  const PlannedProbe p = KilledMidPress(f, engine, plan, run_id);

  const RunReport resumed = engine.Execute(run_id);
  CHECK(resumed.outcome == RunOutcome::kDone);
  CHECK_THAT(RunEvents(f, run_id),
             Contains("backed out along probe " + std::to_string(p.plan_index) + "'s axis"));
  CheckOneAttemptEach(f, run_id);
  CHECK(RunDatabase(f.db).CountProbes(run_id).failed <= 2);  // fin-hidden probes, not this one
}

TEST_CASE("a controller restarted while the ball may be in the gel is not homed without asking",
          "[daemon][safety]") {
  RigFixture f("gelhome", 30, 0.0);
  RunEngine engine(f.db);
  ProbePlan plan;
  const auto run_id = engine.CreateRun(f.config, &plan);
  const PlannedProbe p = KilledMidPress(f, engine, plan, run_id);
  f.rig->cnc().PowerCycle();  // boots in Alarm (homing lock), MPos 0,0,0

  const RunReport asked = engine.Execute(run_id);
  REQUIRE(asked.outcome == RunOutcome::kAwaiting);
  CHECK_THAT(asked.message, Contains("in or near the gel") && Contains("Nothing was moved"));
  CHECK((f.rig->cnc().TruePositionNow() - p.press_machine).norm() < 0.01);
  // The user lifts the tool out by hand (here: unlocks, and with soft limits off, since MPos
  // is wrong, moves up 20 mm) and confirms: it homes.
  ByHand(f, {"$X", "$20=0", "G91 G0 Z20", "G90", "$20=1"});
  SessionOverrides confirm;
  confirm.confirm = "position";
  CHECK(engine.Execute(run_id, confirm).outcome == RunOutcome::kDone);
}

TEST_CASE("a session killed while it homes: the next trusts the finished cycle, not a stray move",
          "[daemon][safety]") {
  RigFixture f("homekill", 30, 0.0);
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  StopAfter(engine, run_id, 3);
  engine.SetProgressCallback({});
  // What the killed session's $H did: the machine homed, away from every point of the path.
  ByHand(f, {"$H"});
  SECTION("the $H was recorded: resumed, said in the events") {
    RunDatabase(f.db).MarkHomingSent(run_id);
    CHECK(engine.Execute(run_id).outcome == RunOutcome::kDone);
    CHECK_THAT(RunEvents(f, run_id), Contains("finished the homing cycle sent before"));
    CheckOneAttemptEach(f, run_id);
  }
  SECTION("without it the same position is a stray move: asked") {
    const RunReport asked = engine.Execute(run_id);
    CHECK(asked.outcome == RunOutcome::kAwaiting);
    CHECK_THAT(asked.message, Contains("mm from any point of that motion"));
  }
}

TEST_CASE("a reset at the bottom of a press is recovered without spending an attempt",
          "[daemon][safety]") {
  RigFixture f("dwellreset", 30, 0.0);
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  AtProbe(engine, 4, [&] { f.rig->cnc().ResetDuringNextDwell(); });
  const RunReport r = engine.Execute(run_id);
  CHECK(r.outcome == RunOutcome::kDone);
  CHECK(r.recoveries >= 1);
  CHECK(f.rig->cnc().Stats().resets >= 1);
  const std::string events = RunEvents(f, run_id);
  CHECK_THAT(events, Contains("position verified") && Contains("backed out along probe"));
  CheckOneAttemptEach(f, run_id);
  RunDatabase db(f.db);
  for (const ProbeRecord& p : db.ListProbes(run_id, ProbeState::kFailed)) {
    CHECK_THAT(p.last_error, Contains("no impression"));  // fin-hidden, never the reset
  }
}

TEST_CASE("an earlier session's bytes on the line are discarded, not taken as replies",
          "[daemon][safety]") {
  RigFixture f("stale", 30, 0.0);
  {
    GrblClientOptions o;
    o.status_poll_interval = 0ms;
    auto earlier = GrblClient::ForUri(f.rig->PtyPath(), TransportOptions{}, o);
    earlier->Connect();
  }
  // Replies the earlier host never read: an ok, an error, a status report with a made-up MPos.
  f.rig->cnc().SendRaw("ok\r\nerror:9\r\n<Idle|MPos:1.000,2.000,3.000|FS:0,0>\r\n");
  test::WaitUntil([&] { return f.rig->cnc().PendingOutputBytes() == 0; }, 1s);
  GrblClientOptions o;
  o.status_poll_interval = 0ms;
  auto client = GrblClient::ForUri(f.rig->PtyPath(), TransportOptions{}, o);
  client->Connect();
  const auto status = client->QueryStatus(2s);
  REQUIRE(status);
  REQUIRE(status->machine_position);
  CHECK(status->machine_position->norm() < 1e-9);  // the controller's own report, not the stale one
  CHECK(client->Stats().replies == 2);             // $I and $$ only
  CHECK(client->Send("$I").Wait(5s).Ok());
}

TEST_CASE("an earlier session's replies arriving after the port opens are not this one's",
          "[daemon][safety]") {
  RigFixture f("stalelate", 30, 0.0);
  GrblClientOptions o;
  o.status_poll_interval = 0ms;
  // The earlier session: it took the controller's power-up welcome, so none greets the next.
  GrblClient::ForUri(f.rig->PtyPath(), TransportOptions{}, o)->Connect();
  auto client = GrblClient::ForUri(f.rig->PtyPath(), TransportOptions{}, o);
  // While the client waits for a welcome that a controller without a reset never sends, what an
  // earlier host asked for arrives: its ok and a status report with a made-up position.
  std::thread late([&] {
    test::WaitUntil([&] { return f.rig->cnc().HostAttached(); }, 5s);
    // The scenario: they come half a second after the port opened, after the client read what
    // was already waiting (well inside its 2.5 s wait for a welcome).
    std::this_thread::sleep_for(500ms);
    f.rig->cnc().SendRaw("ok\r\n<Idle|MPos:1.000,2.000,3.000|FS:0,0>\r\n");
  });
  client->Connect();
  late.join();
  CHECK(client->StrayRepliesSinceWelcome() == 0);  // not taken for lines run after a restart
  const auto status = client->QueryStatus(2s);
  REQUIRE(status);
  REQUIRE(status->machine_position);
  CHECK(status->machine_position->norm() < 1e-9);
  CHECK(client->Send("$I").Wait(5s).Ok());
}

TEST_CASE("a controller whose travel does not reach the plan is refused at connect",
          "[daemon][safety]") {
  RigFixture f("travel", 30, 0.0, false, [](VirtualRigOptions& o) {
    o.cnc.settings.max_travel_mm = Eigen::Vector3d(300.0, 180.0, 5.0);  // $132 = 5 mm
  });
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  CHECK_THROWS_WITH(engine.Execute(run_id),
                    Contains("$130-$132") && Contains("5.0 mm") && Contains("[plan.machine]"));
  CHECK(f.rig->cnc().TruePositionNow().norm() < 1e-9);
  CHECK(RunDatabase(f.db).CountProbes(run_id).captured == 0);
}

namespace {

// A virtual rig like `f`'s but with its sensor `shift` away on the bed (machine frame, mm).
std::unique_ptr<VirtualRig> ShiftedRig(const RigFixture& f, const Eigen::Vector3d& shift,
                                       const std::string& name) {
  SimRigOptions moved = cli::SimRigOptionsFor(f.config.rig, 7);
  moved.rig.base_in_machine += shift;
  VirtualRigOptions options;
  options.rig = moved;
  options.camera.sensor.seed = 7;
  options.cnc.time_scale = 0.0;
  options.frame_socket = f.dir / (name + ".sock");
  return std::make_unique<VirtualRig>(options);
}

}  // namespace

TEST_CASE("a press that leaves no impression fails and is not pressed again", "[daemon][safety]") {
  RigFixture f("nomark", 30, 0.0);
  f.config.engine.max_attempts = 2;
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  // The sensor is not where the plan says (60 mm off on the bed): every press meets thin air.
  const auto away = ShiftedRig(f, Eigen::Vector3d(60.0, 0.0, 0.0), "away");
  const RunReport r = engine.Execute(run_id, {away->PtyPath(), away->FrameUri(), ""});
  RunDatabase db(f.db);
  const ProbeCounts counts = db.CountProbes(run_id);
  CHECK(counts.captured == 0);
  CHECK(counts.failed == counts.total);
  for (const ProbeRecord& p : db.ListProbes(run_id, ProbeState::kFailed)) {
    CHECK(p.attempts == 1);  // a second press would meet the same air
    CHECK_FALSE(p.retry);
    CHECK_THAT(p.last_error, Contains("no impression") && Contains("Not pressed again"));
  }
  CHECK(r.outcome == RunOutcome::kDone);
}

TEST_CASE("resume asks when the re-pressed probes cannot be compared", "[daemon][safety]") {
  RigFixture f("unverified", 40, 0.0);
  f.config.engine.require_impression = false;  // else the blank re-presses fail outright
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  StopAfter(engine, run_id, 8);
  const auto before = RunDatabase(f.db).CountProbes(run_id).captured;

  // The sensor taken off the bed: a second rig, its sensor 60 mm away, where no press touches.
  const auto away = ShiftedRig(f, Eigen::Vector3d(60.0, 0.0, 0.0), "away");
  const RunReport asked = engine.Execute(run_id, {away->PtyPath(), away->FrameUri(), ""});
  REQUIRE(asked.outcome == RunOutcome::kAwaiting);
  CHECK_THAT(asked.message, Contains("could not be verified") && Contains("--confirm sensor"));
  CHECK(RunDatabase(f.db).GetRun(run_id)->awaiting == "sensor");
  CHECK(RunDatabase(f.db).CountProbes(run_id).captured == before);  // nothing else pressed
}

TEST_CASE("resume re-presses only probes whose stored impression is clear", "[daemon][safety]") {
  RigFixture f("faint", 40, 0.0);
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  StopAfter(engine, run_id, 12);

  // Every stored press frame but three becomes its reference brightened by 8 DN: a faint change
  // over the whole frame, like a probe at a fin's edge under LED drift. Its "impression" centre
  // is the frame's middle, nowhere near where a re-press marks the gel.
  std::vector<std::pair<std::int64_t, EncodedFrame>> faint;
  {
    RunDatabase db(f.db);
    const auto captured = db.ListCapturedProbes(run_id);
    REQUIRE(captured.size() >= 12);
    const std::set<std::size_t> keep = {1, captured.size() / 2 + 2, captured.size() - 3};
    for (std::size_t i = 0; i < captured.size(); ++i) {
      if (keep.count(i)) continue;
      const auto ref = db.NearestReferenceFrame(run_id, captured[i].frame_time);
      REQUIRE(ref);
      cv::Mat drifted;
      db.LoadFrame(ref->id).convertTo(drifted, -1, 1.0, 8.0);
      faint.emplace_back(captured[i].frame_id, EncodeFrame(drifted));
    }
  }
  {
    test::RawDb raw(f.db);
    for (const auto& [id, frame] : faint) {
      raw.ExecWithBlob("UPDATE frames SET png = ?, size = " + std::to_string(frame.png.size()) +
                           ", checksum = '" + BlobChecksum(frame.png) +
                           "' WHERE id = " + std::to_string(id),
                       frame.png);
    }
  }

  const RunReport r = engine.Execute(run_id);
  CHECK(r.outcome == RunOutcome::kDone);
  RunDatabase db(f.db);
  bool matched = false;
  for (const EventRecord& e : db.ListEvents(run_id)) {
    if (e.message.find("3 re-pressed probes match") != std::string::npos) matched = true;
    CHECK_THAT(e.message, !Contains("sensor has moved"));
  }
  CHECK(matched);
}

TEST_CASE("a board that resets when its port opens: each session homes again, nothing is lost",
          "[daemon][safety]") {
  RigFixture f("resetopen", 30, 0.0, false,
               [](VirtualRigOptions& o) { o.cnc.reset_on_open = true; });
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  StopAfter(engine, run_id, 4);
  const auto boots = f.rig->cnc().Stats().boots;
  const auto before = RunDatabase(f.db).CountProbes(run_id).captured;
  // The resume's open restarts the board (MPos 0,0,0, homing lock): the tool was parked clear of
  // the gel at a settled point, so the run homes and goes on.
  const RunReport r = engine.Execute(run_id);
  CHECK(r.outcome == RunOutcome::kDone);
  CHECK(f.rig->cnc().Stats().boots > boots);
  CHECK(RunDatabase(f.db).CountProbes(run_id).captured > before);
  CheckOneAttemptEach(f, run_id);
  const cli::CaptureTruth truth = cli::CheckCapturesAgainstTruth(*f.rig, RunDatabase(f.db), run_id);
  CHECK(truth.off_target == 0);
}
