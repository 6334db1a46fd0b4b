// Runs on a virtual Marlin printer (issue 34): the engine drives it through the Machine interface
// exactly as it drives GRBL, and each fault a printer's serial line and board bring (a checksum
// error, a lost line or ok, a reboot on open and mid-run, a halt, a kill mid-press) ends done or
// asks, with every committed frame taken at its press point.

#include <catch2/catch.hpp>

#include <chrono>
#include <set>
#include <string>
#include <vector>

#include "cli/sim_args.h"
#include "gcode/marlin_machine.h"
#include "gcode/probe_program.h"
#include "rig_fixture.h"
#include "storage/run_database.h"

using namespace gs360;
using namespace std::chrono_literals;
using Catch::Contains;
using gs360::test::AtProbe;
using gs360::test::RigFixture;
using gs360::test::RunEvents;
using gs360::test::StopAfter;

namespace {

void Printer(VirtualRigOptions& o) {
  o.cnc.firmware = CncFirmware::kMarlin;
}

// The built-in rig on an Ender-3-class printer's bed (cli/sim_args.h).
RigFixture PrinterFixture(const std::string& name, int candidates,
                          const std::function<void(VirtualRigOptions&)>& tweak = Printer) {
  return RigFixture(name, candidates, 0.0, false, tweak,
                    [](RunConfig& c) { cli::ApplyPrinterDefaults(&c); });
}

void CheckMarlinCommitted(RigFixture& f, std::int64_t run_id) {
  RunDatabaseOptions ro;
  ro.read_only = true;
  RunDatabase db(f.db, ro);
  const auto captured = db.ListCapturedProbes(run_id);
  std::set<std::int64_t> probes;
  for (const auto& fr : db.ListFrames(run_id, FrameKind::kPress)) {
    REQUIRE(fr.probe_id);
    CHECK(probes.insert(*fr.probe_id).second);  // never two frames for one probe
  }
  CHECK(probes.size() == captured.size());
  const cli::CaptureTruth truth = cli::CheckCapturesAgainstTruth(*f.rig, db, run_id);
  CHECK(truth.frames == static_cast<int>(captured.size()));
  CHECK(truth.off_target == 0);
  CHECK(truth.unverified == 0);
  CHECK(truth.max_reported_error_mm < 0.002);  // M114 R: the steppers' position, 3 decimals
}

// The fault after `after` committed probes; the run resumed (confirming what it asks, as a user
// who checked) until done. The first session's report.
RunReport RunMarlinWithFault(RigFixture& f, std::int64_t after,
                             const std::function<void()>& inject) {
  f.config.engine.sync_timeout_s = 10.0;
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  AtProbe(engine, after, inject);
  const RunReport first = engine.Execute(run_id);
  CheckMarlinCommitted(f, run_id);
  RunReport last = first;
  for (int attempt = 0; attempt < 3 && last.outcome != RunOutcome::kDone; ++attempt) {
    SessionOverrides overrides;
    overrides.confirm = RunDatabase(f.db).GetRun(run_id)->awaiting;
    last = engine.Execute(run_id, overrides);
    CheckMarlinCommitted(f, run_id);
  }
  CHECK(last.outcome == RunOutcome::kDone);
  CHECK(last.counts.planned == 0);
  return first;
}

// A terminal on the printer: trusts its position, sends `lines` (Marlin's own), waits for each.
void MarlinByHand(RigFixture& f, const std::vector<std::string>& lines) {
  MarlinMachine machine(
      [path = f.rig->PtyPath()] { return OpenTermiosTransport(path, TransportOptions{}); });
  machine.Connect();
  machine.Unlock();
  machine.MarkPositionTrusted();
  for (const std::string& line : lines) {
    const MachineReply r = machine.Send(line).Wait(10s);
    INFO(line << ": " << r.Describe());
    REQUIRE(r.Ok());
  }
  REQUIRE(machine.WaitIdle(10s) == MachineWaitResult::kIdle);
}

}  // namespace

TEST_CASE("marlin: a run on a printer captures every probe at its press point",
          "[daemon][marlin]") {
  RigFixture f = PrinterFixture("marlin-clean", 40);
  RunEngine engine(f.db);
  ProbePlan plan;
  const auto run_id = engine.CreateRun(f.config, &plan);
  REQUIRE(plan.probes.size() >= 10);
  const RunReport report = engine.Execute(run_id);
  CHECK(report.outcome == RunOutcome::kDone);
  CHECK(report.counts.captured >= static_cast<std::int64_t>(plan.probes.size()) - 2);
  CheckMarlinCommitted(f, run_id);
  const std::string events = RunEvents(f, run_id);
  CHECK_THAT(events, Contains("connected to Marlin 2.1") && Contains("Virtual Ender-3"));
  // A board that does not reboot on open: its MPos taken (a fresh run, machine.home), then
  // homed from above the sensor (G28 moves X and Y first).
  CHECK_THAT(events, !Contains("rebooted"));
  CHECK_THAT(events, Contains("raising Z") && Contains("before homing"));
  CHECK(f.rig->cnc().Stats().boots == 1);
}

TEST_CASE("marlin fault: a garbled line is resent, a lost line or ok retried, no recovery",
          "[daemon][marlin]") {
  SECTION("a checksum error") {
    RigFixture f = PrinterFixture("marlin-garble", 30);
    const RunReport r = RunMarlinWithFault(f, 4, [&] { f.rig->cnc().GarbleNextBytes(3); });
    CHECK(r.outcome == RunOutcome::kDone);
    CHECK(r.recoveries == 0);
  }
  SECTION("bytes lost on the way to the printer") {
    RigFixture f = PrinterFixture("marlin-drop", 30);
    const RunReport r = RunMarlinWithFault(f, 4, [&] { f.rig->cnc().DropNextBytes(40); });
    CHECK(r.outcome == RunOutcome::kDone);
    CHECK(r.recoveries == 0);
  }
  SECTION("a lost ok") {
    RigFixture f = PrinterFixture("marlin-lost-ok", 30);
    const RunReport r = RunMarlinWithFault(f, 4, [&] { f.rig->cnc().LoseNextReply(); });
    CHECK(r.outcome == RunOutcome::kDone);
    CHECK(r.recoveries == 0);
  }
  SECTION("garbled replies") {
    RigFixture f = PrinterFixture("marlin-garble-reply", 30);
    const RunReport r = RunMarlinWithFault(
        f, 4, [&] { f.rig->cnc().GarbleNextBytes(6, FaultDirection::kCncToHost); });
    CHECK(r.outcome == RunOutcome::kDone);
  }
}

TEST_CASE("marlin: long waits bring busy keep-alives, which are no time-out", "[daemon][marlin]") {
  // Ten machine seconds per wall second and a keep-alive every 0.1 machine s: every M400, dwell
  // and homing prints them, in hundreds, among the replies; none is taken for an ok, none ends a
  // wait, and nothing needs recovering.
  RigFixture f = PrinterFixture("marlin-busy", 16, [](VirtualRigOptions& o) {
    o.cnc.firmware = CncFirmware::kMarlin;
    o.cnc.time_scale = 10.0;
    o.cnc.marlin.keepalive_s = 0.1;
  });
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  const RunReport r = engine.Execute(run_id);
  CHECK(r.outcome == RunOutcome::kDone);
  CHECK(r.recoveries == 0);
  CheckMarlinCommitted(f, run_id);
  INFO("keep-alives: " << f.rig->cnc().Stats().keepalives);
  CHECK(f.rig->cnc().Stats().keepalives >= 20);
}

TEST_CASE("marlin fault: a reboot mid-run loses the position: homed when clear, else asked",
          "[daemon][marlin]") {
  RigFixture f = PrinterFixture("marlin-reboot", 30);
  const RunReport r = RunMarlinWithFault(f, 4, [&] { f.rig->cnc().PowerCycle(); });
  CHECK((r.outcome == RunOutcome::kDone || r.outcome == RunOutcome::kAwaiting));
  if (r.outcome == RunOutcome::kAwaiting) CHECK_THAT(r.message, Contains("in or near the gel"));
  CHECK_THAT(RunEvents(f, 1), Contains("the printer rebooted"));
  CHECK(f.rig->cnc().Stats().boots >= 2);
}

TEST_CASE("marlin: a board that reboots when its port opens is homed by each session",
          "[daemon][marlin]") {
  RigFixture f = PrinterFixture("marlin-dtr", 30, [](VirtualRigOptions& o) {
    o.cnc.firmware = CncFirmware::kMarlin;
    o.cnc.reset_on_open = true;
    o.cnc.boot_delay = 200ms;
  });
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  // Rebooted by the open, nothing on record of where the tool is: G28 would sweep X and Y at an
  // unknown height, so it asks.
  const RunReport asked = engine.Execute(run_id);
  REQUIRE(asked.outcome == RunOutcome::kAwaiting);
  CHECK_THAT(asked.message, Contains("moves X and Y first") && Contains("Nothing was moved") &&
                                Contains("--confirm position"));
  CHECK((f.rig->cnc().TruePositionNow() - f.config.plan.start_machine).norm() < 1e-9);
  // Confirmed (the tool is above the sensor): homes, runs; stopped after 5 probes.
  AtProbe(engine, 5, [&engine] { engine.RequestStop(); });
  SessionOverrides confirm;
  confirm.confirm = "position";
  REQUIRE(engine.Execute(run_id, confirm).outcome == RunOutcome::kStopped);
  engine.SetProgressCallback({});
  // The next session's reboot finds the motion on record: raised above it, homed, done.
  const RunReport resumed = engine.Execute(run_id);
  CHECK(resumed.outcome == RunOutcome::kDone);
  CheckMarlinCommitted(f, run_id);
  const std::string events = RunEvents(f, run_id);
  CHECK_THAT(events, Contains("rebooted when the port opened") && Contains("raising Z"));
  CHECK(f.rig->cnc().Stats().boots >= 4);  // power-up, then once per session
}

TEST_CASE("marlin fault: a halt mid-move stops the run, and once reset it resumes",
          "[daemon][marlin]") {
  RigFixture f = PrinterFixture("marlin-halt", 30);
  RunEngine engine(f.db);
  const auto run_id = engine.CreateRun(f.config);
  AtProbe(engine, 4, [&] { f.rig->cnc().RaiseAlarmDuringNextMove(1, 0.5); });
  const RunReport halted = engine.Execute(run_id);
  CHECK(halted.outcome == RunOutcome::kFailed);
  CHECK_THAT(halted.message, Contains("halted") && Contains("kill() called"));
  engine.SetProgressCallback({});
  // The user resets the printer (its reset button) and resumes, confirming what it asks.
  f.rig->cnc().PowerCycle();
  RunReport r = engine.Execute(run_id);
  for (int i = 0; i < 2 && r.outcome != RunOutcome::kDone; ++i) {
    SessionOverrides confirm;
    confirm.confirm = RunDatabase(f.db).GetRun(run_id)->awaiting;
    r = engine.Execute(run_id, confirm);
  }
  CHECK(r.outcome == RunOutcome::kDone);
  CheckMarlinCommitted(f, run_id);
}

TEST_CASE("marlin: a run killed mid-press backs out along the probe's axis before any travel",
          "[daemon][marlin]") {
  RigFixture f = PrinterFixture("marlin-midpress", 30);
  RunEngine engine(f.db);
  ProbePlan plan;
  const auto run_id = engine.CreateRun(f.config, &plan);
  StopAfter(engine, run_id, 3);
  engine.SetProgressCallback({});
  const auto next = RunDatabase(f.db).NextPendingProbe(run_id, 3);
  REQUIRE(next);
  const PlannedProbe& p = plan.probes.at(static_cast<std::size_t>(next->plan_index));
  // What a SIGKILL during its press leaves: the ball 1 mm in the gel, the motion recorded.
  MarlinByHand(f, {"G90", MachineMoveLine(p.approach_machine, 3000.0),
                   MachineMoveLine(p.press_machine, 60.0)});
  RunDatabase(f.db).SetCommandedPath(
      run_id, std::vector<Eigen::Vector3d>{p.approach_machine, p.press_machine});

  const RunReport resumed = engine.Execute(run_id);
  CHECK(resumed.outcome == RunOutcome::kDone);
  CHECK_THAT(RunEvents(f, run_id),
             Contains("backed out along probe " + std::to_string(p.plan_index) + "'s axis"));
  CheckMarlinCommitted(f, run_id);
}
