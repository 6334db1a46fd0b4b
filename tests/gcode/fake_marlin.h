#pragma once
// A scripted Marlin 2.x printer on a pseudo-terminal for the client tests: it checks every line's
// number and checksum as Marlin's queue does (refusing with an error, a Resend and an ok), runs
// the few commands a probe run needs (G0/G1 move at once, G28 homes to 0,0,0 with busy
// keep-alives, M400, M114, M115 with capabilities, M211, M110, M112 halts), and injects the faults
// that matter: a garbled line, a lost ok, a reboot. Not the virtual printer (no motion in time).

#include <atomic>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <Eigen/Core>

#include "sim/pty.h"

namespace gs360::test {

struct FakeMarlinOptions {
  bool reboot_on_open = true;  // print "start" and a banner once the fake runs (a DTR reset)
  int garble_line = -1;        // this line number arrives with a bit flipped, once
  int drop_ok_line = -1;       // this line number's ok is lost, once
  int reboot_at_line = -1;     // this line number reboots the board instead of running, once
  bool busy_forever = false;   // answers every line with "echo:busy: processing", never ok
};

class FakeMarlin {
 public:
  explicit FakeMarlin(const FakeMarlinOptions& options = {});
  ~FakeMarlin();
  const std::string& Path() const { return pty_.slave_path(); }
  // Commands run, in order (without numbers and checksums).
  std::vector<std::string> Ran() const;
  Eigen::Vector3d Position() const;

 private:
  void Serve();
  void Reply(const std::string& text);
  void Line(std::string line);
  void Run(const std::string& command);

  FakeMarlinOptions options_;
  Pty pty_;
  std::atomic<bool> stop_{false};
  mutable std::mutex mu_;
  std::vector<std::string> ran_;
  Eigen::Vector3d position_ = Eigen::Vector3d::Zero();
  long last_ = -1;
  bool halted_ = false;
  std::thread thread_;
};

}  // namespace gs360::test
