// The daemon's parts on their own: instance locks, the safety guard, the event hub.

#include <catch2/catch.hpp>

#include <unistd.h>

#include <fstream>
#include <thread>

#include "base/json_reader.h"
#include "daemon/daemon.h"
#include "daemon/daemon_config.h"
#include "daemon/event_hub.h"
#include "daemon/instance_lock.h"
#include "gcode/probe_program.h"
#include "run/calibration_inputs.h"
#include "run/run_engine.h"
#include "run/run_session.h"
#include "run/safety.h"
#include "tests/run/rig_fixture.h"

using namespace gs360;

TEST_CASE("an instance lock is exclusive and names its holder", "[daemon][lock]") {
  const auto dir = test::FreshDir("lock");
  const auto file = dir / "gs360d.lock";
  InstanceLock first = InstanceLock::Acquire(file, "the data folder X", "gs360d pid 1 at URL");
  CHECK(first.Held());
  // A second open of the file (as another process would) cannot take it.
  try {
    InstanceLock::Acquire(file, "the data folder X", "second");
    FAIL("the second lock was granted");
  } catch (const LockHeldError& e) {
    CHECK(e.holder() == "gs360d pid 1 at URL");
    CHECK_THAT(e.what(), Catch::Contains("the data folder X is in use by gs360d pid 1 at URL"));
  }
  first.SetHolder("gs360d pid 1 at http://127.0.0.1:7360");
  try {
    InstanceLock::Acquire(file, "the data folder X", "second");
    FAIL("the second lock was granted");
  } catch (const LockHeldError& e) {
    CHECK(e.holder() == "gs360d pid 1 at http://127.0.0.1:7360");
  }
  first.Release();
  InstanceLock second = InstanceLock::Acquire(file, "the data folder X", "second");
  CHECK(second.Held());
  std::filesystem::remove_all(dir);
}

TEST_CASE("a machine port's lock follows symlinks to the device", "[daemon][lock]") {
  const auto dir = test::FreshDir("portlock");
  std::ofstream(dir / "ttyUSB0") << "";
  std::filesystem::create_symlink(dir / "ttyUSB0", dir / "by-id-cnc");
  CHECK(MachineLockPath((dir / "ttyUSB0").string(), dir) ==
        MachineLockPath((dir / "by-id-cnc").string(), dir));
  CHECK(MachineLockPath("tcp://10.0.0.5:23", dir) != MachineLockPath("tcp://10.0.0.6:23", dir));
  CHECK(MachineLockPath("tcp://10.0.0.5:23", dir).parent_path() == dir);
  std::filesystem::remove_all(dir);
}

TEST_CASE("the safety guard refuses lines outside the limits, naming the limit",
          "[daemon][safety]") {
  RunConfig config;
  const RigGeometry rig = MakeRigGeometry(config.rig);
  auto travel = std::make_shared<TravelPlanner>(rig, config.plan);
  SafetyLimits limits;
  limits.envelope_min = {-250.0, -150.0, -45.0};
  limits.max_feed_mm_per_min = 1000.0;
  limits.max_press_depth = 1.0;
  const SafetyGuard guard(limits, travel, config.rig.ball_radius, config.rig.gel_thickness);
  CHECK(guard.MaxDepth() == 1.0);

  // A press 1.0 mm deep on the wall's outward normal at mid-height passes; 1.5 mm does not.
  const Eigen::Vector3d p(10.0, 0.0, 15.0), n(1.0, 0.0, 0.0);
  const Eigen::Vector3d approach = travel->MachineFromBall(p + n * 3.0);
  const auto press_at = [&](double depth) {
    return MachineMoveLine(travel->MachineFromBall(p + n * (2.0 - depth)), 120.0);
  };
  CHECK_FALSE(guard.CheckLine(press_at(1.0), approach));
  const auto deep = guard.CheckLine(press_at(1.5), approach);
  REQUIRE(deep);
  CHECK_THAT(*deep,
             Catch::Contains("1.500 mm into the gel") && Catch::Contains("limits.max_press_depth"));
  // The envelope, per axis.
  const auto out = guard.CheckLine("G53 G0 X-260.000 Y-90.000 Z-10.000", approach);
  REQUIRE(out);
  CHECK_THAT(*out, Catch::Contains("X -260.000 is below limits.envelope_min.x = -250.000"));
  CHECK(guard.CheckLine("G53 G0 X-100.000 Y-90.000 Z1.000", approach).has_value());
  // Feeds, work coordinates and unknown words.
  CHECK_THAT(*guard.CheckLine("G53 G1 X-100 Y-90 Z-10 F2000", approach),
             Catch::Contains("limits.max_feed_mm_per_min"));
  CHECK_THAT(*guard.CheckLine("G0 X-100 Y-90 Z-10", approach), Catch::Contains("G53"));
  CHECK_THAT(*guard.CheckLine("G53 G0 X-100 Y-90 Z-10 M3", approach), Catch::Contains("M3"));
  // Lines without motion pass.
  CHECK_FALSE(guard.CheckLine("G4 P0.300", approach));
  CHECK_FALSE(guard.CheckLine("G21", approach));
  CHECK_FALSE(guard.CheckLine("$H", approach));
  // A straight move that would cut through the sensor is caught along the way.
  const Eigen::Vector3d other = travel->MachineFromBall(Eigen::Vector3d(-13.0, 0.0, 15.0));
  CHECK(guard.CheckLine(MachineMoveLine(other), approach).has_value());
}

TEST_CASE("every motion line of a probe's program is recorded with its target", "[daemon]") {
  test::RigFixture f("targets", 40, 0.0);
  RunEngine engine(f.db);
  ProbePlan plan;
  engine.CreateRun(f.config, &plan);
  REQUIRE(plan.probes.size() > 2);
  PlannedProbe p = plan.probes[1];
  p.travel_machine = {p.approach_machine + Eigen::Vector3d(0.0, 0.0, 5.0)};
  p.reference_before = true;
  const ProbeProgram program = MakeProbeProgram(p, f.config.plan);
  std::vector<Eigen::Vector3d> targets;
  for (const auto* part : {&program.reference, &program.press, &program.retract}) {
    for (const std::string& line : *part) {
      const auto target = session::MotionTarget(line);
      const bool moves =
          line.find(" G0 ") != std::string::npos || line.find(" G1 ") != std::string::npos;
      INFO(line);
      CHECK(target.has_value() == moves);  // G4 dwells are not motion
      if (target) targets.push_back(*target);
    }
  }
  // Travel, approach (a "G90 G53 G0" line), press, back to the approach.
  REQUIRE(targets.size() == 4);
  CHECK(targets[0].isApprox(p.travel_machine[0], 1e-3));
  CHECK((targets[1] - p.approach_machine).norm() < 1e-3);
  CHECK((targets[2] - p.press_machine).norm() < 1e-3);
  CHECK((targets[3] - p.approach_machine).norm() < 1e-3);
  CHECK_FALSE(session::MotionTarget("G91 G0 Z5"));
  CHECK_FALSE(session::MotionTarget("G53 G0 X1 Y2"));
}

TEST_CASE("a stored run's calibration inputs carry where its plan could not probe", "[daemon]") {
  const auto dir = test::FreshDir("gaps");
  RunConfig config;
  config.machine.uri = "/dev/ttyACM0";  // planned and stored, never connected
  config.camera.uri = "replay:/nowhere";
  config.plan.probe_count = 1500;
  ProbePlan plan;
  const std::int64_t run = RunEngine(dir / "gs360.db").CreateRun(config, &plan);
  REQUIRE_FALSE(plan.coverage_gaps.empty());
  const CalibrationInputs inputs = CalibrationInputsFor(RunDatabase(dir / "gs360.db"), run);
  REQUIRE(inputs.coverage_gaps.size() == plan.coverage_gaps.size());
  CHECK(inputs.coverage_gaps[0]["text"] == plan.coverage_gaps[0].Describe());
  std::filesystem::remove_all(dir);
}

TEST_CASE("a plan that breaks a safety limit is refused at creation, naming the probe",
          "[daemon][safety]") {
  RunConfig config;
  config.machine.uri = "unused";
  config.camera.uri = "unused";
  config.plan.probe_count = 80;
  SafetyLimits limits;
  CHECK_NOTHROW(RunEngine::PlanRun(config, &limits));
  limits.max_press_depth = 0.8;  // the plan presses 1.0 mm
  try {
    RunEngine::PlanRun(config, &limits);
    FAIL("the plan was accepted");
  } catch (const ConfigError& e) {
    CHECK(e.field() == "plan");
    CHECK_THAT(e.what(), Catch::Contains("probe 0") && Catch::Contains("limits.max_press_depth"));
  }
  limits = SafetyLimits{};
  limits.envelope_max.z() = -20.0;  // the upper presses need more height
  CHECK_THROWS_WITH(RunEngine::PlanRun(config, &limits), Catch::Contains("limits.envelope_max.z"));
  limits = SafetyLimits{};
  limits.max_feed_mm_per_min = 100.0;  // the press feed is 120
  CHECK_THROWS_WITH(RunEngine::PlanRun(config, &limits),
                    Catch::Contains("F120.0") && Catch::Contains("limits.max_feed_mm_per_min"));
}

TEST_CASE("the event hub delivers in order, keeps the recent ones and wakes on close",
          "[daemon][events]") {
  EventHub hub(16);
  CHECK(hub.WaitAfter(0, std::chrono::milliseconds(10)).empty());
  for (int i = 0; i < 20; ++i) hub.Publish("log", {{"i", i}});
  CHECK(hub.LastId() == 20);
  const auto kept = hub.WaitAfter(0, std::chrono::milliseconds(0));
  REQUIRE(kept.size() == 16);  // the oldest fell out
  CHECK(kept.front().id == 5);
  CHECK(kept.back().data["i"] == 19);
  CHECK(hub.WaitAfter(18, std::chrono::milliseconds(0)).size() == 2);

  std::vector<HubEvent> got;
  std::thread waiter([&] { got = hub.WaitAfter(20, std::chrono::seconds(30)); });
  hub.Publish("progress", {{"run", 1}});
  waiter.join();
  REQUIRE(got.size() == 1);
  CHECK(got[0].type == "progress");

  std::thread closed([&] { got = hub.WaitAfter(21, std::chrono::seconds(30)); });
  hub.Close();
  closed.join();
  CHECK(got.empty());
  CHECK(hub.Closed());
}

TEST_CASE("a vanished device's port lock is let go until the device is back", "[daemon][lock]") {
  // The kernel reuses tty names: a daemon whose pty or USB tty went away must not keep a lock
  // that a new device under the same name (another rig, another daemon) then runs into.
  const auto dir = std::filesystem::canonical(test::FreshDir("vanish"));
  const auto tty = dir / "ttyACM0";
  std::ofstream(tty).put('\n');
  const DaemonConfig config = DaemonConfigFromToml(
      "data_dir = \"data\"\n[machine]\nuri = \"" + tty.string() + "\"\n", "test.toml", dir);
  Daemon daemon(config);
  CHECK_THROWS_AS(InstanceLock::Acquire(MachineLockPath(tty.string()), "a", "test"), LockHeldError);
  std::filesystem::remove(tty);
  daemon.FollowPortLock();
  {
    InstanceLock taken = InstanceLock::Acquire(MachineLockPath(tty.string()), "a", "test");
    CHECK(taken.Held());
  }
  std::ofstream(tty).put('\n');
  daemon.FollowPortLock();
  CHECK_THROWS_AS(InstanceLock::Acquire(MachineLockPath(tty.string()), "a", "test"), LockHeldError);
  // A second daemon on the same port still gets a clear error (after its one-second wait).
  const DaemonConfig second = DaemonConfigFromToml(
      "data_dir = \"data2\"\n[machine]\nuri = \"" + tty.string() + "\"\n", "test.toml", dir);
  CHECK_THROWS_WITH(Daemon(second), Catch::Contains("the machine port " + tty.string() +
                                                    " is in use by gs360d pid"));
  daemon.Shutdown();
  std::filesystem::remove_all(dir);
}

TEST_CASE("the port lock follows the configured symlink to a replugged controller",
          "[daemon][lock]") {
  const auto dir = test::FreshDir("follow");
  const auto first = dir / "pts-a";
  const auto second = dir / "pts-b";
  std::ofstream(first).put('\n');
  std::ofstream(second).put('\n');
  const auto link = dir / "ttyCNC";
  std::filesystem::create_symlink(first, link);
  const DaemonConfig config = DaemonConfigFromToml(
      "data_dir = \"data\"\n[machine]\nuri = \"" + link.string() + "\"\n", "test.toml", dir);
  Daemon daemon(config);
  CHECK_THROWS_AS(InstanceLock::Acquire(MachineLockPath(first.string()), "a", "test"),
                  LockHeldError);
  // The symlink moves at once (a new link renamed over it): were it gone for a moment, the
  // daemon's event pump could see a vanished device and let go of its lock (the test below).
  const auto repoint = [&](const std::filesystem::path& target) {
    const auto fresh = dir / "ttyCNC.new";
    std::filesystem::create_symlink(target, fresh);
    std::filesystem::rename(fresh, link);
  };
  // The controller comes back under another name; the symlink follows it, and so does the lock.
  repoint(second);
  daemon.FollowPortLock();
  CHECK(InstanceLock::Acquire(MachineLockPath(first.string()), "a", "test").Held());
  CHECK_THROWS_AS(InstanceLock::Acquire(MachineLockPath(second.string()), "b", "test"),
                  LockHeldError);
  // A name another daemon holds is not taken over: the lock stays where it was.
  InstanceLock other = InstanceLock::Acquire(MachineLockPath(first.string()), "a", "other");
  repoint(first);
  daemon.FollowPortLock();
  CHECK_THROWS_AS(InstanceLock::Acquire(MachineLockPath(second.string()), "b", "test"),
                  LockHeldError);
  daemon.Shutdown();
  std::filesystem::remove_all(dir);
}
