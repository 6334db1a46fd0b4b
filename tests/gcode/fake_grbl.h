#pragma once
// A scripted GRBL 1.1 peer for the client tests: it serves one file descriptor (a pty master it
// creates, or an accepted TCP socket), records what it receives, and checks the host's character
// counting: the bytes received and not yet consumed by its line processor may never exceed the
// advertised RX buffer (GRBL drops such bytes; the fake drops them too and flags the overflow).
// Real-time bytes (? ! ~ 0x18) are picked off on arrival, as GRBL's serial ISR does.
//
// Lines are processed one at a time on a processor thread, which can be paused so the host's
// buffer fills. Default replies: $I -> [VER]/[OPT]/ok, $$ -> settings/ok, $H -> ok (homed at
// 0,0,0), $X -> [MSG:Caution: Unlocked]/ok, G-code in alarm -> error:9, other lines -> ok (axis
// words move the position at once). A responder can override the reply of any line; reply lines
// are interpreted as they are written ("ALARM:N" alarms the fake, a welcome resets it).

#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <Eigen/Core>

namespace gs360 {

inline constexpr const char* kFakeWelcome = "Grbl 1.1h ['$' for help]";
// In a responder's reply: stop here until the host sends a soft reset (0x18), then write the
// rest (GRBL's critical-alarm loop: ALARM:2, [MSG:Reset to continue], wait, ok, welcome).
inline constexpr const char* kFakeWaitReset = "\x01wait-reset";

struct FakeGrblOptions {
  int rx_size = 128;
  int planner_blocks = 15;
  bool report_opt = true;                   // $I prints [OPT:V,blocks,rx_size]
  bool welcome_on_start = true;             // print the welcome as soon as the fake starts
  bool alarm_at_start = false;              // start in Alarm with [MSG:'$H'|'$X' to unlock]
  std::chrono::microseconds line_delay{0};  // processing time per line
};

struct FakeLine {
  std::string line;
  std::size_t unanswered_at_arrival = 0;  // earlier lines received and not yet answered
  std::size_t outstanding_bytes = 0;      // RX bytes held after this line arrived
  std::chrono::steady_clock::time_point at{};
};

struct FakeRealtime {
  char byte = 0;
  std::size_t unanswered_lines = 0;  // lines received and not answered when it arrived
  std::chrono::steady_clock::time_point at{};
};

class FakeGrbl {
 public:
  using Responder = std::function<std::optional<std::vector<std::string>>(const std::string&)>;

  // A fresh pseudo-terminal pair; the host opens Path() (the slave). Slave in raw mode.
  static std::unique_ptr<FakeGrbl> CreatePty(FakeGrblOptions options = {});
  // Serves an already connected descriptor (e.g. an accepted socket); takes ownership.
  FakeGrbl(int fd, int slave_fd, std::string path, FakeGrblOptions options);
  ~FakeGrbl();
  FakeGrbl(const FakeGrbl&) = delete;
  FakeGrbl& operator=(const FakeGrbl&) = delete;

  const std::string& Path() const { return path_; }

  void SetResponder(Responder responder);
  // While off, complete lines wait unprocessed in the RX buffer.
  void SetProcessing(bool on);
  // Writes raw bytes to the host (garbage, unsolicited messages). "\r\n" is not added.
  void Emit(const std::string& bytes);
  // A spontaneous reset (power glitch, watchdog): buffers flushed, welcome printed.
  void ResetAndWelcome();
  // Hangs up (like a USB unplug): the host sees its port vanish.
  void Close();

  std::vector<FakeLine> Lines() const;
  std::vector<FakeRealtime> Realtime() const;
  std::size_t CountRealtime(char c) const;
  std::size_t MaxOutstandingBytes() const;
  bool Overflowed() const;
  std::size_t Pending() const;  // complete lines waiting for the processor
  Eigen::Vector3d Position() const;
  bool InAlarm() const;

  // Polls `pred` every 2 ms until true or timeout.
  static bool WaitUntil(const std::function<bool()>& pred, std::chrono::milliseconds timeout);

 private:
  void ReaderLoop();
  void ProcessorLoop();
  std::vector<std::string> DefaultReply(const std::string& line);
  void WriteReplies(const std::vector<std::string>& lines);
  void ResetLocked();
  std::string StatusReportLocked() const;
  void WriteRaw(const std::string& bytes);

  int fd_;
  int slave_fd_;
  std::string path_;
  FakeGrblOptions options_;

  mutable std::mutex mu_;
  std::condition_variable cv_;
  std::mutex write_mu_;
  bool stop_ = false;
  bool closed_ = false;
  bool processing_ = true;
  bool busy_ = false;  // the processor holds a line it has not answered yet
  bool waiting_reset_ = false;
  std::size_t resets_ = 0;
  std::string partial_;
  std::vector<std::string> pending_;
  std::size_t outstanding_ = 0;
  std::size_t max_outstanding_ = 0;
  bool overflowed_ = false;
  bool alarm_;
  bool hold_ = false;
  Eigen::Vector3d position_ = Eigen::Vector3d::Zero();
  std::vector<FakeLine> lines_;
  std::vector<FakeRealtime> realtime_;
  Responder responder_;
  std::thread reader_;
  std::thread processor_;
};

}  // namespace gs360
