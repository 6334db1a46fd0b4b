// The plan's motion estimate against the virtual CNC executing the plan's G-code in real time
// (serial pacing, the planner re-planning as lines arrive): the machine's own trajectory
// (ground truth) must take the estimated time. The host here is a minimal send-response
// streamer on the pty (each line waits for its `ok`, which GRBL sends when the line is queued,
// so motion is still pipelined), independent of the GRBL client.

#include <fcntl.h>
#include <termios.h>
#include <unistd.h>

#include <poll.h>
#include <catch2/catch.hpp>
#include <chrono>
#include <stdexcept>
#include <string>

#include "gcode/probe_program.h"
#include "sim/virtual_cnc.h"

using namespace gs360;
using Clock = std::chrono::steady_clock;

namespace {

class PtyHost {
 public:
  explicit PtyHost(const std::string& path) {
    fd_ = ::open(path.c_str(), O_RDWR | O_NOCTTY);
    if (fd_ < 0) throw std::runtime_error("cannot open " + path);
    termios t{};
    ::tcgetattr(fd_, &t);
    ::cfmakeraw(&t);
    ::tcsetattr(fd_, TCSANOW, &t);
  }
  ~PtyHost() { ::close(fd_); }

  // Next line (without "\r\n"); throws after `timeout_s`.
  std::string ReadLine(double timeout_s) {
    const auto deadline = Clock::now() + std::chrono::duration<double>(timeout_s);
    for (;;) {
      if (const auto nl = buf_.find('\n'); nl != std::string::npos) {
        std::string line = buf_.substr(0, nl);
        buf_.erase(0, nl + 1);
        if (!line.empty() && line.back() == '\r') line.pop_back();
        if (!line.empty()) return line;
        continue;
      }
      const auto left =
          std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
      if (left.count() <= 0) throw std::runtime_error("timeout waiting for a line");
      pollfd p{fd_, POLLIN, 0};
      if (::poll(&p, 1, static_cast<int>(left.count())) > 0) {
        char b[256];
        const ssize_t n = ::read(fd_, b, sizeof(b));
        if (n > 0) buf_.append(b, static_cast<std::size_t>(n));
      }
    }
  }

  // Sends a line and waits for its ok (other lines skipped); returns the time the ok arrived.
  Clock::time_point Send(const std::string& line, double timeout_s = 20.0) {
    const std::string bytes = line + "\n";
    if (::write(fd_, bytes.data(), bytes.size()) != static_cast<ssize_t>(bytes.size())) {
      throw std::runtime_error("write failed");
    }
    for (;;) {
      const std::string reply = ReadLine(timeout_s);
      if (reply == "ok") return Clock::now();
      if (reply.rfind("error:", 0) == 0 || reply.rfind("ALARM:", 0) == 0) {
        throw std::runtime_error("'" + line + "' -> " + reply);
      }
    }
  }
  Clock::time_point SendAll(const std::vector<std::string>& lines) {
    Clock::time_point t{};
    for (const auto& l : lines) t = Send(l);
    return t;
  }

 private:
  int fd_ = -1;
  std::string buf_;
};

}  // namespace

TEST_CASE("Probe motion on the virtual CNC takes the estimated time", "[plan][sim]") {
  VirtualCncOptions vo;
  vo.time_scale = 1.0;  // real time: what the overnight run does
  VirtualCnc cnc(vo);
  PtyHost host(cnc.PtyPath());
  while (host.ReadLine(5.0).rfind("Grbl", 0) != 0) {
  }
  host.Send("$X");

  // The virtual CNC's settings, and a sensor mounted near the home corner (short first travel).
  PlanOptions o;
  const GrblSettings s = cnc.Settings();
  o.machine.max_rate_mm_per_min = s.max_rate_mm_per_min;
  o.machine.acceleration_mm_per_s2 = s.acceleration_mm_per_s2;
  o.machine.max_travel_mm = s.max_travel_mm;
  o.machine.junction_deviation_mm = s.junction_deviation_mm;
  o.probe_count = 60;
  o.reference_every = 0;
  RigConfig ro;
  ro.base_in_machine = Eigen::Vector3d(-25.0, -25.0, -93.0);
  const ProbePlan plan = MakeProbePlan(MakeRigGeometry(ro), o);
  REQUIRE(plan.probes.size() >= 3);

  host.SendAll(ProgramPreamble());
  Clock::time_point retract_sent{};
  for (int k = 0; k < 3; ++k) {
    const PlannedProbe& p = plan.probes[k];
    const ProbeProgram prog = MakeProbeProgram(p, o);
    if (!prog.reference.empty()) host.SendAll(prog.reference);
    const Clock::time_point ok = host.SendAll(prog.press);
    if (k > 0) {
      // The motion since the previous retract was sent: retract, travel, approach, press.
      const auto pieces = cnc.TrueTrajectory(retract_sent, ok);
      REQUIRE_FALSE(pieces.empty());
      const double motion = pieces.back().t1 - pieces.front().t0;
      std::vector<Move> moves{{plan.probes[k - 1].retract_machine, o.retract_feed_mm_per_min}};
      for (const auto& w : p.travel_machine) moves.push_back({w, 0.0});
      moves.push_back({p.approach_machine, 0.0});
      moves.push_back({p.press_machine, o.press_feed_mm_per_min});
      const double grbl =
          PathTime(plan.probes[k - 1].press_machine, moves, o.machine, JunctionModel::kGrbl);
      const double stop =
          PathTime(plan.probes[k - 1].press_machine, moves, o.machine, JunctionModel::kStop);
      INFO("probe " << k << ": machine " << motion << " s, estimate " << grbl << " s, stop bound "
                    << stop << " s");
      CHECK(motion == Approx(grbl).epsilon(0.005).margin(0.005));
      CHECK(motion <= stop + 0.005);
      // The sync: the ok arrives after the motion ended and the dwell elapsed.
      CHECK(cnc.MachineTime(ok) >= pieces.back().t1 + o.settle_dwell_s - 0.001);
      // And the machine stopped where the plan pressed.
      CHECK((pieces.back().End() - p.press_machine).norm() < 0.002);
    }
    retract_sent = Clock::now();
    host.SendAll(prog.retract);
  }
}
