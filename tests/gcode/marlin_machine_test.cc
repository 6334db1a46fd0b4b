// The Marlin machine (gcode/marlin_machine.h) against the virtual Marlin printer on a real pty:
// the engine's G-code as Marlin takes it, M503's settings and M211's travel on connect, a press
// synchronised by its dwell, and reboots and halts as alarms that keep the tool where it is.

#include <catch2/catch.hpp>

#include <chrono>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "gcode/marlin_machine.h"
#include "gcode/marlin_messages.h"
#include "gcode/open_machine.h"
#include "sim/pty.h"
#include "sim/virtual_cnc.h"

namespace {

using gs360::MachineReplyKind;
using gs360::MarlinMachine;
using std::chrono::milliseconds;

gs360::VirtualCncOptions Printer(double time_scale) {
  gs360::VirtualCncOptions o;
  o.firmware = gs360::CncFirmware::kMarlin;
  o.settings = gs360::GrblSettings::PrinterDefaults();
  o.time_scale = time_scale;
  o.baud_rate = 0;
  o.initial_true_position = {50.0, 60.0, 40.0};
  return o;
}

std::unique_ptr<MarlinMachine> Open(const gs360::VirtualCnc& printer) {
  gs360::MarlinMachineOptions o;
  o.client.boot_timeout = milliseconds(1500);
  o.client.boot_quiet = milliseconds(100);
  o.client.reply_timeout = milliseconds(1000);  // the keep-alive: 2 machine s, 0.5 s here
  const std::string path = printer.PtyPath();
  return std::make_unique<MarlinMachine>([path] { return gs360::OpenTermiosTransport(path, {}); },
                                         o);
}

// Without a reboot on open the power-up's "start" waits in the pty for the first host; on a real
// board it went out to nobody long ago. Read it away.
void ReadBoot(const gs360::VirtualCnc& printer) {
  auto t = gs360::OpenTermiosTransport(printer.PtyPath(), {});
  char buf[512];
  while (t->Read(buf, sizeof buf, milliseconds(100)) > 0) {
  }
}

bool Near(const Eigen::Vector3d& a, const Eigen::Vector3d& b, double tol) {
  return (a - b).cwiseAbs().maxCoeff() <= tol;
}

}  // namespace

TEST_CASE("MarlinCommandsFor: the engine's G-code as Marlin takes it", "[gcode][marlin]") {
  using V = std::vector<std::string>;
  CHECK(gs360::MarlinCommandsFor("G21", 3000) == V{"G21"});
  CHECK(gs360::MarlinCommandsFor("G90 G53 G0 X1.000 Y2.000 Z3.000", 3000) ==
        V{"G90", "G0 X1.000 Y2.000 Z3.000 F3000.0"});
  CHECK(gs360::MarlinCommandsFor("G53 G0 X1.000 Y2.000 Z3.000", 12000) ==
        V{"G0 X1.000 Y2.000 Z3.000 F12000.0"});
  CHECK(gs360::MarlinCommandsFor("G53 G1 X1.000 Y2.000 Z3.000 F60.0", 3000) ==
        V{"G1 X1.000 Y2.000 Z3.000 F60.0"});
  CHECK(gs360::MarlinCommandsFor("G4 P0.300", 3000) == V{"M400", "G4 P300"});
  CHECK(gs360::MarlinCommandsFor("G4 P0.0005", 3000) == V{"M400", "G4 P1"});
  CHECK_THROWS_WITH(gs360::MarlinCommandsFor("$H", 3000), Catch::Contains("GRBL system command"));
  CHECK_THROWS_AS(gs360::MarlinCommandsFor("G53 G2 X1", 3000), std::invalid_argument);
}

TEST_CASE("ReadMarlinSettings: rates, accelerations and junction deviation from M503",
          "[gcode][marlin]") {
  std::vector<gs360::MarlinMessage> m;
  for (const char* line :
       {"echo:; Max feedrates (units/s):", "echo:  M203 X500.00 Y400.00 Z5.00 E25.00",
        "echo:  M201 X500.00 Y500.00 Z100.00 E5000.00",
        "echo:  M205 B20000.00 S0.00 T0.00 J0.013"}) {
    m.push_back(gs360::ParseMarlinLine(line));
  }
  gs360::MachineSettings s;
  CHECK(gs360::ReadMarlinSettings(m, &s));
  CHECK(Near(s.max_rate_mm_per_min, {30000.0, 24000.0, 300.0}, 1e-9));
  CHECK(Near(s.acceleration_mm_per_s2, {500.0, 500.0, 100.0}, 1e-9));
  CHECK(s.junction_deviation_mm == Approx(0.013));
  m.erase(m.begin() + 2);  // no M201
  CHECK_FALSE(gs360::ReadMarlinSettings(m, &s));
}

TEST_CASE("MarlinMachine: connects, homes, presses and syncs on the dwell", "[gcode][marlin]") {
  gs360::VirtualCncOptions o = Printer(8.0);
  o.reset_on_open = true;
  o.boot_delay = milliseconds(200);
  gs360::VirtualCnc printer(o);
  auto machine = Open(printer);
  const gs360::MachineInfo info = machine->Connect();
  CHECK_THAT(info.description, Catch::StartsWith("Marlin 2.1") && Catch::Contains("Ender-3"));
  CHECK(info.rates_known);
  CHECK(Near(info.settings.max_rate_mm_per_min, {30000.0, 30000.0, 300.0}, 1e-9));
  CHECK(info.travel_known);
  CHECK(Near(info.settings.TravelMin(), Eigen::Vector3d::Zero(), 1e-9));
  CHECK(Near(info.settings.TravelMax(), {235.0, 235.0, 250.0}, 1e-9));
  // It rebooted when the port opened: position lost until homed, and no motion.
  CHECK(machine->PositionLost());
  CHECK_FALSE(machine->Alarmed());
  CHECK_THAT(machine->AlarmText(), Catch::Contains("rebooted"));
  CHECK(machine->Send("G53 G0 X1.000 Y1.000 Z1.000").Wait(milliseconds(100)).kind ==
        MachineReplyKind::kRefused);
  const gs360::MachineReply homed = machine->Home(0.0);
  INFO(homed.Describe());
  REQUIRE(homed.Ok());
  CHECK_FALSE(machine->PositionLost());
  CHECK(Near(printer.TruePositionNow(), Eigen::Vector3d::Zero(), 1e-9));

  for (const char* line : {"G21", "G90", "G90 G53 G0 X10.000 Y20.000 Z30.000"}) {
    REQUIRE(machine->Send(line).Wait(milliseconds(2000)).Ok());
  }
  machine->Send("G53 G1 X10.000 Y20.000 Z25.000 F300.0");
  const gs360::MachineReply sync = machine->Send("G4 P0.300").Wait(milliseconds(20000));
  REQUIRE(sync.Ok());
  // The dwell's reply comes after the press ended: the tool stands at the press point.
  CHECK(Near(printer.TruePosition(sync.received_at), {10.0, 20.0, 25.0}, 1e-9));
  const auto status = machine->QueryStatus(milliseconds(2000));
  REQUIRE(status);
  CHECK(status->state == gs360::MachineState::kIdle);
  CHECK(Near(*status->machine_position, {10.0, 20.0, 25.0}, 0.003));
}

TEST_CASE("MarlinMachine: a reboot mid-move and a halt are alarms, and nothing moves after them",
          "[gcode][marlin]") {
  gs360::VirtualCnc printer(Printer(4.0));
  ReadBoot(printer);
  auto machine = Open(printer);
  machine->Connect();
  CHECK_FALSE(machine->PositionLost());  // no reboot on open: it kept its (unverified) position
  machine->MarkPositionTrusted();
  machine->Send("G53 G0 X150.000 Y60.000 Z40.000");  // 100 mm
  const gs360::MachineHandle sync = machine->Send("G4 P0.100");
  std::this_thread::sleep_for(milliseconds(100));
  printer.PowerCycle();
  const gs360::MachineReply r = sync.Wait(milliseconds(3000));
  CHECK(r.kind == MachineReplyKind::kReset);
  CHECK(machine->PositionLost());
  CHECK_FALSE(machine->Alarmed());  // a reboot loses the position; it is no halt
  CHECK_FALSE(machine->PositionTrusted());
  CHECK(machine->Send("G53 G0 X0.000 Y0.000 Z0.000").Wait(milliseconds(100)).kind ==
        MachineReplyKind::kRefused);
  const auto status = machine->QueryStatus(milliseconds(2000));
  REQUIRE(status);
  CHECK(Near(*status->machine_position, Eigen::Vector3d::Zero(), 1e-9));  // it believes 0,0,0
  machine->MarkPositionTrusted();  // the position established (by the user, here)
  CHECK_FALSE(machine->PositionLost());

  printer.RaiseAlarmDuringNextMove(1, 0.5);
  machine->Send("G53 G0 X10.000 Y0.000 Z0.000");
  const gs360::MachineReply halted = machine->Send("G4 P0.100").Wait(milliseconds(3000));
  CHECK(halted.kind == MachineReplyKind::kReset);
  REQUIRE(halted.alarm);
  CHECK_THAT(*halted.alarm, Catch::Contains("kill() called"));
  CHECK(machine->Alarmed());
  CHECK(machine->PositionLost());
  CHECK_FALSE(machine->Unlock().Ok());  // only a reset of the printer ends a halt
  CHECK(machine->Send("G21").Wait(milliseconds(100)).kind == MachineReplyKind::kRefused);
}

TEST_CASE("OpenMachine auto: tells GRBL from Marlin, spoken to or silent, and loses nothing",
          "[gcode][marlin]") {
  gs360::OpenMachineOptions o;
  o.detect_wait = milliseconds(400);
  o.marlin.client.boot_timeout = milliseconds(500);
  o.marlin.client.boot_quiet = milliseconds(100);
  o.grbl.welcome_timeout = milliseconds(500);
  SECTION("a GRBL welcome waiting in the port") {
    gs360::VirtualCncOptions g;
    g.time_scale = 0.0;
    gs360::VirtualCnc cnc(g);
    gs360::MachineFirmware f = gs360::MachineFirmware::kAuto;
    auto machine = gs360::OpenMachine(gs360::MachineFirmware::kAuto, cnc.PtyPath(), o, &f);
    CHECK(f == gs360::MachineFirmware::kGrbl);
    // The welcome read by the detection is the handshake's too: no soft reset was needed.
    CHECK_THAT(machine->Connect().firmware, Catch::StartsWith("Grbl 1.1h"));
    CHECK(cnc.Stats().resets == 0);
  }
  SECTION("a Marlin printer that reboots when its port opens") {
    gs360::VirtualCncOptions p = Printer(0.0);
    p.reset_on_open = true;
    p.boot_delay = milliseconds(100);
    gs360::VirtualCnc printer(p);
    gs360::MachineFirmware f = gs360::MachineFirmware::kAuto;
    auto machine = gs360::OpenMachine(gs360::MachineFirmware::kAuto, printer.PtyPath(), o, &f);
    CHECK(f == gs360::MachineFirmware::kMarlin);
    machine->Connect();
    CHECK(machine->PositionLost());     // the start the detection read is the handshake's too
    CHECK(printer.Stats().boots == 2);  // power-up, the one open: not rebooted twice
  }
  SECTION("silent ones are asked M115, and the answer is not left for the session") {
    gs360::VirtualCnc printer(Printer(0.0));
    ReadBoot(printer);
    gs360::MachineFirmware f = gs360::MachineFirmware::kAuto;
    auto machine = gs360::OpenMachine(gs360::MachineFirmware::kAuto, printer.PtyPath(), o, &f);
    CHECK(f == gs360::MachineFirmware::kMarlin);
    machine->Connect();
    CHECK_FALSE(machine->PositionLost());
    machine->MarkPositionTrusted();
    CHECK(machine->Send("G53 G0 X1.000 Y2.000 Z3.000").Wait(milliseconds(2000)).Ok());
    const auto status = machine->QueryStatus(milliseconds(2000));
    REQUIRE(status);
    CHECK(Near(*status->machine_position, {1.0, 2.0, 3.0}, 0.01));

    gs360::VirtualCncOptions g;
    g.time_scale = 0.0;
    gs360::VirtualCnc cnc(g);
    ReadBoot(cnc);
    CHECK(gs360::OpenMachine(gs360::MachineFirmware::kAuto, cnc.PtyPath(), o, &f) != nullptr);
    CHECK(f == gs360::MachineFirmware::kGrbl);
  }
  SECTION("a port where nothing answers is an error naming it") {
    gs360::Pty silent = gs360::Pty::Open();
    CHECK_THROWS_WITH(
        gs360::OpenMachine(gs360::MachineFirmware::kAuto, silent.slave_path(), o),
        Catch::Contains(silent.slave_path()) && Catch::Contains("set [machine] firmware"));
  }
}
