#pragma once
// A Marlin 2.x printer (or Klipper's G-code pseudo-terminal) as a Machine (gcode/machine.h), over
// the synchronous MarlinClient (gcode/marlin_client.h) on a worker thread of its own: lines queue
// and run one at a time, each answered when the printer has processed it.
//
// The engine's G-code, as Marlin takes it (MarlinCommandsFor):
//   "G21", "G90"                     as they are
//   "G90 G53 G0 X Y Z"               "G90", then "G0 X Y Z F<rapid>"
//   "G53 G0 X Y Z"                   "G0 X Y Z F<rapid>": Marlin's G0 moves at the modal feed, so
//                                    the rapid rate is given (the axes' M203 limits cap it)
//   "G53 G1 X Y Z F<f>"              "G1 X Y Z F<f>" (printers have no G53: their coordinates are
//                                    the machine's)
//   "G4 P<seconds>"                  "M400", then "G4 P<milliseconds>": its ok comes once every
//                                    move has ended and the dwell elapsed (the press's sync)
// Status: "M114 R" (the steppers' position; a firmware without M114_REALTIME answers it as M114,
// the planned position, which equals the real one once M400 has returned). Homing: "G28".
//
// Position (docs/running.md, "Where the tool is"): not trusted after Connect(), a reboot (Marlin
// believes 0,0,0 until homed) or a halt; motion is refused until Home() or MarkPositionTrusted().
// A reboot on open or mid-run loses the position (PositionLost()) until Home() or
// MarkPositionTrusted(); a halt (kill(), M112) is an alarm (Alarmed()) that only resetting the
// printer and connecting again ends.

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "gcode/machine.h"
#include "gcode/marlin_client.h"
#include "gcode/transport.h"

namespace gs360 {

struct MarlinMachineOptions {
  MarlinClientOptions client;
  std::chrono::milliseconds homing_timeout{180000};
  // How long one command may run while the printer says it is busy (a long M400 or G4).
  std::chrono::milliseconds command_timeout{600000};
  // G0's feed (mm/min); 0: the fastest axis rate M503 reports (M203), else `fallback_rapid`.
  double rapid_mm_per_min = 0.0;
  double fallback_rapid_mm_per_min = 3000.0;
  // Reconnect retry backoff.
  std::chrono::milliseconds reconnect_backoff{500};

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

// The Marlin commands for one of the engine's lines (see the header). Throws
// std::invalid_argument for a GRBL system command ('$...') or a G53 line of another form.
std::vector<std::string> MarlinCommandsFor(std::string_view line, double rapid_mm_per_min);

// M503's motion lines ("M203 X500.00 Y500.00 Z5.00 E25.00" mm/s, "M201 ..." mm/s^2, "M205 ...
// J0.013") into `settings` (rates in mm/min); returns whether both rates and accelerations were
// there.
bool ReadMarlinSettings(const std::vector<MarlinMessage>& m503, MachineSettings* settings);

class MarlinMachine : public Machine {
 public:
  using TransportFactory = std::function<std::unique_ptr<Transport>()>;

  MarlinMachine(TransportFactory factory, const MarlinMachineOptions& options = {});
  static std::unique_ptr<MarlinMachine> ForUri(const std::string& uri,
                                               const TransportOptions& transport_options,
                                               const MarlinMachineOptions& options = {});
  ~MarlinMachine() override;
  MarlinMachine(const MarlinMachine&) = delete;
  MarlinMachine& operator=(const MarlinMachine&) = delete;

  // Opens the port, waits out a reboot on open (then: Alarmed()), M115, M211, M503. Throws
  // MarlinError and TransportError.
  MachineInfo Connect() override;
  bool Reconnect(std::chrono::milliseconds timeout) override;
  bool Connected() const override;
  MachineHandle Send(std::string_view line) override;
  // G28 (after "G91", "G0 Z<lift> F<Z's rate>", "G90" when lift_mm > 0).
  MachineReply Home(double lift_mm) override;
  bool HomesZFirst() const override { return false; }  // G28: X, then Y, then Z
  std::chrono::milliseconds HomingTimeout() const override { return options_.homing_timeout; }
  MachineReply Unlock() override;
  // Marlin has no soft reset: the port is opened again (most boards reboot when it is).
  bool SoftReset() override;
  std::optional<MachineStatus> LatestStatus() const override;
  std::optional<MachineStatus> QueryStatus(std::chrono::milliseconds timeout) override;
  MachineWaitResult WaitIdle(std::chrono::milliseconds timeout) override;
  bool Held() const override { return false; }
  bool Alarmed() const override;  // halted
  bool PositionLost() const override;
  std::string AlarmText() const override;
  bool PositionTrusted() const override;
  void MarkPositionTrusted() override;
  // Numbered lines: a line written into a rebooting board is refused by its new boot, never run.
  std::uint64_t StrayRepliesSinceWelcome() const override { return 0; }
  bool RepliesCanBeLost() const override { return false; }
  std::uint64_t UnreadableLines() const override;

  const MarlinInfo& Info() const { return info_; }

 private:
  struct Job;
  class Source;

  // `kind`: Job::Kind (0: a line). Resolved at once when refused.
  std::shared_ptr<Job> Enqueue(std::vector<std::string> commands, std::string line, bool motion,
                               int kind);
  void Worker();
  void Run(const std::shared_ptr<Job>& job);
  // The job failed with `kind`: it and every job still queued resolve (under mu_).
  void FailLocked(const std::shared_ptr<Job>& job, MachineReplyKind kind, const std::string& why,
                  std::optional<std::string> alarm);
  void Resolve(const std::shared_ptr<Job>& job, MachineReply reply);
  void StopWorker();
  void StartWorker();
  MachineInfo Handshake();

  TransportFactory factory_;
  MarlinMachineOptions options_;
  MarlinInfo info_;
  double rapid_mm_per_min_ = 0.0;
  double z_rate_mm_per_min_ = 300.0;  // Z's M203 (the lift before homing)

  mutable std::mutex mu_;
  std::condition_variable cv_;
  std::unique_ptr<MarlinClient> client_;  // the worker's while it runs
  std::thread worker_;
  bool stop_ = false;
  std::deque<std::shared_ptr<Job>> queue_;
  std::uint64_t next_sequence_ = 0;
  bool connected_ = false;
  bool trusted_ = false;
  bool halted_ = false;
  bool rebooted_ = false;    // since the position was last established
  bool unanswered_ = false;  // the printer stopped answering: nothing more until reconnected
  bool moved_ = false;       // motion sent since the last M400 or G4 ended
  std::string alarm_text_;
  std::optional<MachineStatus> latest_;
  std::uint64_t unreadable_ = 0;
};

}  // namespace gs360
