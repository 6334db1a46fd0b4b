// GrblClient against a scripted GRBL peer on a real pseudo-terminal (and once over TCP).

#include <catch2/catch.hpp>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <pty.h>
#include <sys/socket.h>
#include <termios.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "base/format.h"
#include "gcode/grbl_client.h"
#include "tests/gcode/fake_grbl.h"
#include "tests/wait.h"

using namespace std::chrono_literals;
using gs360::FakeGrbl;
using gs360::FakeGrblOptions;
using gs360::GrblClient;
using gs360::GrblClientOptions;
using gs360::GrblHandle;
using gs360::GrblReply;
using gs360::GrblReplyKind;

namespace {

GrblClientOptions FastOptions() {
  GrblClientOptions o;
  o.welcome_timeout = 500ms;
  o.reset_timeout = 1500ms;
  o.query_timeout = 3000ms;
  o.homing_timeout = 5000ms;
  o.status_poll_interval = 0ms;  // off unless a test needs it: keeps the recorded stream clean
  o.reconnect_backoff_initial = 20ms;
  o.reconnect_backoff_max = 200ms;
  return o;
}

GrblClient::TransportFactory PtyFactory(const std::string& path) {
  return [path] { return gs360::OpenTransport(path, gs360::TransportOptions{}); };
}

// Waits for every handle; returns the replies in order.
std::vector<GrblReply> WaitAll(const std::vector<GrblHandle>& handles,
                               std::chrono::milliseconds timeout = 10s) {
  std::vector<GrblReply> replies;
  for (const auto& h : handles) replies.push_back(h.Wait(timeout));
  return replies;
}

std::size_t LinesAfter(const FakeGrbl& fake, std::size_t before) {
  return fake.Lines().size() - before;
}

}  // namespace

TEST_CASE("Connect reads the RX size from $I and streams within it", "[grbl_client]") {
  const int rx = GENERATE(128, 256);
  FakeGrblOptions fo;
  fo.rx_size = rx;
  auto fake = FakeGrbl::CreatePty(fo);
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  const gs360::GrblMachineInfo info = client.Connect();
  CHECK(info.firmware == "Grbl");
  CHECK(info.version == "1.1h");
  CHECK(info.build == "1.1h.20190830");
  CHECK(info.rx_buffer_bytes == rx);
  CHECK(info.rx_buffer_from_firmware);
  CHECK(info.planner_blocks == 15);
  CHECK(info.Setting(110) == 3000.0);
  CHECK(info.Setting(122) == 100.0);
  CHECK(info.Setting(22) == 1.0);
  CHECK_FALSE(info.Setting(999));
  CHECK(client.StreamCapacity() == static_cast<std::size_t>(rx - 1));
  // The output of a query is collected on its reply.
  const GrblReply settings = client.Send("$$").Wait(2s);
  REQUIRE(settings.Ok());
  REQUIRE(settings.messages.size() == 13);
  CHECK(settings.messages[4] == "$110=3000.000");
  const GrblReply build = client.Send("$I").Wait(2s);
  REQUIRE(build.messages.size() == 2);
  CHECK(build.messages[1] == "[OPT:V,15," + std::to_string(rx) + "]");
  CHECK_FALSE(client.PositionTrusted());
  REQUIRE(client.Home().Ok());
  CHECK(client.PositionTrusted());

  // Lines of varying length; with the peer paused, exactly the prefix that fits is sent.
  std::vector<std::string> lines;
  for (int i = 0; i < 200; ++i) {
    lines.push_back("G1 X" + std::to_string(i * 7 % 1000) + ".500 Y-" + std::to_string(i % 13) +
                    ".25 F" + std::to_string(100 + i % 3 * 1000));
  }
  std::size_t fit = 0;
  std::size_t fit_bytes = 0;
  while (fit < lines.size() && fit_bytes + lines[fit].size() + 1 <= client.StreamCapacity()) {
    fit_bytes += lines[fit].size() + 1;
    ++fit;
  }
  fake->SetProcessing(false);
  const std::size_t before = fake->Lines().size();
  std::vector<GrblHandle> handles;
  for (const auto& l : lines) handles.push_back(client.Send(l));
  REQUIRE(FakeGrbl::WaitUntil([&] { return LinesAfter(*fake, before) >= fit; }, 3s));
  std::this_thread::sleep_for(100ms);  // nothing more may arrive while nothing is answered
  CHECK(LinesAfter(*fake, before) == fit);
  CHECK(client.InFlightBytes() == fit_bytes);
  CHECK(client.QueuedLines() == lines.size() - fit);
  CHECK(fake->MaxOutstandingBytes() == fit_bytes);
  CHECK(fit_bytes > static_cast<std::size_t>(rx) - 30);  // the buffer really was used

  fake->SetProcessing(true);
  for (const GrblReply& r : WaitAll(handles)) REQUIRE(r.kind == GrblReplyKind::kOk);
  CHECK_FALSE(fake->Overflowed());
  CHECK(fake->MaxOutstandingBytes() <= static_cast<std::size_t>(rx - 1));
  CHECK(client.Stats().max_in_flight_bytes <= static_cast<std::size_t>(rx - 1));
  if (rx == 256) CHECK(fake->MaxOutstandingBytes() > 128);  // $I's size was used, not 128
  const auto received = fake->Lines();
  REQUIRE(received.size() == before + lines.size());
  for (std::size_t i = 0; i < lines.size(); ++i) CHECK(received[before + i].line == lines[i]);
}

TEST_CASE("without [OPT] sizes the client counts against 128 bytes", "[grbl_client]") {
  FakeGrblOptions fo;
  fo.rx_size = 256;
  fo.report_opt = false;
  fo.line_delay = 200us;
  auto fake = FakeGrbl::CreatePty(fo);
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  const auto info = client.Connect();
  CHECK(info.rx_buffer_bytes == 128);
  CHECK_FALSE(info.rx_buffer_from_firmware);
  client.MarkPositionTrusted();
  std::vector<GrblHandle> handles;
  for (int i = 0; i < 100; ++i) handles.push_back(client.Send("G1 X1.000 Y2.000 Z-3.000 F500"));
  for (const auto& r : WaitAll(handles)) REQUIRE(r.Ok());
  CHECK(fake->MaxOutstandingBytes() <= 127);
  CHECK(fake->MaxOutstandingBytes() >= 90);
}

TEST_CASE("a controller without a welcome is asked before it is reset, a dead one a clear error",
          "[grbl_client]") {
  SECTION("no welcome on open, but it answers a status query: taken as it is, no reset") {
    // A controller still running (perhaps still moving) after its last host died: a reset would
    // stop it dead and lose its position.
    FakeGrblOptions fo;
    fo.welcome_on_start = false;
    auto fake = FakeGrbl::CreatePty(fo);
    GrblClientOptions o = FastOptions();
    o.welcome_timeout = 150ms;
    GrblClient client(PtyFactory(fake->Path()), o);
    CHECK(client.Connect().version == "1.1h");
    CHECK(fake->CountRealtime('?') >= 1);
    CHECK(fake->CountRealtime('\x18') == 0);
    CHECK(client.Stats().resets == 0);
    CHECK_FALSE(client.PositionTrusted());
    CHECK(client.Send("G4 P0").Wait(1s).Ok());
  }
  SECTION("nothing answers") {
    int master = -1;
    int slave = -1;
    char name[256] = {};
    termios raw{};
    ::cfmakeraw(&raw);
    REQUIRE(::openpty(&master, &slave, name, &raw, nullptr) == 0);
    GrblClientOptions o = FastOptions();
    o.welcome_timeout = 100ms;
    o.reset_timeout = 200ms;
    GrblClient client(PtyFactory(name), o);
    CHECK_THROWS_WITH(client.Connect(),
                      Catch::Contains("no GRBL welcome") && Catch::Contains(std::string(name)));
    CHECK_FALSE(client.Connected());
    ::close(master);
    ::close(slave);
  }
}

TEST_CASE("real-time bytes go out at once while the RX buffer is full", "[grbl_client]") {
  auto fake = FakeGrbl::CreatePty();
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  client.Connect();
  REQUIRE(client.Home().Ok());
  fake->SetProcessing(false);
  std::vector<GrblHandle> handles;
  for (int i = 0; i < 20; ++i) handles.push_back(client.Send("G1 X10.000 Y10.000 F300"));
  REQUIRE(FakeGrbl::WaitUntil([&] { return fake->Pending() == 5; }, 2s));  // 5 x 24 bytes fit
  REQUIRE(client.QueuedLines() == 15);

  REQUIRE(client.FeedHold());
  REQUIRE(FakeGrbl::WaitUntil([&] { return fake->CountRealtime('!') == 1; }, 2s));
  const auto status = client.QueryStatus(2s);
  REQUIRE(status);
  CHECK(status->status.state == gs360::GrblMachineState::kHold);
  CHECK(status->status.substate == 0);
  REQUIRE(client.CycleStart());
  REQUIRE(FakeGrbl::WaitUntil([&] { return fake->CountRealtime('~') == 1; }, 2s));
  for (const auto& rt : fake->Realtime()) {
    if (rt.byte == '!' || rt.byte == '?' || rt.byte == '~') {
      CHECK(rt.unanswered_lines == 5);  // arrived while the buffer was full
    }
  }
  CHECK(client.QueuedLines() == 15);  // the lines themselves still wait for room

  // A soft reset voids everything at once.
  CHECK(client.SoftReset());
  CHECK(fake->CountRealtime('\x18') == 1);
  for (const auto& r : WaitAll(handles, 1s)) CHECK(r.kind == GrblReplyKind::kReset);
  CHECK(client.InFlightBytes() == 0);
  CHECK_FALSE(client.PositionTrusted());
  fake->SetProcessing(true);
}

TEST_CASE("error:N resolves only its own line and the stream goes on", "[grbl_client]") {
  auto fake = FakeGrbl::CreatePty();
  fake->SetResponder([](const std::string& line) -> std::optional<std::vector<std::string>> {
    if (line == "G65 P1") return std::vector<std::string>{"error:20"};
    return std::nullopt;
  });
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  client.Connect();
  REQUIRE(client.Home().Ok());
  std::vector<GrblHandle> handles;
  for (int i = 0; i < 12; ++i) {
    handles.push_back(client.Send(i == 5 ? "G65 P1" : "G1 X" + std::to_string(i) + " F100"));
  }
  const auto replies = WaitAll(handles);
  for (std::size_t i = 0; i < replies.size(); ++i) {
    INFO(replies[i].Describe());
    CHECK(replies[i].sequence == handles[i].Sequence());
    CHECK(replies[i].line == handles[i].Line());
    if (i == 5) {
      CHECK(replies[i].kind == GrblReplyKind::kError);
      CHECK(replies[i].error_code == 20);
      CHECK(replies[i].detail.find("Unsupported") != std::string::npos);
    } else {
      CHECK(replies[i].kind == GrblReplyKind::kOk);
    }
  }
  CHECK_FALSE(client.Alarmed());
  CHECK(fake->Position().x() == 11.0);
}

TEST_CASE("an ALARM before the ok is attributed to its line, the reset after it voids the rest",
          "[grbl_client]") {
  auto fake = FakeGrbl::CreatePty();
  // GRBL 1.1 soft limit: ALARM:2 and [MSG:Reset to continue], then nothing until the host's
  // reset; then the offending line's ok, the welcome, and the start-up alarm message.
  fake->SetResponder([](const std::string& line) -> std::optional<std::vector<std::string>> {
    if (line == "G1 X999 F100") {
      return std::vector<std::string>{
          "ALARM:2", "[MSG:Reset to continue]", gs360::kFakeWaitReset,
          "ok",      gs360::kFakeWelcome,       "[MSG:'$H'|'$X' to unlock]"};
    }
    return std::nullopt;
  });
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  client.Connect();
  REQUIRE(client.Home().Ok());
  fake->SetProcessing(false);
  std::vector<GrblHandle> handles = {client.Send("G1 X1 F100"), client.Send("G1 X999 F100"),
                                     client.Send("G1 X2 F100"), client.Send("G1 X3 F100")};
  REQUIRE(FakeGrbl::WaitUntil([&] { return fake->Pending() == 4; }, 2s));
  fake->SetProcessing(true);
  REQUIRE(FakeGrbl::WaitUntil([&] { return client.ResetRequired(); }, 2s));
  CHECK(client.Alarmed());
  CHECK(client.LastAlarm() == 2);
  CHECK(handles[0].Wait(1s).kind == GrblReplyKind::kOk);
  CHECK_FALSE(handles[1].Done());  // its reply comes after the reset
  const GrblReply blocked = client.Send("G4 P0").Wait(1s);
  CHECK(blocked.kind == GrblReplyKind::kRefused);
  CHECK(blocked.detail.find("reset") != std::string::npos);

  REQUIRE(client.SoftReset());
  const auto replies = WaitAll(handles);
  CHECK_FALSE(replies[0].alarm_code);
  CHECK(replies[1].kind == GrblReplyKind::kOk);  // its own reply...
  CHECK(replies[1].alarm_code == 2);             // ...with the alarm that preceded it
  CHECK(replies[2].kind == GrblReplyKind::kReset);
  CHECK(replies[3].kind == GrblReplyKind::kReset);
  CHECK_FALSE(replies[2].alarm_code);

  REQUIRE(FakeGrbl::WaitUntil([&] { return client.Alarmed(); }, 2s));  // [MSG:..to unlock]
  CHECK_FALSE(client.ResetRequired());
  CHECK_FALSE(client.PositionTrusted());  // the reset lost it
  const GrblReply refused = client.Send("G1 X1 F100").Wait(1s);
  CHECK(refused.kind == GrblReplyKind::kRefused);
  CHECK(refused.detail.find("alarm") != std::string::npos);
  REQUIRE(client.Unlock().Ok());
  CHECK_FALSE(client.Alarmed());
  // Unlocked but still not homed since the reset: motion stays refused.
  CHECK(client.Send("G1 X1 F100").Wait(1s).kind == GrblReplyKind::kRefused);
  CHECK(client.Send("G4 P0").Wait(2s).kind == GrblReplyKind::kOk);  // non-motion is fine
  REQUIRE(client.Home().Ok());
  CHECK(client.Send("G1 X1 F100").Wait(2s).kind == GrblReplyKind::kOk);
}

TEST_CASE("a probe alarm: in-flight lines get error:9, queued lines are not sent",
          "[grbl_client]") {
  auto fake = FakeGrbl::CreatePty();
  fake->SetResponder([](const std::string& line) -> std::optional<std::vector<std::string>> {
    if (line.rfind("G38.2", 0) == 0) return std::vector<std::string>{"ALARM:5", "ok"};
    return std::nullopt;
  });
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  client.Connect();
  REQUIRE(client.Home().Ok());
  fake->SetProcessing(false);
  std::vector<GrblHandle> handles = {client.Send("G38.2 Z-10.000 F10")};                // 19 bytes
  for (int i = 0; i < 7; ++i) handles.push_back(client.Send("G1 X1.000 Y1.000 F100"));  // 22
  REQUIRE(FakeGrbl::WaitUntil([&] { return fake->Pending() == 5; }, 2s));  // 19 + 4 x 22 = 107
  REQUIRE(client.QueuedLines() == 3);
  fake->SetProcessing(true);
  const auto replies = WaitAll(handles);
  CHECK(replies[0].kind == GrblReplyKind::kOk);
  CHECK(replies[0].alarm_code == 5);
  for (int i = 1; i <= 4; ++i) {
    CHECK(replies[static_cast<std::size_t>(i)].kind == GrblReplyKind::kError);
    CHECK(replies[static_cast<std::size_t>(i)].error_code == 9);
  }
  for (int i = 5; i <= 7; ++i) {
    CHECK(replies[static_cast<std::size_t>(i)].kind == GrblReplyKind::kRefused);
    CHECK(replies[static_cast<std::size_t>(i)].detail.find("ALARM:5") != std::string::npos);
  }
  CHECK(fake->Lines().size() == 3 + 5);  // $I $$ $H + the five that fitted
  CHECK(client.Alarmed());
  CHECK(client.PositionTrusted());  // a probe failure keeps the position
  CHECK(client.Send("G1 X0 F100").Wait(1s).kind == GrblReplyKind::kRefused);
  REQUIRE(client.Unlock().Ok());
  CHECK(client.Send("G1 X0 F100").Wait(2s).kind == GrblReplyKind::kOk);
}

TEST_CASE("a welcome line mid-job voids every line in flight", "[grbl_client]") {
  auto fake = FakeGrbl::CreatePty();
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  client.Connect();
  REQUIRE(client.Home().Ok());
  fake->SetProcessing(false);
  std::vector<GrblHandle> handles;
  for (int i = 0; i < 8; ++i) handles.push_back(client.Send("G1 X1.000 Y1.000 F100"));
  REQUIRE(FakeGrbl::WaitUntil([&] { return fake->Pending() == 5; }, 2s));
  fake->ResetAndWelcome();
  for (const auto& r : WaitAll(handles, 2s)) {
    CHECK(r.kind == GrblReplyKind::kReset);
    CHECK(r.received_at >= r.sent_at);
  }
  CHECK(client.InFlightBytes() == 0);
  CHECK(client.QueuedLines() == 0);
  CHECK_FALSE(client.PositionTrusted());
  CHECK(client.Stats().resets == 2);  // the connect welcome and this one
  fake->SetProcessing(true);
  CHECK(client.Send("G1 X1 F100").Wait(1s).kind == GrblReplyKind::kRefused);
  CHECK(client.Send("G4 P0").Wait(2s).kind == GrblReplyKind::kOk);
  REQUIRE(client.Home().Ok());
  handles.clear();
  for (int i = 0; i < 30; ++i) handles.push_back(client.Send("G1 X2.000 Y2.000 F100"));
  for (const auto& r : WaitAll(handles)) CHECK(r.Ok());
  CHECK_FALSE(fake->Overflowed());  // the byte count restarted from zero, as GRBL's buffer did
}

TEST_CASE("status polling never exceeds 5 Hz", "[grbl_client]") {
  GrblClientOptions bad = FastOptions();
  bad.status_poll_interval = 100ms;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("status_poll_interval") &&
                                     Catch::Contains(">= status_min_interval (200 ms)"));
  bad.status_min_interval = 100ms;  // a faster controller: allowed down to its own minimum
  CHECK_NOTHROW(bad.Check());
  bad.status_min_interval = 0ms;
  CHECK_THROWS_WITH(bad.Check(),
                    Catch::Contains("status_min_interval must be in 1..1000 ms, got 0"));

  auto fake = FakeGrbl::CreatePty();
  GrblClientOptions o = FastOptions();
  o.status_poll_interval = 200ms;
  GrblClient client(PtyFactory(fake->Path()), o);
  client.Connect();
  const std::size_t before = fake->CountRealtime('?');
  const auto start = std::chrono::steady_clock::now();
  // The poller plus a caller hammering QueryStatus share one 5 Hz budget.
  std::atomic<int> answered{0};
  std::thread hammer([&] {
    while (std::chrono::steady_clock::now() - start < 1500ms) {
      if (client.QueryStatus(1s)) ++answered;
    }
  });
  hammer.join();
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const std::size_t requests = fake->CountRealtime('?') - before;
  INFO("requests " << requests << " in " << seconds << " s");
  CHECK(static_cast<double>(requests) <= seconds * 5.0 + 1.0);
  CHECK(requests >= 4);
  CHECK(answered >= 3);
  const auto latest = client.LatestStatus();
  REQUIRE(latest);
  CHECK(latest->status.state == gs360::GrblMachineState::kIdle);
  REQUIRE(latest->machine_position);
  // Fresh: the poller asks every 200 ms (a slower sanitizer build gets GS360_TEST_TIME_SCALE).
  CHECK(std::chrono::steady_clock::now() - latest->received_at < gs360::test::Scaled(1s));
  CHECK(client.Stats().status_requests == requests);
}

TEST_CASE("settings writes are sent one at a time", "[grbl_client]") {
  FakeGrblOptions fo;
  fo.line_delay = 2ms;
  auto fake = FakeGrbl::CreatePty(fo);
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  client.Connect();
  std::vector<std::string> lines;
  for (int i = 0; i < 5; ++i) lines.push_back("G4 P0");
  lines.push_back("$110=2500");
  for (int i = 0; i < 5; ++i) lines.push_back("G4 P0");
  lines.push_back("G10 L20 P1 X0 Y0 Z0");
  for (int i = 0; i < 4; ++i) lines.push_back("G4 P0");
  lines.push_back("$120=150.5");
  lines.push_back("G4 P0");
  const std::size_t before = fake->Lines().size();
  std::vector<GrblHandle> handles;
  for (const auto& l : lines) handles.push_back(client.Send(l));
  for (const auto& r : WaitAll(handles)) REQUIRE(r.Ok());
  const auto received = fake->Lines();
  REQUIRE(received.size() == before + lines.size());
  std::size_t pipelined = 0;
  for (std::size_t i = before; i < received.size(); ++i) {
    const std::string& l = received[i].line;
    const bool settings = l[0] == '$' || l.rfind("G10", 0) == 0;
    INFO(l << " arrived with " << received[i].unanswered_at_arrival << " unanswered");
    if (settings) CHECK(received[i].unanswered_at_arrival == 0);
    const bool after_settings =
        i > before && (received[i - 1].line[0] == '$' || received[i - 1].line.rfind("G10", 0) == 0);
    if (after_settings) CHECK(received[i].unanswered_at_arrival == 0);
    if (!settings && received[i].unanswered_at_arrival > 0) ++pipelined;
  }
  CHECK(pipelined > 0);  // ordinary lines were pipelined: the rule above is not vacuous
}

TEST_CASE("a vanished port is detected and the client reconnects to a new path", "[grbl_client]") {
  // Device names are symlinks to ptys, like udev's /dev/ttyUSB0 that comes back as /dev/ttyUSB1.
  const std::string base =
      std::string(GS360_BINARY_DIR) + "/gs360_test_ttyGRBL_" + std::to_string(::getpid()) + "_";
  const std::string name0 = base + "0";
  const std::string name1 = base + "1";
  ::unlink(name0.c_str());
  ::unlink(name1.c_str());
  // The resolver: whichever name exists now (FindPortByUsbId plays this role for real ports).
  auto resolve = [&]() -> std::unique_ptr<gs360::Transport> {
    for (const std::string& name : {name0, name1}) {
      if (::access(name.c_str(), F_OK) == 0) {
        return gs360::OpenTransport(name, gs360::TransportOptions{});
      }
    }
    throw gs360::TransportError("no GRBL device plugged in (yet)");
  };

  auto first = FakeGrbl::CreatePty();
  REQUIRE(::symlink(first->Path().c_str(), name0.c_str()) == 0);
  GrblClient client(resolve, FastOptions());
  client.Connect();
  REQUIRE(client.Home().Ok());
  first->SetProcessing(false);
  std::vector<GrblHandle> handles;
  for (int i = 0; i < 8; ++i) handles.push_back(client.Send("G1 X1.000 Y1.000 F100"));
  REQUIRE(FakeGrbl::WaitUntil([&] { return first->Pending() == 5; }, 2s));
  first->Close();  // USB unplug: the device and its name disappear
  ::unlink(name0.c_str());
  for (const auto& r : WaitAll(handles, 3s)) CHECK(r.kind == GrblReplyKind::kDisconnected);
  REQUIRE(FakeGrbl::WaitUntil([&] { return !client.Connected(); }, 2s));
  CHECK(client.Send("G4 P0").Wait(1s).kind == GrblReplyKind::kDisconnected);
  CHECK_FALSE(client.FeedHold());

  // The device comes back 300 ms later under the other name.
  std::unique_ptr<FakeGrbl> second;
  std::thread replug([&] {
    std::this_thread::sleep_for(300ms);
    second = FakeGrbl::CreatePty();
    ::symlink(second->Path().c_str(), name1.c_str());
  });
  std::atomic<int> attempts{0};
  std::string reopened;
  const bool ok = client.Reconnect(
      [&] {
        ++attempts;
        auto t = resolve();
        reopened = t->Describe();
        return t;
      },
      5s);
  replug.join();
  REQUIRE(ok);
  CHECK(attempts > 1);  // it retried while nothing was plugged in
  CHECK(client.Connected());
  CHECK(reopened == "termios " + name1);
  CHECK_FALSE(client.PositionTrusted());  // re-home or verify before any motion
  CHECK(client.Send("G1 X5 F100").Wait(1s).kind == GrblReplyKind::kRefused);
  REQUIRE(client.Home().Ok());
  CHECK(client.Send("G1 X5 F100").Wait(2s).kind == GrblReplyKind::kOk);
  CHECK(second->Position().x() == 5.0);
  ::unlink(name1.c_str());
}

TEST_CASE("Reconnect gives up at its timeout", "[grbl_client]") {
  auto fake = FakeGrbl::CreatePty();
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  client.Connect();
  fake->Close();
  const auto start = std::chrono::steady_clock::now();
  CHECK_FALSE(client.Reconnect(
      []() -> std::unique_ptr<gs360::Transport> { throw gs360::TransportError("unplugged"); },
      300ms));
  CHECK(std::chrono::steady_clock::now() - start >= 300ms);
  CHECK_FALSE(client.Connected());
}

TEST_CASE("WaitIdle and VerifyPosition read the machine position", "[grbl_client]") {
  auto fake = FakeGrbl::CreatePty();
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  client.Connect();
  REQUIRE(client.Home().Ok());
  REQUIRE(client.Send("G90 G1 X5.000 Y-6.000 Z-7.000 F100").Wait(2s).Ok());
  CHECK(client.WaitIdle(3s) == gs360::GrblWaitResult::kIdle);
  const auto good = client.VerifyPosition(Eigen::Vector3d(5, -6, -7), 0.01, 3s);
  CHECK(good.ok);
  REQUIRE(good.reported);
  CHECK(good.error_mm < 1e-9);
  const auto bad = client.VerifyPosition(Eigen::Vector3d(5, -6, 0), 0.01, 3s);
  CHECK_FALSE(bad.ok);
  CHECK(bad.error_mm == Approx(7.0));
  // After a reset the position is untrusted until verified.
  REQUIRE(client.SoftReset());
  CHECK_FALSE(client.PositionTrusted());
  CHECK(client.VerifyPosition(Eigen::Vector3d(5, -6, -7), 0.01, 3s).ok);
  CHECK(client.PositionTrusted());
  CHECK(client.Send("G1 X0 F100").Wait(2s).Ok());
}

TEST_CASE("WaitForOk gives the host time of the ok and times out while the line waits",
          "[grbl_client]") {
  auto fake = FakeGrbl::CreatePty();
  fake->SetResponder([](const std::string& line) -> std::optional<std::vector<std::string>> {
    if (line == "G4 P0.200") {
      std::this_thread::sleep_for(200ms);  // the dwell
      return std::vector<std::string>{"ok"};
    }
    return std::nullopt;
  });
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  client.Connect();
  REQUIRE(client.Home().Ok());
  const GrblHandle dwell = client.Send("G4 P0.200");
  const GrblReply r = client.WaitForOk(dwell, 3s);
  REQUIRE(r.Ok());
  CHECK(r.received_at - r.sent_at >= 200ms);
  CHECK(std::chrono::steady_clock::now() >= r.received_at);

  fake->SetProcessing(false);
  const GrblHandle held = client.Send("G4 P0");
  const GrblReply waiting = client.WaitForOk(held, 100ms);
  CHECK(waiting.kind == GrblReplyKind::kTimeout);
  CHECK_FALSE(held.Done());
  fake->SetProcessing(true);
  CHECK(client.WaitForOk(held, 2s).Ok());
  CHECK(held.Done());
}

TEST_CASE("garbage from the controller neither crashes nor desynchronises", "[grbl_client]") {
  auto fake = FakeGrbl::CreatePty();
  int n = 0;
  fake->SetResponder([&n](const std::string& line) -> std::optional<std::vector<std::string>> {
    if (line != "G4 P0") return std::nullopt;
    switch (n++ % 4) {
      case 0:
        return std::vector<std::string>{"\x01\x02%%garbage", "ok"};
      case 1:
        return std::vector<std::string>{"\xff\xfeok\x00"};
      case 2:
        return std::vector<std::string>{"<Idle|MPos:1.0,abc>", "[MSG:noise", "ok"};
      default:
        return std::vector<std::string>{std::string(3000, '#'), "ok"};
    }
  });
  std::atomic<int> heard{0};
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  client.SetMessageListener([&](const gs360::GrblMessage&) { ++heard; });
  client.Connect();
  std::vector<GrblHandle> handles;
  for (int i = 0; i < 40; ++i) handles.push_back(client.Send("G4 P0"));
  for (const auto& r : WaitAll(handles)) CHECK(r.Ok());
  fake->Emit("\x13\x11\xff\r\nnonsense\r\n");
  CHECK(client.Send("$I").Wait(2s).Ok());
  CHECK(client.Stats().unknown_lines >= 30);
  CHECK(client.InFlightBytes() == 0);
  CHECK(heard > 80);
  CHECK(client.Connected());
}

TEST_CASE("the motion guard tells motion from other lines", "[grbl_client]") {
  auto fake = FakeGrbl::CreatePty();
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  client.Connect();
  REQUIRE_FALSE(client.PositionTrusted());
  for (const char* motion : {"G0 X1", "g1x1f100", "X5", "G28", "G30", "$J=G91 X1 F100", "G53 G0 Z0",
                             "G1 Y-2 (probe) F100", "G38.2 Z-5 F10"}) {
    INFO(motion);
    const GrblReply r = client.Send(motion).Wait(1s);
    CHECK(r.kind == GrblReplyKind::kRefused);
    CHECK(r.detail.find("not trusted") != std::string::npos);
  }
  for (const char* other : {"G4 P0", "G10 L20 P1 X0 Y0 Z0", "G92 X0", "(move X5 later)", "G21 G90",
                            "M5", "G28.1", "; X9", "$G"}) {
    INFO(other);
    CHECK(client.Send(other).Wait(2s).kind == GrblReplyKind::kOk);
  }
  client.MarkPositionTrusted();
  CHECK(client.Send("G0 X1").Wait(2s).kind == GrblReplyKind::kOk);

  GrblClientOptions unguarded = FastOptions();
  unguarded.guard_motion = false;
  auto fake2 = FakeGrbl::CreatePty();
  GrblClient free_client(PtyFactory(fake2->Path()), unguarded);
  free_client.Connect();
  CHECK(free_client.Send("G0 X2").Wait(2s).kind == GrblReplyKind::kOk);
  CHECK(fake2->Position().x() == 2.0);
}

TEST_CASE("Send rejects lines that can never be sent", "[grbl_client]") {
  auto fake = FakeGrbl::CreatePty();
  GrblClient client(PtyFactory(fake->Path()), FastOptions());
  CHECK(client.Send("G4 P0").Wait(100ms).kind == GrblReplyKind::kDisconnected);
  client.Connect();
  CHECK_THROWS_AS(client.Send("G0 X1?"), std::invalid_argument);
  CHECK_THROWS_AS(client.Send("G0 X1\nG0 X2"), std::invalid_argument);
  CHECK_THROWS_AS(client.Send("G0 X1!"), std::invalid_argument);
  CHECK_THROWS_AS(client.Send(std::string(200, 'G')), std::invalid_argument);
  CHECK(client.Send("G4 P0").Wait(2s).Ok());
}

TEST_CASE("the client streams over TCP like over a serial port", "[grbl_client]") {
  const int listen_fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  REQUIRE(listen_fd >= 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  REQUIRE(::bind(listen_fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) == 0);
  REQUIRE(::listen(listen_fd, 1) == 0);
  socklen_t len = sizeof(addr);
  REQUIRE(::getsockname(listen_fd, reinterpret_cast<sockaddr*>(&addr), &len) == 0);
  const std::string uri = "tcp://127.0.0.1:" + std::to_string(ntohs(addr.sin_port));

  std::unique_ptr<FakeGrbl> fake;
  std::thread server([&] {
    const int fd = ::accept(listen_fd, nullptr, nullptr);
    FakeGrblOptions fo;
    fo.rx_size = 1024;  // grblHAL
    fo.line_delay = 100us;
    fake = std::make_unique<FakeGrbl>(fd, -1, "tcp", fo);
  });
  auto client = GrblClient::ForUri(uri, {}, FastOptions());
  const auto info = client->Connect();
  server.join();
  CHECK(info.rx_buffer_bytes == 1024);
  REQUIRE(client->Home().Ok());
  std::vector<GrblHandle> handles;
  for (int i = 0; i < 200; ++i) handles.push_back(client->Send("G1 X1.000 Y2.000 Z3.000 F1000"));
  for (const auto& r : WaitAll(handles)) CHECK(r.Ok());
  CHECK_FALSE(fake->Overflowed());
  CHECK(fake->MaxOutstandingBytes() > 128);
  CHECK(fake->MaxOutstandingBytes() <= 1023);
  fake->Close();
  CHECK(FakeGrbl::WaitUntil([&] { return !client->Connected(); }, 2s));
  ::close(listen_fd);
}

TEST_CASE("press G-code is formatted with fixed decimals", "[grbl_client]") {
  gs360::PressMotion m;
  m.approach = Eigen::Vector3d(10.0, -20.5, 3.25);
  m.press = Eigen::Vector3d(10.0001, -0.0001, 1.2496);
  m.press_feed_mm_min = 60.0;
  m.dwell_s = 0.3;
  const gs360::PressGcode g = gs360::MakePressGcode(m);
  CHECK(g.approach == "G90 G53 G0 X10.000 Y-20.500 Z3.250");
  CHECK(g.press == "G53 G1 X10.000 Y0.000 Z1.250 F60.0");
  CHECK(g.dwell == "G4 P0.300");
  CHECK(g.retract == "G53 G0 X10.000 Y-20.500 Z3.250");
  m.machine_coordinates = false;
  m.retract_feed_mm_min = 300.0;
  const gs360::PressGcode w = gs360::MakePressGcode(m);
  CHECK(w.approach == "G90 G0 X10.000 Y-20.500 Z3.250");
  CHECK(w.retract == "G1 X10.000 Y-20.500 Z3.250 F300.0");
  CHECK(gs360::FormatFixed(-0.0004, 3) == "0.000");
  CHECK(gs360::FormatFixed(-1234.5678, 3) == "-1234.568");
  m.press_feed_mm_min = 0.0;
  CHECK_THROWS_WITH(gs360::MakePressGcode(m), Catch::Contains("press_feed_mm_min"));
  m.press_feed_mm_min = 60.0;
  m.dwell_s = -1.0;
  CHECK_THROWS_WITH(gs360::MakePressGcode(m), Catch::Contains("dwell_s"));
  m.dwell_s = 0.3;
  m.press.x() = std::nan("");
  CHECK_THROWS_WITH(gs360::MakePressGcode(m), Catch::Contains("press"));
}
