// The virtual CNC driven through its real pseudo-terminal, as a host would drive a GRBL board.
#include <catch2/catch.hpp>

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <termios.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <deque>
#include <functional>
#include <iostream>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "sim/virtual_cnc.h"
#include "tests/wait.h"

using gs360::CncFirmware;
using gs360::FaultDirection;
using gs360::GrblState;
using gs360::VirtualCnc;
using gs360::VirtualCncOptions;
using Clock = std::chrono::steady_clock;

namespace {

double Seconds(Clock::duration d) {
  return std::chrono::duration<double>(d).count();
}

// A host on the slave side of the pty: raw termios, line-oriented reads with arrival times.
class Host {
 public:
  explicit Host(const std::string& path) {
    fd_ = ::open(path.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK);
    REQUIRE(fd_ >= 0);
    termios t;
    REQUIRE(::tcgetattr(fd_, &t) == 0);
    ::cfmakeraw(&t);
    ::cfsetispeed(&t, B115200);
    ::cfsetospeed(&t, B115200);
    REQUIRE(::tcsetattr(fd_, TCSANOW, &t) == 0);
  }
  ~Host() {
    if (fd_ >= 0) ::close(fd_);
  }
  Host(const Host&) = delete;
  Host& operator=(const Host&) = delete;

  void Send(const std::string& s) {
    std::size_t done = 0;
    while (done < s.size()) {
      const ssize_t n = ::write(fd_, s.data() + done, s.size() - done);
      if (n > 0) {
        done += static_cast<std::size_t>(n);
      } else if (n < 0 && errno == EAGAIN) {
        pollfd p = {fd_, POLLOUT, 0};
        ::poll(&p, 1, 100);
      } else {
        FAIL("write to the pty failed");
      }
    }
  }

  // Next non-empty line without its CR/LF, or nullopt after `timeout_s` (or at EOF).
  std::optional<std::string> Line(double timeout_s = 3.0) {
    const Clock::time_point deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                                          std::chrono::duration<double>(timeout_s));
    while (true) {
      const std::size_t nl = buffer_.find('\n');
      if (nl != std::string::npos) {
        std::string line = buffer_.substr(0, nl);
        buffer_.erase(0, nl + 1);
        if (!line.empty() && line.back() == '\r') line.pop_back();
        if (line.empty()) continue;
        last_line_time = Clock::now();
        return line;
      }
      const auto left =
          std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
      if (left <= 0 || eof) return std::nullopt;
      pollfd p = {fd_, POLLIN, 0};
      ::poll(&p, 1, static_cast<int>(std::min<long long>(left, 50)));
      char buf[512];
      const ssize_t n = ::read(fd_, buf, sizeof(buf));
      if (n > 0) {
        buffer_.append(buf, static_cast<std::size_t>(n));
      } else if (n == 0 || (n < 0 && errno == EIO)) {
        eof = true;
      }
    }
  }

  // Reads until a line equal to `want` (or starting with it when `prefix`); returns the lines
  // before it. Fails the test on timeout.
  std::vector<std::string> Until(const std::string& want, bool prefix = false,
                                 double timeout_s = 5.0) {
    std::vector<std::string> before;
    const Clock::time_point deadline =
        Clock::now() + std::chrono::milliseconds(static_cast<int>(timeout_s * 1000));
    while (Clock::now() < deadline) {
      std::optional<std::string> l = Line(Seconds(deadline - Clock::now()));
      if (!l) break;
      if (*l == want || (prefix && l->rfind(want, 0) == 0)) return before;
      before.push_back(*l);
    }
    std::string seen;
    for (const auto& b : before) seen += b + " | ";
    FAIL("timed out waiting for '" << want << "', saw: " << seen);
    return before;
  }

  // '?' -> the next status report.
  std::string Status() {
    Send("?");
    const Clock::time_point deadline = Clock::now() + std::chrono::seconds(3);
    while (Clock::now() < deadline) {
      std::optional<std::string> l = Line(1.0);
      if (l && l->front() == '<') return *l;
      if (l) pending.push_back(*l);
    }
    FAIL("no status report");
    return "";
  }

  // Sends a line and returns its reply (ok / error:N), keeping other lines in `pending`.
  std::string Command(const std::string& line, double timeout_s = 3.0) {
    Send(line + "\n");
    const Clock::time_point deadline =
        Clock::now() + std::chrono::milliseconds(static_cast<int>(timeout_s * 1000));
    while (Clock::now() < deadline) {
      std::optional<std::string> l = Line(Seconds(deadline - Clock::now()));
      if (!l) break;
      if (*l == "ok" || l->rfind("error:", 0) == 0) return *l;
      pending.push_back(*l);
    }
    FAIL("no reply to '" << line << "'");
    return "";
  }

  bool eof = false;
  Clock::time_point last_line_time;
  std::vector<std::string> pending;

 private:
  int fd_ = -1;
  std::string buffer_;
};

Eigen::Vector3d Field3(const std::string& status, const std::string& key) {
  const std::size_t p = status.find(key);
  REQUIRE(p != std::string::npos);
  Eigen::Vector3d v;
  REQUIRE(std::sscanf(status.c_str() + p + key.size(), "%lf,%lf,%lf", &v[0], &v[1], &v[2]) == 3);
  return v;
}
Eigen::Vector3d MPos(const std::string& status) {
  return Field3(status, "MPos:");
}

std::string StateOf(const std::string& status) {
  return status.substr(1, status.find('|') - 1);
}

VirtualCncOptions FastOptions(double scale = 50.0) {
  VirtualCncOptions o;
  o.time_scale = scale;
  o.settings.homing_enable = false;
  o.settings.soft_limits = false;
  return o;
}

// Waits (polling '?') until the status state equals `state`.
std::string WaitState(Host& host, const std::string& state, double timeout_s = 5.0) {
  std::string s;
  const bool reached = gs360::test::WaitUntil(
      [&] {
        s = host.Status();
        return StateOf(s) == state;
      },
      std::chrono::milliseconds(static_cast<int>(timeout_s * 1000)));
  if (!reached) FAIL("state " << state << " never reached; last " << s);
  return s;
}

// Waits (polling '?') until a status report satisfies `done`; returns it.
std::string WaitStatus(Host& host, const std::function<bool(const std::string&)>& done,
                       double timeout_s = 5.0) {
  std::string s;
  const bool met = gs360::test::WaitUntil(
      [&] {
        s = host.Status();
        return done(s);
      },
      std::chrono::milliseconds(static_cast<int>(timeout_s * 1000)));
  if (!met) FAIL("condition never met; last status " << s);
  return s;
}

// Waits until the machine runs and MPos X has passed `x` (moving toward -X).
std::string WaitMovingPast(Host& host, double x) {
  return WaitStatus(host,
                    [x](const std::string& s) { return StateOf(s) == "Run" && MPos(s)[0] < x; });
}

// Waits until `done` holds (fails the test after `timeout_s`).
void WaitFor(const std::function<bool()>& done, double timeout_s = 5.0) {
  if (!gs360::test::WaitUntil(done,
                              std::chrono::milliseconds(static_cast<int>(timeout_s * 1000)))) {
    FAIL("condition never met");
  }
}

constexpr char kHalWelcome[] = "GrblHAL 1.1f ['$' or '$HELP' for help]";

}  // namespace

TEST_CASE("Welcome - unlock message - the $ queries", "[virtual_cnc]") {
  VirtualCncOptions o;  // homing and soft limits enabled: Alarm at power-up
  o.time_scale = 0;
  VirtualCnc cnc(o);
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  CHECK(*host.Line() == "[MSG:'$H'|'$X' to unlock]");
  CHECK(cnc.State() == GrblState::kAlarm);

  host.Send("$I\n");
  CHECK(*host.Line() == "[VER:1.1h.20190825:]");
  CHECK(*host.Line() == "[OPT:V,15,128]");
  CHECK(*host.Line() == "ok");

  host.Send("$$\n");
  std::vector<std::string> settings = host.Until("ok");
  REQUIRE(settings.size() == 34);
  CHECK(settings[0] == "$0=10");
  CHECK(settings[8] == "$11=0.010");
  CHECK(settings[11] == "$20=1");
  CHECK(settings[13] == "$22=1");
  CHECK(settings[25] == "$110=2000.000");
  CHECK(settings[27] == "$112=800.000");
  CHECK(settings[28] == "$120=150.000");
  CHECK(settings[33] == "$132=45.000");

  host.Send("$G\n");
  CHECK(*host.Line() == "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]");
  CHECK(*host.Line() == "ok");
  host.Send("$\n");
  CHECK(*host.Line() == "[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]");
  CHECK(*host.Line() == "ok");
  host.Send("$#\n");
  std::vector<std::string> params = host.Until("ok");
  REQUIRE(params.size() == 11);
  CHECK(params[0] == "[G54:0.000,0.000,0.000]");
  CHECK(params[10] == "[PRB:0.000,0.000,0.000:0]");

  // Alarm: G-code is locked out, $X unlocks.
  CHECK(host.Command("G0X-1") == "error:9");
  host.Send("$X\n");
  CHECK(*host.Line() == "[MSG:Caution: Unlocked]");
  CHECK(*host.Line() == "ok");
  CHECK(host.Command("G0X-1") == "ok");
  const std::string s = WaitState(host, "Idle");
  CHECK(s.rfind("<Idle|MPos:-1.000,0.000,0.000|FS:0,0", 0) == 0);
}

TEST_CASE("Bad lines get GRBL error codes and every line terminator counts", "[virtual_cnc]") {
  VirtualCnc cnc(FastOptions(0));
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  CHECK(host.Command("G5") == "error:20");
  CHECK(host.Command("G0X") == "error:2");
  CHECK(host.Command("G0X1X2") == "error:25");
  CHECK(host.Command("G1X-1") == "error:22");
  CHECK(host.Command("$Q") == "error:2");
  CHECK(host.Command("$$$") == "error:3");
  CHECK(host.Command("$20=1") == "error:10");  // soft limits need homing
  CHECK(host.Command("$0=2") == "error:6");
  CHECK(host.Command("$H") == "error:5");  // homing disabled
  CHECK(host.Command("g0 x-1 (comment) ; more") == "ok");
  // At most 79 significant characters per line (spaces and comments do not count).
  CHECK(host.Command("G90" + std::string(76, ' ') + "G0X-1") == "ok");  // spaces do not count
  std::string too_long = "N1" + std::string(78, '0');
  CHECK(host.Command(too_long) == "error:11");
  // "\r\n" ends two lines: the empty one gets its own ok.
  host.Send("G0X-2\r\n");
  CHECK(*host.Line() == "ok");
  CHECK(*host.Line() == "ok");
  CHECK_FALSE(host.Line(0.2));
  const auto st = cnc.Stats();
  CHECK(st.errors >= 9);
}

TEST_CASE("Status reports during and after motion", "[virtual_cnc]") {
  VirtualCncOptions o = FastOptions(2);
  o.settings.status_report_mask = 3;  // MPos + buffer state
  VirtualCnc cnc(o);
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  // The first report after a reset carries WCO, the next one the overrides.
  std::string s = host.Status();
  CHECK(s == "<Idle|MPos:0.000,0.000,0.000|Bf:15,128|FS:0,0|WCO:0.000,0.000,0.000>");
  s = host.Status();
  CHECK(s == "<Idle|MPos:0.000,0.000,0.000|Bf:15,128|FS:0,0|Ov:100,100,100>");
  CHECK(host.Command("G1X-30F1200") == "ok");  // 1.6 s of machine time, 0.8 s at 2x
  s = WaitMovingPast(host, -5.0);              // at the programmed feed by then
  CHECK(s.find("|Bf:14,128|FS:1200,0") != std::string::npos);
  const double x = MPos(s)[0];
  CHECK(x < -5.0);
  CHECK(x > -30.0);
  s = WaitState(host, "Idle");
  CHECK(MPos(s)[0] == -30.0);
  CHECK(cnc.TruePositionNow().isApprox(Eigen::Vector3d(-30, 0, 0)));
  // Work coordinates: G10 L20 makes here X0 in G54; $10=2 reports WPos.
  CHECK(host.Command("G10L20P1X0") == "ok");
  CHECK(host.Command("$10=2") == "ok");
  s = host.Status();
  CHECK(s.rfind("<Idle|WPos:0.000,0.000,0.000|Bf:15,128|FS:0,0|WCO:-30.000,0.000,0.000", 0) == 0);
}

TEST_CASE("Homing: Z then XY with pull-off and the Home state answered at the end",
          "[virtual_cnc]") {
  VirtualCncOptions o;
  o.time_scale = 50;
  o.initial_true_position = Eigen::Vector3d(-30, -20, -10);
  VirtualCnc cnc(o);
  Host host(cnc.PtyPath());
  host.Until("[MSG:'$H'|'$X' to unlock]");
  CHECK(cnc.ReportedPosition().isZero());  // believes 0,0,0 at power-up
  const double m0 = cnc.MachineTime(Clock::now());
  host.Send("$H\n");
  WaitFor([&] { return cnc.State() == GrblState::kHome; });
  host.Send("?");
  const std::vector<std::string> before = host.Until("ok", false, 10.0);
  const double machine_s = cnc.MachineTime(Clock::now()) - m0;
  REQUIRE(before.size() == 1);  // one status report, made during homing, answered at its end
  CHECK(StateOf(before[0]) == "Home");
  CHECK(MPos(before[0]).isApprox(Eigen::Vector3d(-1, -1, -1)));
  CHECK(cnc.TruePositionNow().isApprox(Eigen::Vector3d(-1, -1, -1), 1e-9));
  CHECK(cnc.ReportedPosition().isApprox(Eigen::Vector3d(-1, -1, -1)));
  CHECK(cnc.State() == GrblState::kIdle);
  // Seeking 10 mm (Z) and 30 mm (XY diagonal) at $25 plus locating at $24 and debounces takes
  // several machine seconds.
  CHECK(machine_s > 3.0);
  CHECK(StateOf(host.Status()) == "Idle");
}

TEST_CASE("Soft limit: ALARM:2 before the ok of its line - reset required - error:9 until $X",
          "[virtual_cnc]") {
  VirtualCncOptions o;
  o.time_scale = 20;
  VirtualCnc cnc(o);
  Host host(cnc.PtyPath());
  host.Until("[MSG:'$H'|'$X' to unlock]");
  CHECK(host.Command("$H", 10.0) == "ok");
  // A target beyond travel (X > 0) while moving: a controlled stop, then the alarm.
  CHECK(host.Command("G1X-100F600") == "ok");
  WaitMovingPast(host, -1.0);
  host.Send("G1X10F600\n");
  CHECK(*host.Line() == "ALARM:2");
  CHECK(*host.Line() == "[MSG:Reset to continue]");
  // Controlled stop: position kept, no further motion.
  const Eigen::Vector3d stopped = cnc.TruePositionNow();
  CHECK(stopped[0] < -1.0);
  CHECK(stopped[0] > -100.0);
  // Everything but a reset is ignored now, status requests too.
  host.Send("?");
  host.Send("$X\n");
  CHECK_FALSE(host.Line(0.3));
  CHECK(cnc.TruePositionNow().isApprox(stopped));
  host.Send("\x18");
  CHECK(*host.Line() == "ok");  // the offending line's reply comes after the reset
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK(*host.Line() == "[MSG:'$H'|'$X' to unlock]");
  CHECK(cnc.ReportedPosition().isApprox(stopped, 1e-3));
  CHECK(host.Command("G0X-1") == "error:9");
  CHECK(host.Command("$X") == "ok");
  CHECK(host.Command("G0X-1") == "ok");
}

TEST_CASE("Reset during motion: ALARM:3 then the welcome - position kept or lost",
          "[virtual_cnc]") {
  VirtualCncOptions o = FastOptions(2);
  VirtualCnc cnc(o);
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  CHECK(host.Command("G1X-50F1200") == "ok");
  WaitFor([&] { return cnc.TruePositionNow()[0] < -1.5; });
  host.Send("\x18");
  CHECK(*host.Line() == "ALARM:3");
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK(*host.Line() == "[MSG:'$H'|'$X' to unlock]");
  CHECK(cnc.State() == GrblState::kAlarm);
  const Eigen::Vector3d t = cnc.TruePositionNow();
  CHECK(t[0] < -1.0);
  CHECK(t[0] > -49.0);
  // Stopped dead: at rest, nothing left to execute.
  CHECK(cnc.TrueSpeed(Clock::now()) == 0.0);
  CHECK(cnc.PlannerBlocksQueued() == 0);
  CHECK(cnc.TruePositionNow().isApprox(t));
  CHECK((cnc.ReportedPosition() - t).norm() < 1e-3);
  CHECK(host.Command("$X") == "ok");

  // With position loss, the controller's belief no longer matches the machine.
  cnc.LosePositionOnReset(true);
  CHECK(host.Command("G1X-100F1200") == "ok");
  WaitFor([&] { return cnc.TrueSpeed(Clock::now()) > 0.0; });
  host.Send("\x18");
  CHECK(*host.Line() == "ALARM:3");
  host.Until("[MSG:'$H'|'$X' to unlock]");
  const Eigen::Vector3d diff = cnc.ReportedPosition() - cnc.TruePositionNow();
  CHECK(diff.cwiseAbs().maxCoeff() > 1e-3);
  CHECK(diff.cwiseAbs().maxCoeff() <= 0.5 + 1e-3);

  // A reset while idle is just a welcome, no alarm.
  CHECK(host.Command("$X") == "ok");
  host.Send("\x18");
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK(StateOf(host.Status()) == "Idle");
}

TEST_CASE("Feed hold: Hold:1 then Hold:0 - parser suspended - resume finishes", "[virtual_cnc]") {
  VirtualCncOptions o = FastOptions(2);
  o.settings.acceleration_mm_per_s2 = Eigen::Vector3d(10, 10, 10);  // 2 s ramps to 20 mm/s
  VirtualCnc cnc(o);
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  CHECK(host.Command("G1X-30F1200") == "ok");
  WaitMovingPast(host, -3.0);  // some 8 mm/s by then: a stop of about 3 mm
  host.Send("!");
  // A '?' in the same breath would be answered first (status before hold).
  WaitFor([&] { return cnc.State() == GrblState::kHold; });
  std::string s = host.Status();
  CHECK(s.rfind("<Hold:1|", 0) == 0);
  s = WaitState(host, "Hold:0");
  const Eigen::Vector3d held = cnc.TruePositionNow();
  CHECK(held[0] < -2.0);
  CHECK(held[0] > -25.0);
  // While held, lines stay in the RX buffer: no reply.
  host.Send("G0X-20\n");
  CHECK_FALSE(host.Line(0.2));
  CHECK(cnc.RxBufferUsed() == 7);
  CHECK(cnc.TruePositionNow().isApprox(held));
  host.Send("~");
  CHECK(*host.Line() == "ok");  // G0X-20 is queued once the parser runs again
  s = WaitState(host, "Idle", 10.0);
  CHECK(MPos(s)[0] == -20.0);
  CHECK(cnc.TruePositionNow().isApprox(Eigen::Vector3d(-20, 0, 0)));
  CHECK(cnc.TrueTrajectory(Clock::now() - std::chrono::seconds(10), Clock::now()).size() > 4);
}

TEST_CASE("Ignoring character counting overflows the RX buffer and loses bytes", "[virtual_cnc]") {
  VirtualCncOptions o = FastOptions(5);
  o.settings.status_report_mask = 3;
  VirtualCnc cnc(o);
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  // The dwell blocks the parser for 0.5 s (wall); 40 more lines (240 bytes) arrive meanwhile.
  std::string burst = "G4P2.5\n";
  for (int i = 0; i < 40; ++i) burst += (i % 2 ? "G0X-1\n" : "G0X-2\n");
  host.Send(burst);
  // The dwell holds the parser: the RX buffer fills up and stays full.
  const std::string s = WaitStatus(
      host, [](const std::string& r) { return r.find("|Bf:15,0|") != std::string::npos; });
  INFO(s);
  CHECK(s.find("|Bf:15,0|") != std::string::npos);
  int replies = 0;
  while (auto l = host.Line(0.6)) {
    if (*l == "ok" || l->rfind("error:", 0) == 0) ++replies;
  }
  CHECK(replies < 41);
  const std::uint64_t dropped = cnc.Stats().rx_overflow_dropped;
  CHECK(dropped >= 240 + 7 - 128 - 7);

  // The last line was cut by the overflow: its head still sits in the line buffer. A reset
  // (once stopped: a reset in motion would alarm) clears it.
  WaitState(host, "Idle");
  host.Send("\x18");
  host.Until("Grbl 1.1h ['$' for help]");
  // Character counting: never more than 128 bytes of unanswered lines. Nothing is lost.
  std::vector<std::string> lines = {"G4P1.0"};
  for (int i = 0; i < 40; ++i) lines.push_back(i % 2 ? "G0X-1" : "G0X-2");
  std::deque<std::size_t> in_flight;
  std::size_t outstanding = 0, next = 0, oks = 0;
  while (oks < lines.size()) {
    while (next < lines.size() && outstanding + lines[next].size() + 1 <= 128) {
      host.Send(lines[next] + "\n");
      in_flight.push_back(lines[next].size() + 1);
      outstanding += lines[next].size() + 1;
      ++next;
    }
    std::optional<std::string> l = host.Line(3.0);
    REQUIRE(l);
    if (*l == "ok") {
      ++oks;
      outstanding -= in_flight.front();
      in_flight.pop_front();
    } else {
      INFO(*l);
      REQUIRE(l->rfind("error", 0) != 0);
    }
  }
  CHECK(cnc.Stats().rx_overflow_dropped == dropped);
}

TEST_CASE("G4 ok after motion and dwell - motion time matches the closed form", "[virtual_cnc]") {
  VirtualCncOptions o = FastOptions(1);
  o.settings.acceleration_mm_per_s2 = Eigen::Vector3d(40, 40, 40);
  VirtualCnc cnc(o);
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  const gs360::MotionLimits limits = cnc.Settings().Limits();
  auto feed = [](double f) {
    gs360::MoveRate r;
    r.rapid = false;
    r.feed_mm_per_min = f;
    return r;
  };

  struct Path {
    const char* name;
    std::vector<std::string> lines;
    std::vector<Eigen::Vector3d> targets;
    double dwell;
  };
  // Relative paths (G91) so that each starts where the previous ended.
  const std::vector<Path> paths = {
      {"single", {"G91G1X-20F1200"}, {{-20, 0, 0}}, 0.2},
      {"collinear",
       {"G91G1X-5F1200", "X-5", "X-5", "X-5"},
       {{-5, 0, 0}, {-10, 0, 0}, {-15, 0, 0}, {-20, 0, 0}},
       0.0},
      {"corner", {"G91G1X-10F1200", "Y-10"}, {{-10, 0, 0}, {-10, -10, 0}}, 0.0},
      {"triangle", {"G91G1X-6F1200"}, {{-6, 0, 0}}, 0.0},
  };
  // Machine time only: how late the ok comes on a loaded host is bench_sim_cnc's figure, not a
  // test's.
  for (const Path& path : paths) {
    INFO(path.name);
    const Eigen::Vector3d start = cnc.ReportedPosition();
    std::vector<gs360::MoveRequest> moves;
    for (const auto& t : path.targets) moves.push_back({start + t, feed(1200)});
    const double motion = gs360::PlannedPathDuration(start, moves, limits);
    const double m0 = cnc.MachineTime(Clock::now());

    std::string batch;
    for (const auto& l : path.lines) batch += l + "\n";
    char dwell[32];
    std::snprintf(dwell, sizeof(dwell), "G4P%.2f\n", path.dwell);
    batch += dwell;
    const Clock::time_point sent = Clock::now();
    host.Send(batch);
    for (std::size_t i = 0; i < path.lines.size(); ++i) {
      CHECK(*host.Line() == "ok");
      // Queued, not executed: the machine is not yet at the path's end.
      CHECK_FALSE(cnc.TruePosition(host.last_line_time).isApprox(start + path.targets.back()));
    }
    CHECK(*host.Line(5.0) == "ok");  // the G4
    const Clock::time_point ok_time = host.last_line_time;
    // Exact: the executed profile in machine time equals the closed form.
    const auto pieces = cnc.TrueTrajectory(sent, ok_time);
    REQUIRE(!pieces.empty());
    CHECK(pieces.back().t1 - pieces.front().t0 == Approx(motion).epsilon(1e-9));
    CHECK(pieces.front().t0 >= m0);
    // At the G4 ok the machine is at the target, at rest, and the dwell has elapsed: never early.
    CHECK(cnc.TruePosition(ok_time).isApprox(start + path.targets.back(), 1e-9));
    CHECK(cnc.MachineTime(ok_time) - pieces.back().t1 >= path.dwell - 1e-6);
  }
}

TEST_CASE("Instant mode completes motion and dwells at once and in order", "[virtual_cnc]") {
  VirtualCnc cnc(FastOptions(0));
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  host.Send("G1X-100F100\nG4P10\n");  // 60 s of motion, 10 s of dwell
  CHECK(*host.Line() == "ok");
  CHECK(*host.Line() == "ok");  // at once: within Line()'s default wait, far below 70 s
  CHECK(cnc.TruePositionNow().isApprox(Eigen::Vector3d(-100, 0, 0)));
  CHECK(cnc.MachineTime(Clock::now()) >= 70.0);
  CHECK(StateOf(host.Status()) == "Idle");
}

TEST_CASE("Jogging and jog cancel", "[virtual_cnc]") {
  VirtualCnc cnc(FastOptions(5));
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  CHECK(host.Command("$J=G91X-50F600") == "ok");
  CHECK(StateOf(host.Status()) == "Jog");
  CHECK(host.Command("G0X0") == "error:9");  // G-code is locked while jogging
  WaitFor([&] { return cnc.TruePositionNow()[0] < -1.0; });
  host.Send("\x85");
  const std::string s = WaitState(host, "Idle");
  CHECK(MPos(s)[0] < -1.0);
  CHECK(MPos(s)[0] > -50.0);
  CHECK(host.Command("$J=X1F100") == "ok");  // back toward 0 from wherever it stopped
  WaitState(host, "Idle");
  CHECK(cnc.TruePositionNow()[0] == Approx(1.0));
}

TEST_CASE("Fault: dropped and garbled bytes in both directions", "[virtual_cnc]") {
  VirtualCnc cnc(FastOptions(0));
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  cnc.DropNextBytes(1, FaultDirection::kHostToCnc);  // the 'G' is lost
  CHECK(host.Command("G0X-1") == "error:1");
  cnc.GarbleNextBytes(1, FaultDirection::kCncToHost);
  host.Send("G0X-2\n");
  const std::string garbled = *host.Line();
  CHECK(garbled != "ok");
  CHECK(garbled.size() == 2);
  cnc.DropNextBytes(4, FaultDirection::kCncToHost);  // a whole "ok\r\n" vanishes
  host.Send("G0X-3\n");
  CHECK_FALSE(host.Line(0.3));
  CHECK(host.Command("G0X-4") == "ok");
  CHECK(cnc.TruePositionNow()[0] == Approx(-4.0));
  CHECK(cnc.Stats().injected_drops == 5);
  CHECK(cnc.Stats().injected_garbles == 1);
  // Random loss: some lines fail, some pass; then the link is clean again.
  cnc.SetDropProbability(0.2, FaultDirection::kHostToCnc);
  host.Send(std::string(20, '\n'));  // 20 empty lines: each is 'ok' only if its '\n' survives
  int oks = 0;
  while (auto l = host.Line(0.3)) oks += *l == "ok";
  CHECK(oks > 5);
  CHECK(oks < 20);
  cnc.SetDropProbability(0.0, FaultDirection::kHostToCnc);
  CHECK(host.Command("$I") == "ok");
}

TEST_CASE("Fault: stalled replies arrive late but intact", "[virtual_cnc]") {
  VirtualCnc cnc(FastOptions(0));
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  cnc.StallReplies(std::chrono::milliseconds(300));
  host.Send("$I\n");
  CHECK_FALSE(host.Line(0.1));  // held back by the stall
  CHECK(*host.Line(2.0) == "[VER:1.1h.20190825:]");
  CHECK(*host.Line() == "[OPT:V,15,128]");
  CHECK(*host.Line() == "ok");
}

TEST_CASE("Fault: alarm mid-move stops dead and a hard limit needs a reset", "[virtual_cnc]") {
  VirtualCnc cnc(FastOptions(10));
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  cnc.RaiseAlarmDuringNextMove(1, 0.5);
  CHECK(host.Command("G1X-40F1200") == "ok");
  CHECK(*host.Line(3.0) == "ALARM:1");
  CHECK(*host.Line() == "[MSG:Reset to continue]");
  CHECK(cnc.TruePositionNow()[0] == Approx(-20.0));
  CHECK(cnc.State() == GrblState::kAlarm);
  host.Send("?");
  CHECK_FALSE(host.Line(0.2));
  host.Send("\x18");
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK(*host.Line() == "[MSG:'$H'|'$X' to unlock]");
  CHECK(cnc.ReportedPosition()[0] == Approx(-20.0));

  // A non-critical code is followed by an automatic reset.
  CHECK(host.Command("$X") == "ok");
  cnc.RaiseAlarmDuringNextMove(3, 0.25);
  CHECK(host.Command("G1X-60F1200") == "ok");
  CHECK(*host.Line(3.0) == "ALARM:3");
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK(cnc.TruePositionNow()[0] == Approx(-30.0));
}

TEST_CASE("Fault: USB unplug and replug under a new path with and without power loss",
          "[virtual_cnc]") {
  VirtualCncOptions o = FastOptions(2);
  o.settings.homing_enable = true;
  o.symlink_path = std::string(GS360_BINARY_DIR) + "/sim_cnc_test_link";
  VirtualCnc cnc(o);
  const std::string first = cnc.PtyPath();
  char target[256] = {};
  REQUIRE(::readlink(o.symlink_path.c_str(), target, sizeof(target) - 1) > 0);
  CHECK(std::string(target) == first);
  {
    Host host(first);
    host.Until("[MSG:'$H'|'$X' to unlock]");
    CHECK(host.Command("$X") == "ok");
    CHECK(host.Command("G1X-30F1200") == "ok");
    WaitFor([&] { return cnc.TruePositionNow()[0] < -0.6; });
    cnc.Unplug();
    CHECK_FALSE(host.Line(0.3));
    CHECK(host.eof);
  }
  CHECK_FALSE(cnc.Plugged());
  CHECK(cnc.PtyPath().empty());
  CHECK(::access(o.symlink_path.c_str(), F_OK) != 0);
  const Eigen::Vector3d where = cnc.TruePositionNow();
  CHECK(where[0] < -0.5);
  CHECK(where[0] > -29.0);  // power died mid-move
  CHECK(cnc.TrueSpeed(Clock::now()) == 0.0);
  CHECK(cnc.PlannerBlocksQueued() == 0);

  cnc.Replug();
  const std::string second = cnc.PtyPath();
  CHECK(second != first);
  REQUIRE(::readlink(o.symlink_path.c_str(), target, sizeof(target) - 1) > 0);
  CHECK(std::string(target).substr(0, second.size()) == second);
  Host host(second);
  host.Until("Grbl 1.1h ['$' for help]");
  CHECK(*host.Line() == "[MSG:'$H'|'$X' to unlock]");
  const std::string s = host.Status();
  CHECK(StateOf(s) == "Alarm");
  CHECK(MPos(s).isZero());  // rebooted: believes 0,0,0 wherever the machine stands
  CHECK(cnc.TruePositionNow().isApprox(where));
  CHECK(cnc.Stats().boots == 2);

  // Without power loss the controller keeps running; the device comes back by itself.
  gs360::UnplugOptions keep;
  keep.power_loss = false;
  keep.replug_after = std::chrono::milliseconds(100);
  cnc.Unplug(keep);
  WaitFor([&] { return cnc.Plugged(); }, 3.0);
  CHECK(cnc.PtyPath() != second);
  Host again(cnc.PtyPath());
  CHECK_FALSE(again.Line(0.2));  // no welcome: it never rebooted
  CHECK(StateOf(again.Status()) == "Alarm");
  CHECK(cnc.Stats().boots == 2);
}

TEST_CASE("reset_on_open: opening the port reboots the controller", "[virtual_cnc]") {
  VirtualCncOptions o = FastOptions(0);
  o.reset_on_open = true;
  o.boot_delay = std::chrono::milliseconds(50);
  VirtualCnc cnc(o);
  WaitFor([&] { return cnc.Stats().unheard == 1; });  // the power-up welcome, to nobody
  {
    Host host(cnc.PtyPath());
    CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
    CHECK(cnc.Stats().boots == 2);  // opening the port rebooted it
    CHECK_FALSE(host.Line(0.2));    // the power-up welcome, sent before anyone listened, is gone
    CHECK(host.Command("G0X-5") == "ok");
  }
  WaitFor([&] { return !cnc.HostAttached(); });
  Host host(cnc.PtyPath());
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK(MPos(host.Status()).isZero());
  CHECK(cnc.TruePositionNow()[0] == Approx(-5.0));
}

TEST_CASE("reset_on_open: a port closed and reopened at once still reboots the controller",
          "[virtual_cnc]") {
  // A session that ends and the next that starts a few microseconds later leave no POLLHUP for
  // the board to see: each open is a DTR pulse all the same, and each host hears the welcome.
  VirtualCncOptions o = FastOptions(0);
  o.reset_on_open = true;
  o.boot_delay = std::chrono::milliseconds(20);
  VirtualCnc cnc(o);
  std::optional<Host> host;
  host.emplace(cnc.PtyPath());
  REQUIRE(host->Line() == std::optional<std::string>("Grbl 1.1h ['$' for help]"));
  for (int session = 0; session < 5; ++session) {
    host.reset();
    host.emplace(cnc.PtyPath());  // the previous host's close and this open, back to back
    CHECK(host->Line() == std::optional<std::string>("Grbl 1.1h ['$' for help]"));
  }
  CHECK(cnc.Stats().boots == 7);  // power-up, then one per open
}

TEST_CASE("RunVirtualCncForeground prints the pty path and stops on SIGTERM", "[virtual_cnc]") {
#if defined(__SANITIZE_THREAD__)
  SUCCEED("fork() with threads is not supported under ThreadSanitizer");
  return;
#endif
  int out[2];
  REQUIRE(::pipe(out) == 0);
  std::cout.flush();  // the child inherits unflushed buffers
  std::fflush(nullptr);
  const pid_t child = ::fork();
  REQUIRE(child >= 0);
  if (child == 0) {
    ::dup2(out[1], STDOUT_FILENO);
    ::close(out[0]);
    int rc = 3;
    try {
      rc = gs360::RunVirtualCncForeground(FastOptions(0));
    } catch (...) {
      rc = 2;
    }
    ::_exit(rc);
  }
  ::close(out[1]);
  struct KillOnExit {  // a failed REQUIRE must not leave the child serving forever
    pid_t pid;
    bool armed = true;
    ~KillOnExit() {
      if (armed) {
        ::kill(pid, SIGKILL);
        ::waitpid(pid, nullptr, 0);
      }
    }
  } guard{child};
  std::string path;
  char c;
  while (::read(out[0], &c, 1) == 1 && c != '\n') path.push_back(c);
  ::close(out[0]);
  REQUIRE(path.rfind("/dev/pts/", 0) == 0);
  {
    Host host(path);
    host.Until("Grbl 1.1h ['$' for help]");
    CHECK(host.Command("$I") == "ok");
  }
  REQUIRE(::kill(child, SIGTERM) == 0);
  int status = 0;
  REQUIRE(::waitpid(child, &status, 0) == child);
  guard.armed = false;
  CHECK(WIFEXITED(status));
  CHECK(WEXITSTATUS(status) == 0);
}

TEST_CASE("VirtualCncOptions and fault arguments are checked", "[virtual_cnc]") {
  VirtualCncOptions o;
  CHECK_NOTHROW(o.Check());
  o.time_scale = -1;
  CHECK_THROWS_WITH(VirtualCnc(o), Catch::Contains("time_scale"));
  o = VirtualCncOptions();
  o.rx_buffer_bytes = 8;
  CHECK_THROWS_WITH(o.Check(), Catch::Contains("rx_buffer_bytes"));
  o = VirtualCncOptions();
  o.baud_rate = -9600;
  CHECK_THROWS_WITH(o.Check(), Catch::Contains("baud_rate"));
  o = VirtualCncOptions();
  o.settings.homing_enable = false;  // soft limits still on: the firmware refuses that
  CHECK_THROWS_WITH(o.Check(), Catch::Contains("soft_limits"));
  VirtualCnc cnc(FastOptions(0));
  CHECK_THROWS_AS(cnc.RaiseAlarmDuringNextMove(0, 0.5), std::invalid_argument);
  CHECK_THROWS_AS(cnc.RaiseAlarmDuringNextMove(1, 1.5), std::invalid_argument);
  CHECK_THROWS_AS(cnc.SetDropProbability(2.0), std::invalid_argument);
  cnc.Stop();
  cnc.Stop();  // idempotent
  CHECK(cnc.PtyPath().empty());
}

TEST_CASE("Homing with HOMING_FORCE_SET_ORIGIN ends at 0,0,0", "[virtual_cnc]") {
  VirtualCncOptions o;
  o.time_scale = 50;
  o.homing_force_set_origin = true;
  o.initial_true_position = Eigen::Vector3d(-5, -6, -7);
  VirtualCnc cnc(o);
  Host host(cnc.PtyPath());
  host.Until("[MSG:'$H'|'$X' to unlock]");
  host.Send("$I\n");
  CHECK(*host.Line() == "[VER:1.1h.20190825:]");
  CHECK(*host.Line() == "[OPT:VZ,15,128]");
  CHECK(*host.Line() == "ok");
  CHECK(host.Command("$H", 10.0) == "ok");
  CHECK(MPos(host.Status()).isZero());
  CHECK(cnc.TruePositionNow().isZero(1e-9));
  CHECK(host.Command("G0X-2") == "ok");
  WaitState(host, "Idle");
  CHECK(cnc.TruePositionNow().isApprox(Eigen::Vector3d(-2, 0, 0)));
}

TEST_CASE("Check mode - startup lines - restore - sleep - arcs - offsets - program flow - probe",
          "[virtual_cnc]") {
  VirtualCnc cnc(FastOptions(0));
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  // $C parses without moving; leaving it resets the controller.
  host.Send("$C\n");
  CHECK(*host.Line() == "[MSG:Enabled]");
  CHECK(*host.Line() == "ok");
  CHECK(host.Command("G0X-10") == "ok");
  CHECK(host.Command("G5") == "error:20");
  CHECK(cnc.TruePositionNow().isZero());
  CHECK(StateOf(host.Status()) == "Check");
  host.Send("$C\n");
  CHECK(*host.Line() == "[MSG:Disabled]");
  CHECK(*host.Line() == "ok");
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  // Startup lines run after every reset (not in Alarm).
  CHECK(host.Command("$N0=G91") == "ok");
  host.Send("$N\n");
  CHECK(*host.Line() == "$N0=G91");
  CHECK(*host.Line() == "$N1=");
  CHECK(*host.Line() == "ok");
  host.Send("\x18");
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK(*host.Line() == ">G91:ok");
  host.Send("$G\n");
  CHECK(*host.Line() == "[GC:G0 G54 G17 G21 G91 G94 M5 M9 T0 F0 S0]");
  CHECK(*host.Line() == "ok");
  CHECK(host.Command("$N0=") == "ok");
  // G54 data survives resets until $RST=#.
  CHECK(host.Command("G90G10L2P1X-3") == "ok");
  host.Send("$#\n");
  CHECK(*host.Line() == "[G54:-3.000,0.000,0.000]");
  host.Until("ok");
  host.Send("$RST=#\n");
  CHECK(*host.Line() == "[MSG:Restoring defaults]");
  CHECK(*host.Line() == "ok");
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  host.Send("$#\n");
  CHECK(*host.Line() == "[G54:0.000,0.000,0.000]");
  host.Until("ok");
  // A counter-clockwise half circle ends at its target; G92 shifts work coordinates.
  CHECK(host.Command("G90G17G3X-20Y0I-10J0F600") == "ok");
  WaitState(host, "Idle");
  CHECK(cnc.TruePositionNow().isApprox(Eigen::Vector3d(-20, 0, 0), 1e-9));
  CHECK(host.Command("G92X0") == "ok");
  CHECK(host.Command("G0X-5") == "ok");
  WaitState(host, "Idle");
  CHECK(cnc.TruePositionNow()[0] == Approx(-25.0));
  // M0 pauses like a feed hold; M2 ends the program.
  host.Send("M0\n");
  CHECK_FALSE(host.Line(0.2));
  CHECK(StateOf(host.Status()) == "Hold:0");
  host.Send("~");
  CHECK(*host.Line() == "ok");
  host.Send("M2\n");
  CHECK(*host.Line() == "[MSG:Pgm End]");
  CHECK(*host.Line() == "ok");
  // No probe is wired: G38.2 runs to its target and fails; G38.4 fails at once.
  host.Send("G38.2Z-2F100\n");
  CHECK(*host.Line() == "ALARM:5");
  CHECK(host.Line()->rfind("[PRB:", 0) == 0);
  CHECK(*host.Line() == "ok");
  CHECK(cnc.TruePositionNow()[2] == Approx(-2.0));
  CHECK(host.Command("$X") == "ok");
  host.Send("G38.4Z0F100\n");
  CHECK(*host.Line() == "ALARM:4");
  CHECK(*host.Line() == "ok");
  CHECK(host.Command("$X") == "ok");
  // Sleep: only a reset wakes it, into Alarm.
  host.Send("$SLP\n");
  CHECK(*host.Line() == "ok");
  CHECK(*host.Line() == "[MSG:Sleeping]");
  CHECK(StateOf(host.Status()) == "Sleep");
  host.Send("\x18");
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK(*host.Line() == "[MSG:'$H'|'$X' to unlock]");
}

TEST_CASE("Fault: PowerCycle restarts the board mid-move with the link up - MPos 0 wherever it is",
          "[virtual_cnc]") {
  VirtualCncOptions o = FastOptions(2);
  o.settings.homing_enable = true;  // Alarm at power-up (soft limits stay off)
  VirtualCnc cnc(o);
  const std::string path = cnc.PtyPath();
  Host host(path);
  host.Until("[MSG:'$H'|'$X' to unlock]");
  CHECK(host.Command("$X") == "ok");
  CHECK(host.Command("G1X-30F1200") == "ok");  // 1.5 machine seconds
  host.Send("G4P0.5\n");                       // parsed, waiting for the move: in flight
  WaitMovingPast(host, -1.0);
  cnc.PowerCycle();
  const Eigen::Vector3d where = cnc.TruePositionNow();
  // A fresh boot and nothing else: no ALARM:3 (this is no reset), no ok for the G4.
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK(*host.Line() == "[MSG:'$H'|'$X' to unlock]");
  CHECK_FALSE(host.Line(0.3));
  CHECK_FALSE(host.eof);  // the link stayed up, under the same path
  CHECK(cnc.PtyPath() == path);
  std::string s = host.Status();
  CHECK(StateOf(s) == "Alarm");
  CHECK(MPos(s).isZero());  // believes 0,0,0 ...
  CHECK(where[0] < -1.0);   // ... where the tool stopped dead mid-move
  CHECK(where[0] > -29.0);
  CHECK(cnc.TrueSpeed(Clock::now()) == 0.0);
  CHECK(cnc.TruePositionNow().isApprox(where));
  CHECK(cnc.Stats().boots == 2);
  CHECK(cnc.Stats().alarms == 0);

  // Settings are EEPROM: $22=0 survives the next restart, which then comes up Idle.
  CHECK(host.Command("$22=0") == "ok");
  cnc.PowerCycle();
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK_FALSE(host.Line(0.2));
  s = host.Status();
  CHECK(StateOf(s) == "Idle");
  CHECK(MPos(s).isZero());
  CHECK(host.Command("G91G0X-1") == "ok");  // relative to a wrong belief: lands at where - 1
  s = WaitState(host, "Idle");
  CHECK(MPos(s)[0] == -1.0);
  CHECK(cnc.TruePositionNow()[0] == Approx(where[0] - 1.0));
}

TEST_CASE("Fault: ResetNow acts as 0x18 - ALARM:3 in motion - at a G4 dwell no alarm",
          "[virtual_cnc]") {
  VirtualCnc cnc(FastOptions(2));
  Host host(cnc.PtyPath());
  host.Until("Grbl 1.1h ['$' for help]");
  // In motion: steppers stop dead, ALARM:3 before the welcome; MPos is where they stopped.
  CHECK(host.Command("G1X-50F1200") == "ok");
  WaitMovingPast(host, -1.0);
  cnc.ResetNow();
  CHECK(*host.Line() == "ALARM:3");
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK(*host.Line() == "[MSG:'$H'|'$X' to unlock]");
  Eigen::Vector3d stopped = cnc.TruePositionNow();
  CHECK(stopped[0] < -1.0);
  CHECK(stopped[0] > -49.0);
  CHECK(cnc.TrueSpeed(Clock::now()) == 0.0);
  CHECK((MPos(host.Status()) - stopped).norm() < 2e-3);
  CHECK(host.Command("$X") == "ok");
  // With position loss on, the belief is shifted by the dead stop.
  cnc.LosePositionOnReset(true);
  CHECK(host.Command("G91G1X-40F1200") == "ok");
  WaitMovingPast(host, stopped[0] - 1.0);
  cnc.ResetNow();
  CHECK(*host.Line() == "ALARM:3");
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK(*host.Line() == "[MSG:'$H'|'$X' to unlock]");
  stopped = cnc.TruePositionNow();
  const Eigen::Vector3d shift = cnc.ReportedPosition() - stopped;
  CHECK(shift.cwiseAbs().maxCoeff() > 1e-3);
  CHECK(shift.cwiseAbs().maxCoeff() <= 0.5 + 1e-3);
  CHECK((MPos(host.Status()) - cnc.ReportedPosition()).norm() < 2e-3);
  CHECK(cnc.Stats().resets == 2);
  cnc.LosePositionOnReset(false);
  CHECK(host.Command("$X") == "ok");

  // At a dwell the planner is empty and the state Idle: a reset stops nothing. The G4 ends
  // with its ok, then the welcome; the two moves still in the RX buffer are never answered.
  const Eigen::Vector3d before = cnc.TruePositionNow();
  const Eigen::Vector3d belief = cnc.ReportedPosition();
  host.Send("G4P4\nG91G0X-1\nG0X-1\n");
  WaitFor([&] { return cnc.RxBufferUsed() == 15; });  // the G4 consumed, dwelling
  CHECK(cnc.State() == GrblState::kIdle);
  CHECK(cnc.PlannerBlocksQueued() == 0);
  cnc.ResetNow();
  CHECK(*host.Line() == "ok");
  CHECK(*host.Line() == "Grbl 1.1h ['$' for help]");
  CHECK_FALSE(host.Line(0.3));
  CHECK(StateOf(host.Status()) == "Idle");
  CHECK(cnc.RxBufferUsed() == 0);
  CHECK(cnc.TruePositionNow().isApprox(before));
  CHECK(cnc.ReportedPosition().isApprox(belief));
  CHECK(cnc.Stats().alarms == 2);
  CHECK(cnc.Stats().resets == 3);
}

TEST_CASE("Fault: stale bytes left in the pty are the first thing the next host reads",
          "[virtual_cnc]") {
  const std::string stale = "ok\r\nerror:9\r\n<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n";
  VirtualCnc cnc(FastOptions(0));
  {
    Host earlier(cnc.PtyPath());  // an earlier session, now over
    earlier.Until("Grbl 1.1h ['$' for help]");
    CHECK(earlier.Command("G0X-2") == "ok");
  }
  cnc.SendRaw(stale);                                      // while no host has the port open
  WaitFor([&] { return cnc.PendingOutputBytes() == 0; });  // all of it sits in the pty
  Host host(cnc.PtyPath());
  host.Send("G0X-1\n");
  CHECK(*host.Line() == "ok");  // stale, not the reply to G0X-1
  CHECK(*host.Line() == "error:9");
  CHECK(*host.Line() == "<Idle|MPos:0.000,0.000,0.000|FS:0,0>");
  CHECK(*host.Line() == "ok");  // the reply to G0X-1
  CHECK_FALSE(host.Line(0.2));
  CHECK(MPos(host.Status())[0] == -1.0);

  // With reset_on_open, output with nobody listening is lost: SendRaw's included.
  VirtualCncOptions o = FastOptions(0);
  o.reset_on_open = true;
  VirtualCnc lossy(o);
  lossy.SendRaw(stale);
  CHECK(lossy.PendingOutputBytes() == 0);
  Host fresh(lossy.PtyPath());
  CHECK(*fresh.Line() == "Grbl 1.1h ['$' for help]");  // the boot that opening the port caused
  CHECK_FALSE(fresh.Line(0.2));
}

TEST_CASE("grblHAL: welcome - $I - ALARM:11 at power-up - $X refused with error:46 until $H",
          "[virtual_cnc][grblhal]") {
  VirtualCncOptions o;  // homing and soft limits enabled, homing lock on
  o.time_scale = 50;
  o.firmware = CncFirmware::kGrblHal;
  o.initial_true_position = Eigen::Vector3d(-20, -10, -5);
  VirtualCnc cnc(o);
  Host host(cnc.PtyPath());
  CHECK(*host.Line() == kHalWelcome);
  CHECK(*host.Line() == "ALARM:11");
  CHECK(*host.Line() == "[MSG:Homing cycle required]");
  host.Send("$I\n");
  CHECK(*host.Line() == "[VER:1.1f.20240101:]");
  CHECK(*host.Line() == "[OPT:VN,15,128,3,0]");  // the RX buffer size stays the third field
  CHECK(*host.Line() == "[AXS:3:XYZ]");
  CHECK(*host.Line() == "[NEWOPT:ENUMS,RT+,HOME]");
  CHECK(*host.Line() == "[FIRMWARE:grblHAL]");
  CHECK(*host.Line() == "ok");
  // Locked: G-code gets the alarm lock, $X is refused and the Alarm stays.
  CHECK(host.Command("G0X-21") == "error:9");
  CHECK(host.Command("$X") == "error:46");
  CHECK(StateOf(host.Status()) == "Alarm");
  // A reset keeps the lock; ALARM:11 is not printed again (the alarm code did not change).
  host.Send("\x18");
  CHECK(*host.Line() == kHalWelcome);
  CHECK(*host.Line() == "[MSG:Homing cycle required]");
  CHECK_FALSE(host.Line(0.2));
  CHECK(host.Command("$H", 10.0) == "ok");
  CHECK(StateOf(host.Status()) == "Idle");
  CHECK(host.Command("G0X-5") == "ok");
  WaitState(host, "Idle");
  CHECK(cnc.TruePositionNow().isApprox(Eigen::Vector3d(-5, -1, -1), 1e-9));
  // Homed status survives a reset at rest ...
  host.Send("\x18");
  CHECK(*host.Line() == kHalWelcome);
  CHECK_FALSE(host.Line(0.2));
  CHECK(StateOf(host.Status()) == "Idle");
  // ... but not a reset in motion (position lost): locked again.
  CHECK(host.Command("G1X-100F200") == "ok");
  WaitMovingPast(host, -6.0);
  host.Send("\x18");
  CHECK(*host.Line() == "ALARM:3");
  CHECK(*host.Line() == kHalWelcome);
  CHECK(*host.Line() == "ALARM:11");
  CHECK(*host.Line() == "[MSG:Homing cycle required]");
  CHECK(host.Command("$X") == "error:46");
  // A restart is a cold start: locked even after homing.
  CHECK(host.Command("$H", 10.0) == "ok");
  cnc.PowerCycle();
  CHECK(*host.Line() == kHalWelcome);
  CHECK(*host.Line() == "ALARM:11");
  CHECK(*host.Line() == "[MSG:Homing cycle required]");
  CHECK(host.Command("$X") == "error:46");
}

TEST_CASE("grblHAL: one reply per CRLF line - an error latches until an empty line or a $ line",
          "[virtual_cnc][grblhal]") {
  VirtualCncOptions o = FastOptions(0);  // homing disabled: Idle at power-up
  o.firmware = CncFirmware::kGrblHal;
  VirtualCnc cnc(o);
  Host host(cnc.PtyPath());
  CHECK(*host.Line() == kHalWelcome);
  CHECK_FALSE(host.Line(0.2));
  host.Send("G0X-1\r\n");
  CHECK(*host.Line() == "ok");
  CHECK_FALSE(host.Line(0.2));  // GRBL 1.1h answers the empty line after '\r' too
  // After error:20 the following G-code lines are not executed and get error:20 again.
  CHECK(host.Command("G5") == "error:20");
  CHECK(host.Command("G0X-2") == "error:20");
  CHECK(host.Command("(only a comment)") == "error:20");
  CHECK(MPos(host.Status())[0] == -1.0);
  CHECK(host.Command("") == "ok");  // an empty line clears the latch
  CHECK(host.Command("G0X-2") == "ok");
  CHECK(MPos(host.Status())[0] == -2.0);
  // A $ line sets the latch to its own status: $G clears it, a failing one sets it.
  CHECK(host.Command("G5") == "error:20");
  CHECK(host.Command("$G") == "ok");
  CHECK(host.Command("G0X-3") == "ok");
  CHECK(host.Command("$Q") == "error:2");
  CHECK(host.Command("G0X-4") == "error:2");
  CHECK(MPos(host.Status())[0] == -3.0);
  // A reset clears it.
  host.Send("\x18");
  CHECK(*host.Line() == kHalWelcome);
  CHECK(host.Command("G0X-4") == "ok");
  // A failed CRLF line: one reply, and the latch holds for the next one.
  host.Send("G5\r\nG0X-5\r\n");
  CHECK(*host.Line() == "error:20");
  CHECK(*host.Line() == "error:20");
  CHECK_FALSE(host.Line(0.2));
  CHECK(MPos(host.Status())[0] == -4.0);
  CHECK(cnc.Stats().errors == 8);
}

TEST_CASE("homing_init_lock off: Idle at power-up with homing enabled - L in the OPT line",
          "[virtual_cnc][grblhal]") {
  for (const CncFirmware firmware : {CncFirmware::kGrbl11h, CncFirmware::kGrblHal}) {
    const bool hal = firmware == CncFirmware::kGrblHal;
    INFO((hal ? "grblHAL" : "GRBL 1.1h"));
    VirtualCncOptions o;
    o.time_scale = 0;
    o.firmware = firmware;
    o.homing_init_lock = false;
    VirtualCnc cnc(o);
    Host host(cnc.PtyPath());
    CHECK(*host.Line() == (hal ? kHalWelcome : "Grbl 1.1h ['$' for help]"));
    CHECK_FALSE(host.Line(0.2));
    CHECK(StateOf(host.Status()) == "Idle");
    host.Send("$I\n");
    CHECK(host.Line()->rfind("[VER:", 0) == 0);
    CHECK(*host.Line() == (hal ? "[OPT:VNL,15,128,3,0]" : "[OPT:VL,15,128]"));
    host.Until("ok");
    CHECK(host.Command("$X") == "ok");  // outside Alarm: no effect
    CHECK(host.Command("G0X-1") == "ok");
  }
}
