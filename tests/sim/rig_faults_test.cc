// Fault kinds by name, and the schedule that injects them while the rig serves.

#include <catch2/catch.hpp>

#include <fcntl.h>
#include <unistd.h>

#include <chrono>
#include <string>
#include <thread>

#include "sim/rig_faults.h"
#include "tests/wait.h"

using namespace gs360;

TEST_CASE("fault kinds parse by name, all of them with 'all', and an unknown one is named",
          "[sim][faults]") {
  CHECK(ParseRigFaults("all").size() == AllRigFaults().size());
  const auto two = ParseRigFaults("drop,,frame-corrupt");
  REQUIRE(two.size() == 2);
  CHECK(two[0] == RigFault::kDrop);
  CHECK(two[1] == RigFault::kFrameCorrupt);
  for (RigFault f : AllRigFaults()) {
    const auto one = ParseRigFaults(std::string(ToString(f)));
    REQUIRE(one.size() == 1);
    CHECK(one[0] == f);
  }
  CHECK_THROWS_WITH(ParseRigFaults("drop,meteor"),
                    Catch::Contains("unknown fault 'meteor'") && Catch::Contains("lost-reply"));
  CHECK_THROWS_WITH(ParseRigFaults(","), Catch::Contains("no fault kinds"));
  RigFaultScheduleOptions options;
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("faults is empty"));
  options.faults = {RigFault::kFrameDrop};
  options.every_probes = 1.0;
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("every_probes") && Catch::Contains("1"));
}

TEST_CASE("the schedule injects camera faults as the controller dwells", "[sim][faults]") {
  VirtualRigOptions options;
  options.cnc.time_scale = 0.0;
  options.cnc.baud_rate = 0;
  VirtualRig rig(options);
  RigFaultScheduleOptions schedule;
  schedule.faults = {RigFault::kFrameCorrupt};
  schedule.every_probes = 2.0;
  RigFaultSchedule faults(rig, schedule);
  // A host's dwells, as probes would send them: G4 lines on the pty.
  const int fd = ::open(rig.PtyPath().c_str(), O_RDWR | O_NOCTTY);
  REQUIRE(fd >= 0);
  // It boots locked (homing enabled): unlock, then dwell.
  for (int i = 0; i < 13; ++i) {
    const std::string line = i == 0 ? "$X\n" : "G4 P0.01\n";
    REQUIRE(::write(fd, line.data(), line.size()) == static_cast<ssize_t>(line.size()));
    std::this_thread::sleep_for(std::chrono::milliseconds(30));
  }
  CHECK(test::WaitUntil([&] { return rig.cnc().Stats().dwells >= 12; }, std::chrono::seconds(5)));
  CHECK(test::WaitUntil([&] { return faults.Total() >= 4; }, std::chrono::seconds(5)));
  CHECK(faults.Injected().at("frame-corrupt") == faults.Total());
  ::close(fd);
}
