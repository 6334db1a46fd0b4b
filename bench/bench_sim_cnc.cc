// Virtual CNC figures: planner/executor throughput, ground-truth query cost, streaming through
// the pty with character counting, status round trip, and how late the G4 `ok` arrives after
// the motion really ended (the sync rule's latency).
//
//   bench_sim_cnc            (no arguments; ~10 s)
#include <fcntl.h>
#include <poll.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <deque>
#include <random>
#include <string>
#include <vector>

#include "sim/grbl_planner.h"
#include "sim/virtual_cnc.h"

using Clock = std::chrono::steady_clock;

namespace {

double Seconds(Clock::duration d) {
  return std::chrono::duration<double>(d).count();
}

class RawHost {
 public:
  explicit RawHost(const std::string& path) {
    fd_ = ::open(path.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK);
    if (fd_ < 0) {
      std::perror("open pty");
      std::exit(1);
    }
    termios t;
    ::tcgetattr(fd_, &t);
    ::cfmakeraw(&t);
    ::tcsetattr(fd_, TCSANOW, &t);
  }
  ~RawHost() { ::close(fd_); }
  void Send(const std::string& s) {
    std::size_t done = 0;
    while (done < s.size()) {
      const ssize_t n = ::write(fd_, s.data() + done, s.size() - done);
      if (n > 0) {
        done += static_cast<std::size_t>(n);
      } else {
        pollfd p = {fd_, POLLOUT, 0};
        ::poll(&p, 1, 10);
      }
    }
  }
  // Next non-empty line ("" on a 5 s timeout).
  std::string Line() {
    const Clock::time_point deadline = Clock::now() + std::chrono::seconds(5);
    while (Clock::now() < deadline) {
      const std::size_t nl = buf_.find('\n');
      if (nl != std::string::npos) {
        std::string l = buf_.substr(0, nl);
        buf_.erase(0, nl + 1);
        if (!l.empty() && l.back() == '\r') l.pop_back();
        if (!l.empty()) return l;
        continue;
      }
      pollfd p = {fd_, POLLIN, 0};
      ::poll(&p, 1, 20);
      char b[512];
      const ssize_t n = ::read(fd_, b, sizeof(b));
      if (n > 0) buf_.append(b, static_cast<std::size_t>(n));
    }
    return "";
  }
  void WaitFor(const std::string& want) {
    while (true) {
      const std::string l = Line();
      if (l == want || l.empty()) return;
    }
  }

 private:
  int fd_ = -1;
  std::string buf_;
};

double Percentile(std::vector<double> v, double p) {
  std::sort(v.begin(), v.end());
  return v[static_cast<std::size_t>(p * static_cast<double>(v.size() - 1))];
}

void PlannerThroughput() {
  gs360::MotionLimits limits = gs360::GrblSettings().Limits();
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-50, 0);
  const int paths = 2000, blocks = 15;
  long total_blocks = 0;
  double machine = 0;
  const Clock::time_point t0 = Clock::now();
  for (int i = 0; i < paths; ++i) {
    gs360::MotionExecutor ex({}, Eigen::Vector3d(-25, -25, -25), 0.0);
    ex.SetLimits(limits);
    for (int b = 0; b < blocks; ++b) {
      gs360::MoveRate r;
      r.rapid = (b % 3) == 0;
      r.feed_mm_per_min = 600;
      total_blocks += ex.AddLine(Eigen::Vector3d(u(rng), u(rng), u(rng) / 4), r, 0.0);
    }
    ex.StartCycle(0.0);
    ex.AdvanceTo(1e9);
    machine += ex.History(0, 1e9).back().t1;
  }
  const double wall = Seconds(Clock::now() - t0);
  std::printf("planner+executor: %ld blocks in %.3f s = %.0f blocks/s (%.0f machine s simulated)\n",
              total_blocks, wall, static_cast<double>(total_blocks) / wall, machine);

  // Ground-truth queries over a long recorded history.
  gs360::MotionExecutor ex({}, Eigen::Vector3d(-25, -25, -25), 0.0);
  ex.SetLimits(limits);
  double t = 0;
  for (int i = 0; i < 10000; ++i) {
    if (ex.PlannerFull()) {
      t += 0.5;
      ex.AdvanceTo(t);
      continue;
    }
    gs360::MoveRate r;
    r.rapid = false;
    r.feed_mm_per_min = 1200;
    ex.AddLine(Eigen::Vector3d(u(rng), u(rng), u(rng) / 4), r, t);
    ex.StartCycle(t);
  }
  ex.AdvanceTo(1e9);
  const double end = ex.StateTime();
  const int queries = 1000000;
  double sink = 0;
  const Clock::time_point q0 = Clock::now();
  for (int i = 0; i < queries; ++i) sink += ex.PositionAt(end * (i % 997) / 997.0)[0];
  const double qwall = Seconds(Clock::now() - q0);
  std::printf("PositionAt (past, %zu pieces of history): %.0f ns/query (checksum %.1f)\n",
              ex.History(0, 1e9).size(), 1e9 * qwall / queries, sink);
}

void Streaming(int baud) {
  gs360::VirtualCncOptions o;
  o.time_scale = 0;  // instant: measures the protocol, not the motion
  o.baud_rate = baud;
  o.settings.homing_enable = false;
  o.settings.soft_limits = false;
  gs360::VirtualCnc cnc(o);
  RawHost host(cnc.PtyPath());
  host.WaitFor("Grbl 1.1h ['$' for help]");
  std::vector<std::string> lines;
  for (int i = 0; i < 3000; ++i) {
    char l[64];
    std::snprintf(l, sizeof(l), "G1X%.3fY%.3fF1200", -1.0 - (i % 50) * 0.5, -1.0 - (i % 7));
    lines.push_back(l);
  }
  std::deque<std::size_t> in_flight;
  std::size_t outstanding = 0, next = 0, oks = 0;
  const Clock::time_point t0 = Clock::now();
  while (oks < lines.size()) {
    while (next < lines.size() && outstanding + lines[next].size() + 1 <= 128) {
      host.Send(lines[next] + "\n");
      in_flight.push_back(lines[next].size() + 1);
      outstanding += lines[next].size() + 1;
      ++next;
    }
    const std::string l = host.Line();
    if (l.empty()) break;
    if (l == "ok") {
      ++oks;
      outstanding -= in_flight.front();
      in_flight.pop_front();
    }
  }
  const double wall = Seconds(Clock::now() - t0);
  std::printf(
      "streaming (instant mode, baud %d%s, char counting): %zu lines in %.2f s = %.0f lines/s\n",
      baud, baud ? "" : " = unpaced", oks, wall, static_cast<double>(oks) / wall);
}

void Latencies() {
  gs360::VirtualCncOptions o;
  o.time_scale = 1;
  o.settings.homing_enable = false;
  o.settings.soft_limits = false;
  gs360::VirtualCnc cnc(o);
  RawHost host(cnc.PtyPath());
  host.WaitFor("Grbl 1.1h ['$' for help]");
  std::vector<double> status_rtt;
  for (int i = 0; i < 200; ++i) {
    const Clock::time_point t0 = Clock::now();
    host.Send("?");
    while (host.Line().rfind("<", 0) != 0) {
    }
    status_rtt.push_back(Seconds(Clock::now() - t0) * 1000);
  }
  std::printf("status '?' round trip (idle, 115200 baud): median %.2f ms, p95 %.2f ms\n",
              Percentile(status_rtt, 0.5), Percentile(status_rtt, 0.95));

  // Press-like sequences: feed move then G4 P0; how long after the true end of motion the host
  // holds the ok.
  std::vector<double> late;
  for (int i = 0; i < 20; ++i) {
    host.Send(i % 2 ? "G1X-2F600\nG4P0\n" : "G1X-1F600\nG4P0\n");
    host.WaitFor("ok");
    host.WaitFor("ok");
    const Clock::time_point ok = Clock::now();
    const auto pieces = cnc.TrueTrajectory(ok - std::chrono::seconds(2), ok);
    const double end_machine = pieces.back().t1;
    late.push_back((cnc.MachineTime(ok) - end_machine) * 1000);
  }
  std::printf("G4 ok after the true end of motion (time scale 1): median %.2f ms, max %.2f ms\n",
              Percentile(late, 0.5), Percentile(late, 1.0));
}

}  // namespace

int main() {
  PlannerThroughput();
  Streaming(115200);
  Streaming(0);
  Latencies();
  return 0;
}
