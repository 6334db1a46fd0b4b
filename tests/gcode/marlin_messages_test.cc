// Marlin's serial protocol: framing with line numbers and checksums, and every reply kind, as
// Marlin 2.x (and Klipper's pseudo-terminal) print them.

#include <catch2/catch.hpp>

#include <stdexcept>
#include <string>

#include "gcode/marlin_messages.h"

using gs360::MarlinMessageKind;
using gs360::ParseMarlinLine;

TEST_CASE("MarlinFrame numbers a command and appends its checksum", "[gcode][marlin]") {
  // The checksums computed apart from this code (XOR of the bytes before '*').
  CHECK(gs360::MarlinFrame(0, "M110 N0") == "N0 M110 N0*125");
  CHECK(gs360::MarlinFrame(12, "G1 X10.5 Y-3 F3000") == "N12 G1 X10.5 Y-3 F3000*123");
  CHECK(gs360::MarlinFrame(7, "  G28 ; home all axes") == "N7 G28*20");
  CHECK(gs360::MarlinChecksum("N1 M114") == 38);
  CHECK_THROWS_WITH(gs360::MarlinFrame(3, "; only a comment"), Catch::Contains("is empty"));
  CHECK_THROWS_WITH(gs360::MarlinFrame(3, "G1 X1*5"), Catch::Contains("'*'"));
  CHECK_THROWS_WITH(gs360::MarlinFrame(3, "G1 X1\nG28"), Catch::Contains("printable"));
  CHECK_THROWS_AS(gs360::MarlinFrame(-1, "G28"), std::invalid_argument);
}

TEST_CASE("Marlin replies: ok, resend and the framing errors", "[gcode][marlin]") {
  auto m = ParseMarlinLine("ok");
  CHECK(m.kind == MarlinMessageKind::kOk);
  CHECK_FALSE(m.line);
  m = ParseMarlinLine("ok N12 P15 B3\r");
  CHECK(m.kind == MarlinMessageKind::kOk);
  CHECK(m.line == 12);
  CHECK(m.planner_free == 15);
  CHECK(m.buffer_free == 3);
  m = ParseMarlinLine("ok T:21.50 /0.00 B:20.93 /0.00 @:0 B@:0");  // M105's answer
  CHECK(m.kind == MarlinMessageKind::kOk);
  CHECK_FALSE(m.buffer_free);
  CHECK(ParseMarlinLine("okay").kind == MarlinMessageKind::kUnknown);

  for (const char* line : {"Resend: 6", "Resend:6", "rs N6", "rs 6"}) {
    INFO(line);
    m = ParseMarlinLine(line);
    CHECK(m.kind == MarlinMessageKind::kResend);
    CHECK(m.line == 6);
  }
  CHECK(ParseMarlinLine("Resend: six").kind == MarlinMessageKind::kUnknown);

  for (const char* line : {"Error:checksum mismatch, Last Line: 5",
                           "Error:Line Number is not Last Line Number+1, Last Line: 5",
                           "Error:No Checksum with line number, Last Line: 5"}) {
    INFO(line);
    m = ParseMarlinLine(line);
    CHECK(m.kind == MarlinMessageKind::kLineError);
    CHECK(m.line == 5);
  }
}

TEST_CASE("Marlin replies: halts, errors, keep-alives and what a host ignores", "[gcode][marlin]") {
  for (const char* line :
       {"Error:Printer halted. kill() called!",
        "Error:Printer stopped due to errors. Fix the error and use M999 to restart.",
        "!! Shutdown due to webhooks request", "// Klipper state: Shutdown"}) {
    INFO(line);
    CHECK(ParseMarlinLine(line).kind == MarlinMessageKind::kHalted);
  }
  auto m = ParseMarlinLine("Error:Thermal Runaway, system stopped! Heater_ID: bed");
  CHECK(m.kind == MarlinMessageKind::kError);
  CHECK(m.text == "Thermal Runaway, system stopped! Heater_ID: bed");
  m = ParseMarlinLine("!! Must home axis first: 10.000 0.000 5.000 [0.000]");
  CHECK(m.kind == MarlinMessageKind::kError);

  m = ParseMarlinLine("echo:busy: processing");
  CHECK(m.kind == MarlinMessageKind::kBusy);
  CHECK(m.text == "processing");
  CHECK(ParseMarlinLine("echo:busy: paused for user").kind == MarlinMessageKind::kBusy);
  CHECK(ParseMarlinLine("start").kind == MarlinMessageKind::kStart);
  m = ParseMarlinLine("echo:Unknown command: \"G999\"");
  CHECK(m.kind == MarlinMessageKind::kEcho);
  CHECK(m.unknown_command);
  m = ParseMarlinLine("echo:  M203 X500.00 Y500.00 Z5.00 E25.00");  // an M503 line
  CHECK(m.kind == MarlinMessageKind::kEcho);
  CHECK(m.text == "M203 X500.00 Y500.00 Z5.00 E25.00");
  CHECK_FALSE(m.unknown_command);
  m = ParseMarlinLine("//action:pause");
  CHECK(m.kind == MarlinMessageKind::kAction);
  CHECK(m.text == "pause");
  CHECK(ParseMarlinLine("// Klipper state: Ready").kind == MarlinMessageKind::kEcho);
  CHECK(ParseMarlinLine(" T:21.50 /0.00 B:20.93 /0.00 @:0 B@:0").kind ==
        MarlinMessageKind::kTemperature);
  CHECK(ParseMarlinLine("\x01\x02  \r").kind == MarlinMessageKind::kEmpty);
  m = ParseMarlinLine("\xff\xfegarbage\x07");
  CHECK(m.kind == MarlinMessageKind::kUnknown);
  CHECK(m.raw == "garbage");
}

TEST_CASE("Marlin replies: positions, firmware, capabilities and soft endstops",
          "[gcode][marlin]") {
  auto m = ParseMarlinLine("X:10.00 Y:-20.50 Z:5.25 E:0.00 Count X:800 Y:-1640 Z:2100");
  REQUIRE(m.kind == MarlinMessageKind::kPosition);
  CHECK(m.position->isApprox(Eigen::Vector3d(10.0, -20.5, 5.25)));
  CHECK(m.extruder == 0.0);
  CHECK(m.stepper_counts);
  m = ParseMarlinLine("X:1.00Y:2.00Z:3.00E:0.00");  // M114 R, M154 and older builds: no spaces
  REQUIRE(m.kind == MarlinMessageKind::kPosition);
  CHECK(m.position->isApprox(Eigen::Vector3d(1.0, 2.0, 3.0)));
  CHECK_FALSE(m.stepper_counts);
  CHECK(ParseMarlinLine("X:1.00 Y:2.00").kind == MarlinMessageKind::kUnknown);
  CHECK(ParseMarlinLine("X:1.00 Y:two Z:3.00").kind == MarlinMessageKind::kUnknown);

  m = ParseMarlinLine(
      "FIRMWARE_NAME:Marlin bugfix-2.1.x (Dec  1 2026 10:00:00) SOURCE_CODE_URL:github.com/"
      "MarlinFirmware/Marlin PROTOCOL_VERSION:1.0 MACHINE_TYPE:Ender-3 EXTRUDER_COUNT:1 "
      "UUID:cede2a2f-41a2-4748-9b12-c55c62f367ff");
  CHECK(m.kind == MarlinMessageKind::kFirmware);
  CHECK(m.text == "Marlin bugfix-2.1.x (Dec  1 2026 10:00:00)");
  CHECK(m.name == "Ender-3");
  m = ParseMarlinLine("FIRMWARE_NAME:Klipper FIRMWARE_VERSION:v0.12.0");
  CHECK(m.text == "Klipper");
  CHECK(m.name.empty());

  m = ParseMarlinLine("Cap:AUTOREPORT_POS:1");
  CHECK(m.kind == MarlinMessageKind::kCapability);
  CHECK(m.name == "AUTOREPORT_POS");
  CHECK(m.enabled);
  CHECK_FALSE(ParseMarlinLine("Cap:EMERGENCY_PARSER:0").enabled);

  m = ParseMarlinLine(
      "echo:Soft endstops: On  Min:  X0.00 Y-5.00 Z0.00   Max:  X235.00 Y235.00 Z250.00");
  REQUIRE(m.kind == MarlinMessageKind::kSoftEndstops);
  CHECK(m.enabled);
  CHECK(m.soft_min->isApprox(Eigen::Vector3d(0.0, -5.0, 0.0)));
  CHECK(m.soft_max->isApprox(Eigen::Vector3d(235.0, 235.0, 250.0)));
  m = ParseMarlinLine("echo:Soft endstops: Off  Min: X0.00 Y0.00 Z0.00 Max: X220 Y220 Z");
  CHECK_FALSE(m.enabled);
  CHECK(m.soft_min);
  CHECK_FALSE(m.soft_max);  // a garbled limit is no limit
}
