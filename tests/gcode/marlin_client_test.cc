// The Marlin client over a real pseudo-terminal against a printer that checks numbers and
// checksums (fake_marlin.h): connecting to a board that reboots on open, a garbled line, a lost
// ok, the position after the moves, a reboot mid-run, a halt, and no heating command ever sent.

#include <catch2/catch.hpp>

#include <chrono>
#include <memory>
#include <string>
#include <vector>

#include "fake_marlin.h"
#include "gcode/marlin_client.h"
#include "gcode/transport.h"

namespace {

using gs360::MarlinClient;
using gs360::MarlinError;
using gs360::test::FakeMarlin;
using gs360::test::FakeMarlinOptions;
using std::chrono::milliseconds;

std::unique_ptr<MarlinClient> Open(const FakeMarlin& printer) {
  gs360::MarlinClientOptions o;
  o.boot_timeout = milliseconds(2000);
  o.boot_quiet = milliseconds(100);
  o.reply_timeout = milliseconds(300);
  return std::make_unique<MarlinClient>(gs360::OpenTermiosTransport(printer.Path(), {}), o);
}

}  // namespace

TEST_CASE("MarlinClient: waits out the boot, learns the firmware, moves and reads back",
          "[gcode][marlin]") {
  FakeMarlin printer;
  auto client = Open(printer);
  const gs360::MarlinInfo info = client->Connect();
  CHECK(info.rebooted_on_open);
  CHECK(info.firmware == "Marlin 2.1.2.1 (Jul 16 2023)");
  CHECK(info.machine_type == "Ender-3");
  CHECK(info.Has("EMERGENCY_PARSER"));
  CHECK_FALSE(info.Has("M114_REALTIME"));
  CHECK(info.soft_endstops);
  CHECK(info.soft_max->isApprox(Eigen::Vector3d(235, 235, 250)));
  const auto homed = client->Execute("G28", milliseconds(2000));
  CHECK(homed.busy == 1);
  client->Execute("G1 X10.5 Y20 Z5 F3000", milliseconds(2000));
  CHECK(client->StoppedPosition(milliseconds(2000)).isApprox(Eigen::Vector3d(10.5, 20, 5)));
  CHECK(printer.Ran() ==
        std::vector<std::string>{"M115", "M211", "G28", "G1 X10.5 Y20 Z5 F3000", "M400", "M114"});
  CHECK_THROWS_WITH(client->Execute("M104 S200", milliseconds(100)), Catch::Contains("heats"));
  CHECK_THROWS_AS(client->Execute("m190 S60", milliseconds(100)), std::invalid_argument);
}

TEST_CASE("MarlinClient: a garbled line and a lost ok, each run once", "[gcode][marlin]") {
  FakeMarlinOptions o;
  o.reboot_on_open = false;
  o.garble_line = 3;   // G1 X1
  o.drop_ok_line = 4;  // G1 X2
  FakeMarlin printer(o);
  auto client = Open(printer);
  CHECK_FALSE(client->Connect().rebooted_on_open);  // M110 is line 0, M115 1, M211 2
  client->Execute("G1 X1", milliseconds(3000));
  client->Execute("G1 X2", milliseconds(3000));
  client->Execute("G1 X3", milliseconds(3000));
  CHECK(printer.Ran() == std::vector<std::string>{"M115", "M211", "G1 X1", "G1 X2", "G1 X3"});
  CHECK(client->Stream().Resends() == 2);  // the garbled line; the retry refused as a duplicate
  CHECK(client->Stream().Retries() == 1);
}

TEST_CASE("MarlinClient: a reboot mid-run and a halt stop it with what to do", "[gcode][marlin]") {
  FakeMarlinOptions o;
  o.reboot_on_open = false;
  o.reboot_at_line = 4;
  FakeMarlin printer(o);
  auto client = Open(printer);
  client->Connect();
  client->Execute("G1 Z10", milliseconds(2000));
  try {
    client->Execute("G1 Z2", milliseconds(2000));
    FAIL("no reboot seen");
  } catch (const MarlinError& e) {
    CHECK(e.kind() == MarlinError::Kind::kRebooted);
    CHECK_THAT(e.what(), Catch::Contains("0,0,0"));
  }
  // Numbering starts over; the printer now believes 0,0,0 wherever the tool is.
  CHECK(client->StoppedPosition(milliseconds(2000)).isApprox(Eigen::Vector3d::Zero()));
  client->EmergencyStop();
  try {
    client->Execute("G1 Z5", milliseconds(2000));
    FAIL("no halt seen");
  } catch (const MarlinError& e) {
    CHECK(e.kind() == MarlinError::Kind::kHalted);
  }
  CHECK_THROWS_WITH(client->Execute("G1 Z6", milliseconds(100)), Catch::Contains("M999"));
}

TEST_CASE("MarlinClient: a printer that only ever says it is busy does not hold a call forever",
          "[gcode][marlin]") {
  FakeMarlinOptions o;
  o.reboot_on_open = false;
  o.busy_forever = true;  // a keep-alive every 20 ms, never an ok
  FakeMarlin printer(o);
  auto client = Open(printer);
  // Connect's first line (M115) never gets its ok: the busy flood must not keep the call alive.
  try {
    client->Connect();
    FAIL("no time-out");
  } catch (const MarlinError& e) {
    CHECK(e.kind() == MarlinError::Kind::kTimeout);
    CHECK_THAT(e.what(), Catch::Contains("M115") && Catch::Contains("not done within"));
  }
}
