// The virtual CNC's Marlin dialect over a real pseudo-terminal: driven by the Marlin client
// (gcode/marlin_client.h) where a host would drive it, and by raw lines where the test needs to see
// exactly what the printer answers. Each fault of the issue (a checksum error and its resend, a
// lost ok, busy keep-alives, a reboot on open and mid-run, a halt) has its own case.

#include <catch2/catch.hpp>

#include <chrono>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "gcode/marlin_client.h"
#include "gcode/marlin_messages.h"
#include "gcode/transport.h"
#include "sim/virtual_cnc.h"

namespace {

using gs360::CncFirmware;
using gs360::FaultDirection;
using gs360::MarlinClient;
using gs360::MarlinError;
using gs360::VirtualCnc;
using gs360::VirtualCncOptions;
using std::chrono::milliseconds;

VirtualCncOptions Printer(double time_scale = 0.0) {
  VirtualCncOptions o;
  o.firmware = CncFirmware::kMarlin;
  o.time_scale = time_scale;
  o.baud_rate = 0;
  o.settings.max_travel_mm = {235.0, 235.0, 250.0};
  o.settings.max_rate_mm_per_min = {30000.0, 30000.0, 300.0};  // Z 5 mm/s
  o.settings.acceleration_mm_per_s2 = {500.0, 500.0, 100.0};
  o.settings.steps_per_mm = {80.0, 80.0, 400.0};
  o.settings.homing_seek_mm_per_min = 3000.0;
  o.settings.homing_feed_mm_per_min = 600.0;
  o.initial_true_position = {50.0, 60.0, 20.0};
  return o;
}

std::unique_ptr<MarlinClient> Open(const VirtualCnc& printer) {
  gs360::MarlinClientOptions o;
  o.boot_timeout = milliseconds(1500);
  o.boot_quiet = milliseconds(100);
  o.reply_timeout = milliseconds(400);
  return std::make_unique<MarlinClient>(gs360::OpenTermiosTransport(printer.PtyPath(), {}), o);
}

bool Near(const Eigen::Vector3d& a, const Eigen::Vector3d& b, double tol = 1e-6) {
  return (a - b).cwiseAbs().maxCoeff() <= tol;
}

// Raw lines, for what the printer says word for word.
class Terminal {
 public:
  explicit Terminal(const VirtualCnc& printer)
      : transport_(gs360::OpenTermiosTransport(printer.PtyPath(), {})) {}
  void Write(const std::string& s) { transport_->Write(s); }
  // Lines until one starts with `last` (included) or `wait` passes.
  std::vector<std::string> ReadUntil(const std::string& last,
                                     milliseconds wait = milliseconds(2000)) {
    std::vector<std::string> out;
    const auto until = std::chrono::steady_clock::now() + wait;
    while (true) {
      for (std::size_t eol; (eol = pending_.find('\n')) != std::string::npos;) {
        out.push_back(pending_.substr(0, eol));
        pending_.erase(0, eol + 1);
        if (out.back().rfind(last, 0) == 0) return out;
      }
      if (std::chrono::steady_clock::now() >= until) return out;
      char buf[256];
      pending_.append(buf, transport_->Read(buf, sizeof buf, milliseconds(20)));
    }
  }

 private:
  std::unique_ptr<gs360::Transport> transport_;
  std::string pending_;  // read, not yet returned
};

}  // namespace

TEST_CASE("Virtual Marlin: boots, reports itself, homes and moves where M114 says",
          "[sim][marlin]") {
  VirtualCncOptions o = Printer();
  o.reset_on_open = true;
  o.boot_delay = milliseconds(200);
  VirtualCnc printer(o);
  auto client = Open(printer);
  const gs360::MarlinInfo info = client->Connect();
  CHECK(info.rebooted_on_open);
  CHECK_THAT(info.firmware, Catch::StartsWith("Marlin 2.1"));
  CHECK(info.machine_type == "Virtual Ender-3");
  CHECK(info.Has("EMERGENCY_PARSER"));
  CHECK(info.Has("AUTOREPORT_POS"));
  CHECK(info.soft_endstops);
  REQUIRE(info.soft_max);
  CHECK(Near(*info.soft_max, {235.0, 235.0, 250.0}));
  CHECK(Near(*info.soft_min, Eigen::Vector3d::Zero()));

  // At boot it believes 0,0,0 wherever the tool stands.
  CHECK(Near(client->StoppedPosition(milliseconds(1000)), Eigen::Vector3d::Zero()));
  client->Execute("G28", milliseconds(5000));
  CHECK(Near(printer.TruePositionNow(), Eigen::Vector3d::Zero(), 1e-9));
  client->Execute("G0 X10.5 Y20 Z5 F6000", milliseconds(2000));
  CHECK(Near(client->StoppedPosition(milliseconds(2000)), {10.5, 20.0, 5.0}, 0.005));
  CHECK(Near(client->StoppedPosition(milliseconds(2000), true), {10.5, 20.0, 5.0}, 0.0005));
  CHECK(Near(printer.TruePositionNow(), {10.5, 20.0, 5.0}, 1e-9));
  // Soft endstops clamp a homed axis into 0..max, silently.
  client->Execute("G0 X-5 Z300", milliseconds(2000));
  CHECK(Near(client->StoppedPosition(milliseconds(2000)), {0.0, 20.0, 250.0}, 0.005));
  CHECK(Near(printer.TruePositionNow(), {0.0, 20.0, 250.0}, 1e-9));
}

TEST_CASE("Virtual Marlin: line numbers, checksums and resends word for word", "[sim][marlin]") {
  VirtualCnc printer(Printer());
  Terminal t(printer);
  t.ReadUntil("echo:Hardcoded", milliseconds(500));  // the boot, waiting in the pty
  t.Write(gs360::MarlinFrame(0, "M110 N0") + "\n");
  CHECK(t.ReadUntil("ok").back() == "ok");
  // A number skipped.
  t.Write(gs360::MarlinFrame(2, "G0 X1") + "\n");
  CHECK(t.ReadUntil("ok") ==
        std::vector<std::string>{"Error:Line Number is not Last Line Number+1, Last Line: 0",
                                 "Resend: 1", "ok"});
  // A wrong checksum.
  std::string bad = gs360::MarlinFrame(1, "G0 X1");
  bad.back() = bad.back() == '0' ? '1' : '0';
  t.Write(bad + "\n");
  CHECK(t.ReadUntil("ok") ==
        std::vector<std::string>{"Error:checksum mismatch, Last Line: 0", "Resend: 1", "ok"});
  t.Write("N1 G0 X1\n");
  CHECK(t.ReadUntil("ok").front() == "Error:No Checksum with line number, Last Line: 0");
  t.Write("G0 X1*12\n");
  CHECK(t.ReadUntil("ok").front() == "Error:No Line Number with checksum, Last Line: 0");
  // The right line; then an unnumbered one; then an unknown command and an empty line.
  t.Write(gs360::MarlinFrame(1, "G0 X1") + "\nG0 X2\n\nG94\n");
  CHECK(t.ReadUntil("ok") == std::vector<std::string>{"ok"});
  CHECK(t.ReadUntil("ok") == std::vector<std::string>{"ok"});
  CHECK(t.ReadUntil("ok") == std::vector<std::string>{"echo:Unknown command: \"G94\"", "ok"});
  CHECK(printer.Stats().lines == 8);  // the empty line is not one
  t.Write("M114\n");
  CHECK(t.ReadUntil("ok").front() == "X:2.00 Y:0.00 Z:0.00 E:0.00 Count X:160 Y:0 Z:0");
}

TEST_CASE("Virtual Marlin: a garbled line is resent and a lost ok retried, each run once",
          "[sim][marlin]") {
  VirtualCnc printer(Printer());
  auto client = Open(printer);
  client->Connect();
  client->Execute("G91", milliseconds(1000));  // relative: a move run twice would show
  printer.GarbleNextBytes(1, FaultDirection::kHostToCnc);
  client->Execute("G0 X1 F6000", milliseconds(3000));
  CHECK(client->Stream().Resends() == 1);
  printer.LoseNextReply();
  client->Execute("G0 X1", milliseconds(3000));
  CHECK(client->Stream().Retries() == 1);
  CHECK(client->Stream().Resends() == 2);  // the retry refused as a duplicate, the next asked for
  client->Execute("G0 X1", milliseconds(3000));
  CHECK(Near(client->StoppedPosition(milliseconds(2000)), {3.0, 0.0, 0.0}, 0.005));
  CHECK(Near(printer.TruePositionNow(), {53.0, 60.0, 20.0}, 1e-9));
}

TEST_CASE("Virtual Marlin: a long command keeps the host waiting with busy keep-alives",
          "[sim][marlin]") {
  VirtualCncOptions o = Printer(8.0);  // eight machine seconds per wall second
  o.marlin.keepalive_s = 1.0;
  o.marlin.temperature_report_s = 0.5;  // reports in between, which the client must ignore
  VirtualCnc printer(o);
  auto client = Open(printer);
  client->Connect();
  const auto start = printer.MachineTime(std::chrono::steady_clock::now());
  const gs360::MarlinReply dwell = client->Execute("G4 S4.2", milliseconds(5000));
  CHECK(dwell.busy == 4);  // at 1, 2, 3 and 4 s
  CHECK(printer.MachineTime(std::chrono::steady_clock::now()) - start >= 4.2);
  // Z at 5 mm/s: 20 mm down takes > 4 s; the move's ok comes at once, M400's after it. (The
  // printer believes it stands at 0,0,0: not homed, nothing clamps.)
  client->Execute("G0 Z-20 F6000", milliseconds(1000));
  const gs360::MarlinReply wait = client->Execute("M400", milliseconds(5000));
  CHECK(wait.busy >= 3);
  CHECK(Near(printer.TruePositionNow(), {50.0, 60.0, 0.0}, 1e-9));
}

TEST_CASE("Virtual Marlin: a reboot mid-move loses the position, a halt stops everything",
          "[sim][marlin]") {
  VirtualCnc printer(Printer(4.0));
  auto client = Open(printer);
  client->Connect();
  client->Execute("G0 X150 F1200", milliseconds(1000));  // 100 mm at 20 mm/s: 5 s machine time
  std::this_thread::sleep_for(milliseconds(300));
  printer.PowerCycle();
  try {
    client->Execute("M400", milliseconds(3000));
    FAIL("no reboot seen");
  } catch (const MarlinError& e) {
    CHECK(e.kind() == MarlinError::Kind::kRebooted);
  }
  const Eigen::Vector3d stopped = printer.TruePositionNow();
  CHECK(stopped.x() > 51.0);
  CHECK(stopped.x() < 149.0);
  CHECK(Near(client->StoppedPosition(milliseconds(2000)), Eigen::Vector3d::Zero()));

  // A driver fault mid-move halts the printer as kill() does.
  printer.RaiseAlarmDuringNextMove(1, 0.5);
  try {
    client->Execute("G0 Y10 F6000", milliseconds(1000));
    client->Execute("M400", milliseconds(3000));
    FAIL("no halt seen");
  } catch (const MarlinError& e) {
    CHECK(e.kind() == MarlinError::Kind::kHalted);
    CHECK_THAT(e.what(), Catch::Contains("kill() called"));
  }
  CHECK(Near(printer.TruePositionNow(), stopped + Eigen::Vector3d(0.0, 5.0, 0.0), 1e-6));
  CHECK(printer.Stats().alarms == 1);
}

TEST_CASE("Virtual Marlin: the emergency parser takes M112 and M410 ahead of the queue",
          "[sim][marlin]") {
  VirtualCnc printer(Printer(4.0));
  Terminal t(printer);
  t.ReadUntil("echo:Hardcoded", milliseconds(500));
  // M410 while a move runs: the move stops dead, the printer goes on.
  t.Write("G0 X150 F1200\n");
  t.ReadUntil("ok");
  std::this_thread::sleep_for(milliseconds(300));
  t.Write("N5 M410*" + std::to_string(gs360::MarlinChecksum("N5 M410")) + "\n");
  std::this_thread::sleep_for(milliseconds(100));
  const Eigen::Vector3d stopped = printer.TruePositionNow();
  CHECK(stopped.x() > 51.0);
  CHECK(stopped.x() < 149.0);
  std::this_thread::sleep_for(milliseconds(200));
  CHECK(Near(printer.TruePositionNow(), stopped, 1e-9));
  t.ReadUntil("ok");  // the M410 line (its number is wrong: refused, still acted on)
  t.Write("M114 R\n");
  const std::vector<std::string> real = t.ReadUntil("ok");
  REQUIRE(real.size() == 2);
  const gs360::MarlinMessage m = gs360::ParseMarlinLine(real[0]);
  REQUIRE(m.position);
  CHECK(Near(*m.position, stopped - Eigen::Vector3d(50.0, 60.0, 20.0), 0.0125));
  // M112 behind a long dwell: taken at once, not after the dwell.
  t.Write("G4 S30\nM112\n");
  CHECK(t.ReadUntil("Error:", milliseconds(1000)).back() == "Error:Printer halted. kill() called!");
  t.Write("M114\n");
  CHECK(t.ReadUntil("ok", milliseconds(500)).empty());  // halted: nothing answers
}

TEST_CASE("Virtual Marlin: homing from beyond the endstop's reach fails and halts",
          "[sim][marlin]") {
  VirtualCncOptions o = Printer();
  o.initial_true_position = {400.0, 10.0, 10.0};  // more than 1.5 x 235 from X's endstop
  VirtualCnc printer(o);
  auto client = Open(printer);
  client->Connect();
  CHECK_THROWS_AS(client->Execute("G28", milliseconds(3000)), MarlinError);
  CHECK(Near(printer.TruePositionNow(), {400.0 - 1.5 * 235.0, 10.0, 10.0}, 1e-9));
}
