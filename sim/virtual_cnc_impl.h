#pragma once
// Internal to the virtual CNC (sim/virtual_cnc*.cc): the implementation class, shared by
// virtual_cnc.cc (protocol, motion, homing, I/O), virtual_cnc_dialect.cc (where GRBL 1.1h and
// grblHAL differ) and virtual_cnc_faults.cc (board-side faults). Not part of the public API:
// include sim/virtual_cnc.h instead.

#include <algorithm>
#include <array>
#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <limits>
#include <mutex>
#include <optional>
#include <random>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "sim/grbl_gcode.h"
#include "sim/pty.h"
#include "sim/virtual_cnc.h"

namespace gs360 {
namespace virtual_cnc_internal {

using Clock = std::chrono::steady_clock;

// Wall time -> machine time. A constant scale, or (instant mode, scale 0) a staircase that
// jumps whenever the controller completes motion or a dwell.
class MachineClock {
 public:
  // `history`: jumps kept (instant mode); older wall instants cannot be mapped any more.
  MachineClock(double scale, Clock::time_point start, std::size_t history)
      : scale_(scale), history_(history) {
    segments_.push_back({start, 0.0});
  }

  bool instant() const { return scale_ <= 0.0; }
  std::uint64_t jumps() const { return jumps_; }

  // Throws std::out_of_range for a wall instant before the oldest kept jump (instant mode, once
  // jumps were evicted): the machine time there is no longer known.
  double At(Clock::time_point w) const {
    auto it =
        std::upper_bound(segments_.begin(), segments_.end(), w,
                         [](Clock::time_point value, const Segment& s) { return value < s.wall; });
    if (it == segments_.begin() && truncated_) {
      throw std::out_of_range(
          "VirtualCnc: wall instant " +
          std::to_string(std::chrono::duration<double>(segments_.front().wall - w).count()) +
          " s before the oldest of the " + std::to_string(segments_.size()) +
          " instant-mode clock jumps kept; raise history_pieces");
    }
    if (it != segments_.begin()) --it;
    if (instant()) return it->machine;
    return it->machine + std::chrono::duration<double>(w - it->wall).count() * scale_;
  }

  // The wall instant at which machine time m is reached (now-ish in instant mode).
  Clock::time_point WallAt(double m) const {
    const Segment& s = segments_.back();
    if (instant()) return s.wall;
    return s.wall + std::chrono::duration_cast<Clock::duration>(
                        std::chrono::duration<double>((m - s.machine) / scale_));
  }

  void JumpTo(Clock::time_point w, double m) {
    if (!instant() || m <= At(w)) return;
    segments_.push_back({w, m});
    ++jumps_;
    while (segments_.size() > history_) {
      segments_.pop_front();
      truncated_ = true;
    }
  }

 private:
  struct Segment {
    Clock::time_point wall;
    double machine;
  };
  double scale_;
  std::size_t history_;
  std::deque<Segment> segments_;
  bool truncated_ = false;  // segments were evicted: instants before front() are unknown
  std::uint64_t jumps_ = 0;
};

// One line as protocol_main_loop() assembles it from the RX buffer (GRBL 1.1h filtering:
// spaces, control characters and comments dropped, upper case, LINE_BUFFER_SIZE - 1 characters).
struct LineBuffer {
  std::string line;  // the significant characters
  bool overflow = false;
  bool paren = false;
  bool semicolon = false;
  std::size_t kept = 0;  // characters grblHAL would keep (its char_counter: comments included)
  char eol = 0;          // the last line terminator acted on (grblHAL's `eol`)

  void Add(char c);
  // grblHAL: true for the second terminator of a "\r\n" or "\n\r" pair, which is not a line.
  // Otherwise records `c` as the terminator of the current line.
  bool PairedTerminator(char c);
  // After a line has been executed (the terminator is remembered).
  void Clear();
};

// The Marlin dialect's state (virtual_cnc_marlin.cc), reset at every boot.
struct MarlinState {
  long last_n = 0;                                     // serial_state.last_N
  double feed_mm_min = 1500.0;                         // feedrate_mm_s, shared by G0 and G1
  bool relative = false;                               // G91
  int homed = 0;                                       // bit per axis homed since boot
  bool soft_endstops = true;                           // M211
  bool in_command = false;                             // KEEPALIVE_STATE(IN_HANDLER)
  double next_busy = 0.0;                              // machine time of the next keep-alive
  double temperature_s = 0.0, next_temperature = 0.0;  // M155
  double position_s = 0.0, next_position = 0.0;        // M154
  std::string ep_line;  // the emergency parser's view of the line arriving
};
struct MarlinWords;
// rt_alarm_ value that halts a Marlin printer (kill()): M112, a fault, a failed homing.
inline constexpr int kMarlinKill = 255;

}  // namespace virtual_cnc_internal

class VirtualCnc::Impl {
 public:
  explicit Impl(const VirtualCncOptions& options);
  ~Impl() { Stop(); }

  void Stop();
  std::string PtyPath() const {
    std::lock_guard<std::mutex> lk(mu_);
    return plugged_ ? pty_.slave_path() : std::string();
  }
  const VirtualCncOptions& options() const { return options_; }

  Eigen::Vector3d TruePosition(Clock::time_point t) const {
    std::lock_guard<std::mutex> lk(mu_);
    return exec_.PositionAt(clock_.At(t));
  }
  double TrueSpeed(Clock::time_point t) const {
    std::lock_guard<std::mutex> lk(mu_);
    return exec_.SpeedAt(clock_.At(t));
  }
  std::vector<MotionPiece> TrueTrajectory(Clock::time_point from, Clock::time_point to) const {
    std::lock_guard<std::mutex> lk(mu_);
    return exec_.History(clock_.At(from), clock_.At(to));
  }
  double MachineTime(Clock::time_point t) const {
    std::lock_guard<std::mutex> lk(mu_);
    return clock_.At(t);
  }
  Eigen::Vector3d ReportedPosition() const {
    std::lock_guard<std::mutex> lk(mu_);
    return Belief();
  }
  GrblState State() const {
    std::lock_guard<std::mutex> lk(mu_);
    return state_;
  }
  GrblSettings Settings() const {
    std::lock_guard<std::mutex> lk(mu_);
    return settings_;
  }
  int PlannerBlocksQueued() const {
    std::lock_guard<std::mutex> lk(mu_);
    return exec_.BlockCount();
  }
  int RxBufferUsed() const {
    std::lock_guard<std::mutex> lk(mu_);
    return static_cast<int>(rx_.size());
  }
  VirtualCncStats Stats() const {
    std::lock_guard<std::mutex> lk(mu_);
    VirtualCncStats stats = stats_;
    stats.clock_jumps = clock_.jumps();
    return stats;
  }

  void DropNextBytes(std::size_t n, FaultDirection d) {
    std::lock_guard<std::mutex> lk(mu_);
    if (d != FaultDirection::kCncToHost) to_cnc_.drop_next += n;
    if (d != FaultDirection::kHostToCnc) to_host_.drop_next += n;
  }
  void SetDropProbability(double p, FaultDirection d) {
    if (!(p >= 0.0 && p <= 1.0)) {
      throw std::invalid_argument("SetDropProbability: p must be in [0, 1], got " +
                                  std::to_string(p));
    }
    std::lock_guard<std::mutex> lk(mu_);
    if (d != FaultDirection::kCncToHost) to_cnc_.drop_probability = p;
    if (d != FaultDirection::kHostToCnc) to_host_.drop_probability = p;
  }
  void GarbleNextBytes(std::size_t n, FaultDirection d) {
    std::lock_guard<std::mutex> lk(mu_);
    if (d != FaultDirection::kCncToHost) to_cnc_.garble_next += n;
    if (d != FaultDirection::kHostToCnc) to_host_.garble_next += n;
  }
  void StallReplies(std::chrono::milliseconds duration) {
    std::lock_guard<std::mutex> lk(mu_);
    stall_until_ = std::max(stall_until_, Clock::now() + duration);
    WakeIo();
  }
  void Unplug(const UnplugOptions& unplug);
  void Replug() {
    std::lock_guard<std::mutex> lk(mu_);
    ReplugLocked();
  }
  bool Plugged() const {
    std::lock_guard<std::mutex> lk(mu_);
    return plugged_;
  }
  bool HostAttached() const {
    std::lock_guard<std::mutex> lk(mu_);
    return plugged_ && host_open_;
  }
  void RaiseAlarmDuringNextMove(int code, double fraction) {
    if (code < 1 || code > 255 || !(fraction >= 0.0 && fraction <= 1.0)) {
      throw std::invalid_argument(
          "RaiseAlarmDuringNextMove: code must be 1..255 and fraction in [0, 1], got " +
          std::to_string(code) + ", " + std::to_string(fraction));
    }
    std::lock_guard<std::mutex> lk(mu_);
    armed_alarm_ = ArmedAlarm{code, fraction};
  }
  void LosePositionOnReset(bool lose) {
    std::lock_guard<std::mutex> lk(mu_);
    lose_position_ = lose;
  }
  // Board-side faults (virtual_cnc_faults.cc).
  void PowerCycle();
  void ResetNow();
  void ResetDuringNextDwell() {
    std::lock_guard<std::mutex> lk(mu_);
    reset_at_dwell_ = true;
  }
  void SendRaw(const std::string& bytes);
  std::size_t PendingOutputBytes() const;
  void FeedHoldPin();
  void LoseNextReply(const std::string& instead);

 private:
  using Lock = std::unique_lock<std::mutex>;
  using LineBuffer = virtual_cnc_internal::LineBuffer;
  struct LinkFaults {
    std::size_t drop_next = 0;
    std::size_t garble_next = 0;
    double drop_probability = 0.0;
  };

  // ----- clock, motion, positions (mu_ held) -----
  double MachineNow() const { return clock_.At(Clock::now()); }
  Eigen::Vector3d Quantize(const Eigen::Vector3d& p) const {
    Eigen::Vector3d q;
    for (int i = 0; i < 3; ++i) {
      q[i] = static_cast<double>(std::lround(p[i] * settings_.steps_per_mm[i])) /
             settings_.steps_per_mm[i];
    }
    return q;
  }
  Eigen::Vector3d Belief() const { return Quantize(exec_.PositionAt(MachineNow()) - offset_); }
  void UpdateMotion();
  void LosePosition();

  // ----- "ISR" side (mu_ held) -----
  void OnHostByte(unsigned char c);
  void McReset();
  void WakeIo() {
    const char b = 1;
    [[maybe_unused]] ssize_t n = ::write(wake_[1], &b, 1);
  }
  // Output of the running firmware (dropped when it belongs to a previous power-up).
  void Emit(const std::string& s);
  // Bytes into the UART: dropped unplugged, unpowered, or with nobody listening (reset_on_open).
  void Transmit(const std::string& s);

  // ----- power (mu_ held) -----
  void PowerOn();
  void PowerOff();
  void ReplugLocked();
  void Reboot();  // power off and on at once, the link staying up (PowerCycle, reset_on_open)
  // The firmware thread is unwinding a run the board no longer executes (power lost or a newer
  // power-up): it must not report anything.
  bool Rebooted() const { return !powered_ || boot_id_ != running_boot_; }

  // ----- firmware thread -----
  void FirmwareMain();
  void InitAfterReset();
  void ProtocolMainLoop(Lock& lk);

  // ----- Marlin (virtual_cnc_marlin.cc) -----
  using MarlinWords = virtual_cnc_internal::MarlinWords;
  bool Marlin() const { return options_.firmware == CncFirmware::kMarlin; }
  std::string MarlinBoot() const;    // "start" and the boot echoes
  void MarlinInit();                 // after every boot
  void MarlinEmergencyByte(char c);  // the ISR's emergency parser (mu_ held)
  void MarlinKill(Lock& lk);         // kill(): the message, then nothing until a reboot
  double MarlinNextIdleEvent() const;
  void MarlinIdle();  // keep-alive and auto-reports when due
  void MarlinMainLoop(Lock& lk);
  void MarlinLineError(const char* error);
  bool MarlinFraming(const std::string& line);
  void MarlinLine(Lock& lk, const std::string& raw);
  bool MarlinCommand(Lock& lk, const std::string& command);
  bool MarlinMCode(Lock& lk, const MarlinWords& w, const std::string& command);
  void MarlinMove(Lock& lk, std::optional<double> x, std::optional<double> y,
                  std::optional<double> z, std::optional<double> f);
  void MarlinHome(Lock& lk, bool x, bool y, bool z);
  bool MarlinHomeAxis(Lock& lk, int axis);
  std::string MarlinPosition(bool real) const;
  void MarlinReportFirmware();
  void MarlinReportSettings();

  // ----- dialect (virtual_cnc_dialect.cc) -----
  bool GrblHal() const { return options_.firmware == CncFirmware::kGrblHal; }
  const char* Welcome() const;
  // grblHAL limits_homing_required(): homing lock on, homing enabled, not homed.
  bool HomingRequired() const;
  // The start of protocol_main_loop(): alarm messages or startup lines. False when aborted.
  bool EnterMainLoop(Lock& lk);
  // One received line: dispatch, alarm lock, grblHAL's error latch. Returns its status.
  int ExecuteLine(Lock& lk, const LineBuffer& in);
  void ReportBuildInfo();          // `$I`
  void ReportCoordinates();        // `$#`
  int RestoreDefaults(char what);  // `$RST=` + what; a GRBL status
  bool Aborting() const { return rt_reset_ || stop_ || !powered_ || boot_id_ != running_boot_; }
  void Wait(Lock& lk, double deadline = std::numeric_limits<double>::infinity());
  void ExecuteRealtime(Lock& lk);
  void RtSystem(Lock& lk);
  void RtAlarm(Lock& lk);  // report rt_alarm_; critical ones block until a reset
  bool Suspended() const { return hold_complete_ || state_ == GrblState::kSleep; }
  void AutoCycleStart();
  void Synchronize(Lock& lk);
  void ReportStatus();
  std::string AxisValues(const Eigen::Vector3d& v) const;
  int SystemExecuteLine(Lock& lk, const std::string& line);
  int GcExecuteLine(Lock& lk, const std::string& line);
  void ExecuteStartupLines(Lock& lk);
  void McLine(Lock& lk, const Eigen::Vector3d& target, const MoveRate& rate);
  void McArc(Lock& lk, const GcodeBlock& blk, const MoveRate& rate);
  void McDwell(Lock& lk, double seconds);
  void MachineDelay(Lock& lk, double seconds);  // uninterruptible except by abort (homing)
  int McProbeCycle(Lock& lk, const GcodeBlock& blk, const MoveRate& rate);
  bool TravelOk(const Eigen::Vector3d& target) const;
  // MPos of `axis` after homing: -$27 toward + ($23 bit clear), -$13x + $27 toward -; 0 with
  // HOMING_FORCE_SET_ORIGIN.
  double HomedPosition(int axis) const;
  void LimitsSoftCheck(Lock& lk, const Eigen::Vector3d& target);
  void FlagWcoChange(Lock& lk) {
    Synchronize(lk);
    wco_counter_ = 0;
  }
  void HomingCycle(Lock& lk);
  bool HomeAxes(Lock& lk, const std::vector<int>& axes);
  bool HomingMove(Lock& lk, const Eigen::Vector3d& target, double rate, bool abrupt);
  double SpindleRpm() const;

  // ----- I/O thread -----
  void IoMain();
  void ReadFromHost(int fd);
  void PaceRx(Clock::time_point now);  // bytes from the host reach the UART at the baud rate
  void PaceTx(Clock::time_point now);  // and leave it at the baud rate

  const VirtualCncOptions options_;
  mutable std::mutex mu_;
  std::condition_variable cv_;     // firmware wake-ups
  std::condition_variable io_cv_;  // I/O thread acknowledgements
  virtual_cnc_internal::MachineClock clock_;
  MotionExecutor exec_;

  // EEPROM.
  GrblSettings settings_;
  CoordinateData coords_;
  std::array<std::string, 2> startup_lines_;
  std::string build_info_;

  // System state.
  GrblState state_ = GrblState::kIdle;
  GcodeState gc_;
  Eigen::Vector3d offset_ = Eigen::Vector3d::Zero();  // true - belief
  Eigen::Vector3d probe_position_ = Eigen::Vector3d::Zero();
  bool probe_succeeded_ = false;
  bool abort_ = false;
  bool hold_complete_ = false;  // SUSPEND_HOLD_COMPLETE
  bool jog_cancel_ = false;     // SUSPEND_JOG_CANCEL
  bool soft_limit_ = false;
  bool cycle_stop_ = false;
  int wco_counter_ = 0;
  int ovr_counter_ = 0;
  // Real-time flags set by the ISR side.
  bool rt_reset_ = false;
  bool rt_status_ = false;
  bool rt_cycle_start_ = false;
  bool rt_feed_hold_ = false;
  bool rt_motion_cancel_ = false;
  bool rt_sleep_ = false;
  int rt_alarm_ = 0;
  std::deque<char> rx_;

  // Power and link.
  bool powered_ = false;
  std::uint64_t boot_id_ = 0;       // incremented at every power-up
  std::uint64_t running_boot_ = 0;  // the power-up the firmware loop is running for
  std::optional<Clock::time_point> boot_at_;
  bool stop_ = false;
  Pty pty_;
  bool plugged_ = false;
  bool close_request_ = false;
  bool host_open_ = false;
  std::optional<Clock::time_point> replug_at_;
  int wake_[2] = {-1, -1};
  std::string rx_line_;  // bytes read from the pty, not yet through the UART
  Clock::time_point rx_clock_{};
  std::string tx_;  // replies not yet through the UART
  Clock::time_point tx_clock_{};
  std::string wire_;             // bytes past the UART and the fault filter, being written
  Clock::duration byte_time_{};  // 10 bits per byte at the baud rate (0: no pacing)

  // Faults.
  std::mt19937_64 rng_;
  LinkFaults to_cnc_, to_host_;
  Clock::time_point stall_until_{};
  std::optional<ArmedAlarm> armed_alarm_;
  bool reset_at_dwell_ = false;           // ResetDuringNextDwell()
  std::deque<std::string> lose_replies_;  // LoseNextReply(): what each lost reply becomes
  bool lose_position_ = false;

  // Dialect state.
  bool homed_ = false;        // $H completed since power-up without losing position since
  int alarm_code_ = 0;        // sys.alarm: the last ALARM:N printed while in Alarm
  int last_error_ = kGrblOk;  // grblHAL gc_state.last_error (the error latch)
  virtual_cnc_internal::MarlinState marlin_;

  VirtualCncStats stats_;
  std::thread firmware_, io_;
};

}  // namespace gs360
