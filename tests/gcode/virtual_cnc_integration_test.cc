// GrblClient driving the virtual CNC (sim/) through its pty: homing, pipelined presses with the
// G4 sync rule checked against the machine's true position, a soft-limit alarm that arrives
// before its line's ok, and a USB unplug that comes back under a new pty path.

#include <catch2/catch.hpp>

#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "gcode/grbl_client.h"
#include "sim/virtual_cnc.h"
#include "tests/wait.h"

using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;
using gs360::GrblClient;
using gs360::GrblClientOptions;
using gs360::GrblReply;
using gs360::GrblReplyKind;
using gs360::VirtualCnc;
using gs360::VirtualCncOptions;

namespace {

constexpr double kTimeScale = 10.0;  // machine seconds per wall second

VirtualCncOptions CncOptions() {
  VirtualCncOptions o;
  o.time_scale = kTimeScale;
  o.initial_true_position = Eigen::Vector3d(-20.0, -15.0, -5.0);
  return o;
}

GrblClientOptions ClientOptions() {
  GrblClientOptions o;
  o.welcome_timeout = 1500ms;
  o.query_timeout = 3000ms;
  o.homing_timeout = 30000ms;
  o.status_poll_interval = 200ms;
  o.reconnect_backoff_initial = 20ms;
  o.reconnect_backoff_max = 200ms;
  return o;
}

GrblClient::TransportFactory CurrentPty(const VirtualCnc& cnc) {
  return [&cnc] {
    const std::string path = cnc.PtyPath();
    if (path.empty()) throw gs360::TransportError("virtual CNC unplugged");
    return gs360::OpenTransport(path, gs360::TransportOptions{});
  };
}

Clock::duration Wall(double machine_seconds) {
  return std::chrono::duration_cast<Clock::duration>(
      std::chrono::duration<double>(machine_seconds / kTimeScale));
}

// One press: approach, press, dwell pipelined; the frame after the dwell's ok; then the
// retract. Checks the sync rule against the true position; returns the dwell's reply.
GrblReply PressAndCheck(GrblClient& client, const VirtualCnc& cnc, const gs360::PressMotion& m) {
  const gs360::PressGcode g = gs360::MakePressGcode(m);
  client.Send(g.approach);
  client.Send(g.press);
  const gs360::GrblHandle dwell = client.Send(g.dwell);
  const GrblReply ok = client.WaitForOk(dwell, 20s);
  REQUIRE(ok.Ok());
  const Clock::time_point frame_time = Clock::now();  // "take the frame" here
  INFO("press at " << m.press.transpose());
  // When the ok was read the machine stood at the press point, and had for most of the dwell.
  CHECK((cnc.TruePosition(ok.received_at) - m.press).norm() < 0.01);
  CHECK((cnc.TruePosition(ok.received_at - Wall(0.8 * m.dwell_s)) - m.press).norm() < 0.01);
  CHECK(cnc.TrueSpeed(ok.received_at) == Approx(0.0).margin(1e-9));
  // The dwell line itself was sent while the machine was still far away (pipelined), so the
  // ok really waited for the motion.
  CHECK((cnc.TruePosition(ok.sent_at) - m.press).norm() > 1.0);
  // The frame is taken before the retract is sent: the machine is still pressing.
  CHECK((cnc.TruePosition(frame_time) - m.press).norm() < 0.01);
  const gs360::GrblHandle retract = client.Send(g.retract);
  CHECK(client.WaitForOk(retract, 5s).Ok());
  return ok;
}

}  // namespace

TEST_CASE("client and virtual CNC: homing, pipelined presses and the G4 sync rule",
          "[grbl_client][virtual_cnc]") {
  VirtualCnc cnc(CncOptions());
  GrblClient client(CurrentPty(cnc), ClientOptions());
  const gs360::GrblMachineInfo info = client.Connect();
  CHECK(info.rx_buffer_bytes == 128);
  CHECK(info.rx_buffer_from_firmware);
  CHECK(info.planner_blocks == 15);
  CHECK(info.Setting(110) == Approx(cnc.Settings().max_rate_mm_per_min.x()));
  CHECK(info.Setting(122) == Approx(cnc.Settings().acceleration_mm_per_s2.z()));
  // Homing enabled: the controller starts in Alarm and nothing moves before $H.
  CHECK(client.Alarmed());
  CHECK(client.Send("G53 G0 X-10").Wait(2s).kind == GrblReplyKind::kRefused);
  const GrblReply homed = client.Home();
  REQUIRE(homed.Ok());
  CHECK(client.PositionTrusted());
  CHECK_FALSE(client.Alarmed());
  const Eigen::Vector3d home = cnc.TruePositionNow();
  CHECK(client.VerifyPosition(home, 0.01, 5s).ok);

  std::vector<gs360::PressMotion> presses;
  for (int i = 0; i < 4; ++i) {
    gs360::PressMotion m;
    m.approach = Eigen::Vector3d(-30.0 - 12.0 * i, -25.0 - 5.0 * (i % 2), -10.0);
    m.press = m.approach + Eigen::Vector3d(0.0, 0.0, -2.5);
    m.press_feed_mm_min = 120.0;
    m.dwell_s = 0.5;
    presses.push_back(m);
  }
  for (const auto& m : presses) PressAndCheck(client, cnc, m);

  CHECK(client.WaitIdle(10s) == gs360::GrblWaitResult::kIdle);
  const auto verified = client.VerifyPosition(presses.back().approach, 0.01, 5s);
  CHECK(verified.ok);
  CHECK((cnc.TruePositionNow() - presses.back().approach).norm() < 0.01);
  const auto latest = client.LatestStatus();
  REQUIRE(latest);
  CHECK(Clock::now() - latest->received_at < gs360::test::Scaled(2s));  // the poller keeps it fresh
  CHECK(cnc.Stats().rx_overflow_dropped == 0);
  CHECK(cnc.Stats().errors == 0);
}

TEST_CASE("client and virtual CNC: a soft-limit ALARM:2 before the ok, reset, re-verify",
          "[grbl_client][virtual_cnc]") {
  VirtualCnc cnc(CncOptions());
  GrblClient client(CurrentPty(cnc), ClientOptions());
  client.Connect();
  REQUIRE(client.Home().Ok());
  const Eigen::Vector3d home = cnc.ReportedPosition();

  const gs360::GrblHandle outside = client.Send("G53 G0 X10.000 Y-5.000");  // beyond X travel
  const gs360::GrblHandle next = client.Send("G53 G0 X-5.000");
  REQUIRE(gs360::test::WaitUntil([&] { return client.ResetRequired(); }, 5s));
  CHECK(client.LastAlarm() == 2);
  CHECK(client.Alarmed());
  CHECK_FALSE(outside.Done());  // GRBL holds the line's reply until the reset
  CHECK(client.Send("G4 P0").Wait(1s).kind == GrblReplyKind::kRefused);

  REQUIRE(client.SoftReset());
  const GrblReply r = outside.Wait(2s);
  INFO(r.Describe());
  CHECK(r.kind == GrblReplyKind::kOk);
  CHECK(r.alarm_code == 2);
  CHECK(next.Wait(2s).kind == GrblReplyKind::kReset);  // flushed by the reset, never answered
  CHECK_FALSE(client.PositionTrusted());
  // Alarm after the reset until $X / $H ([MSG:'$H'|'$X' to unlock] follows the welcome).
  CHECK(gs360::test::WaitUntil([&] { return client.Alarmed(); }, 2s));

  // A soft limit keeps the position: unlock and re-verify instead of re-homing.
  REQUIRE(client.Unlock().Ok());
  const auto verified = client.VerifyPosition(home, 0.01, 5s);
  INFO(verified.detail);
  REQUIRE(verified.ok);
  CHECK(client.PositionTrusted());
  gs360::PressMotion m;
  m.approach = Eigen::Vector3d(-40.0, -30.0, -8.0);
  m.press = Eigen::Vector3d(-40.0, -30.0, -10.0);
  m.dwell_s = 0.3;
  PressAndCheck(client, cnc, m);
}

TEST_CASE("client and virtual CNC: a USB unplug mid-run, replug under a new path, re-home",
          "[grbl_client][virtual_cnc]") {
  VirtualCnc cnc(CncOptions());
  GrblClient client(CurrentPty(cnc), ClientOptions());
  client.Connect();
  REQUIRE(client.Home().Ok());
  gs360::PressMotion m;
  m.approach = Eigen::Vector3d(-50.0, -40.0, -12.0);
  m.press = Eigen::Vector3d(-50.0, -40.0, -14.0);
  m.dwell_s = 0.3;
  PressAndCheck(client, cnc, m);

  // Unplug while a long move is in flight.
  const gs360::GrblHandle moving = client.Send("G53 G0 X-200.000 Y-100.000");
  REQUIRE(client.WaitForOk(moving, 2s).Ok());
  const std::string old_path = cnc.PtyPath();
  gs360::UnplugOptions unplug;
  unplug.power_loss = true;
  unplug.replug_after = 300ms;
  const gs360::GrblHandle lost = client.Send("G4 P5");
  cnc.Unplug(unplug);
  CHECK(lost.Wait(3s).kind == GrblReplyKind::kDisconnected);
  CHECK_FALSE(client.Connected());

  REQUIRE(client.Reconnect(5s));  // the factory reads the new PtyPath()
  CHECK(cnc.PtyPath() != old_path);
  CHECK_FALSE(client.PositionTrusted());
  CHECK(client.Alarmed());  // powered up again: Alarm until homed
  CHECK(client.Send(gs360::MakePressGcode(m).approach).Wait(1s).kind == GrblReplyKind::kRefused);
  REQUIRE(client.Home().Ok());
  PressAndCheck(client, cnc, m);
}
