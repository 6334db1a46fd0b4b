#include "sim/virtual_cnc.h"

#include <fcntl.h>
#include <poll.h>
#include <pthread.h>
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <iostream>
#include <mutex>
#include <random>
#include <sstream>
#include <stdexcept>
#include <thread>
#include <utility>

#include "sim/grbl_gcode.h"
#include "sim/pty.h"
#include "sim/virtual_cnc_impl.h"

namespace gs360 {
namespace {

using Clock = std::chrono::steady_clock;

std::string StatusLine(int code) {
  return code == kGrblOk ? std::string("ok\r\n") : "error:" + std::to_string(code) + "\r\n";
}

}  // namespace

const char* GrblStateName(GrblState state) {
  switch (state) {
    case GrblState::kIdle:
      return "Idle";
    case GrblState::kRun:
      return "Run";
    case GrblState::kHold:
      return "Hold";
    case GrblState::kJog:
      return "Jog";
    case GrblState::kAlarm:
      return "Alarm";
    case GrblState::kDoor:
      return "Door";
    case GrblState::kCheck:
      return "Check";
    case GrblState::kHome:
      return "Home";
    case GrblState::kSleep:
      return "Sleep";
  }
  return "?";
}

void VirtualCncOptions::Check() const {
  auto fail = [](const std::string& field, const std::string& value, const char* what) {
    throw std::invalid_argument("VirtualCncOptions." + field + " " + what + ", got " + value);
  };
  if (!(time_scale >= 0.0) || !std::isfinite(time_scale)) {
    fail("time_scale", std::to_string(time_scale), "must be >= 0 (0 = instant)");
  }
  if (rx_buffer_bytes < 16 || rx_buffer_bytes > 65535) {
    fail("rx_buffer_bytes", std::to_string(rx_buffer_bytes), "must be in 16..65535");
  }
  if (planner_blocks < 1 || planner_blocks > 255) {
    fail("planner_blocks", std::to_string(planner_blocks), "must be in 1..255");
  }
  if (baud_rate < 0) fail("baud_rate", std::to_string(baud_rate), "must be >= 0 (0 = no pacing)");
  if (!initial_true_position.allFinite())
    fail("initial_true_position", "non-finite", "must be finite");
  if (boot_delay.count() < 0)
    fail("boot_delay", std::to_string(boot_delay.count()), "must be >= 0");
  if (!(lost_position_max_mm >= 0.0)) {
    fail("lost_position_max_mm", std::to_string(lost_position_max_mm), "must be >= 0");
  }
  if (history_pieces < 16) fail("history_pieces", std::to_string(history_pieces), "must be >= 16");
  settings.Check();
  marlin.Check();
}

void VirtualMarlinOptions::Check() const {
  auto fail = [](const std::string& field, double value, const char* what) {
    throw std::invalid_argument("VirtualCncOptions.marlin." + field + " " + what + ", got " +
                                std::to_string(value));
  };
  if (!(keepalive_s >= 0.0 && keepalive_s <= 60.0))
    fail("keepalive_s", keepalive_s, "must be in 0..60");
  if (!(temperature_report_s >= 0.0 && temperature_report_s <= 60.0)) {
    fail("temperature_report_s", temperature_report_s, "must be in 0..60");
  }
  if (machine_type.find_first_of("\r\n") != std::string::npos) {
    throw std::invalid_argument("VirtualCncOptions.marlin.machine_type must be one line");
  }
}

VirtualCnc::Impl::Impl(const VirtualCncOptions& options)
    : options_(options),
      clock_(options.time_scale, Clock::now(), options.history_pieces),
      exec_(MotionExecutor::Options{options.planner_blocks, options.history_pieces},
            options.initial_true_position, 0.0),
      settings_(options.settings),
      rng_(options.seed) {
  if (options_.baud_rate > 0) {
    byte_time_ = std::chrono::duration_cast<Clock::duration>(
        std::chrono::duration<double>(10.0 / options_.baud_rate));
  }
  exec_.SetLimits(settings_.Limits());
  if (::pipe2(wake_, O_NONBLOCK | O_CLOEXEC) != 0) {
    throw std::runtime_error(std::string("VirtualCnc: pipe2 failed: ") + std::strerror(errno));
  }
  try {
    pty_ = Pty::Open("", options_.reset_on_open);
    if (!options_.symlink_path.empty()) ReplaceSymlink(pty_.slave_path(), options_.symlink_path);
  } catch (...) {
    ::close(wake_[0]);
    ::close(wake_[1]);
    throw;
  }
  plugged_ = true;
  PowerOn();
  firmware_ = std::thread([this] { FirmwareMain(); });
  io_ = std::thread([this] { IoMain(); });
}

void VirtualCnc::Impl::Stop() {
  {
    std::lock_guard<std::mutex> lk(mu_);
    if (stop_ && !firmware_.joinable() && !io_.joinable()) return;
    stop_ = true;
    cv_.notify_all();
    io_cv_.notify_all();
    WakeIo();
  }
  if (firmware_.joinable()) firmware_.join();
  if (io_.joinable()) io_.join();
  std::lock_guard<std::mutex> lk(mu_);
  pty_.Close();
  plugged_ = false;
  if (!options_.symlink_path.empty()) ::unlink(options_.symlink_path.c_str());
  if (wake_[0] >= 0) ::close(wake_[0]);
  if (wake_[1] >= 0) ::close(wake_[1]);
  wake_[0] = wake_[1] = -1;
}

// ---------------------------------------------------------------------------------------------
// Power and link.

void VirtualCnc::Impl::PowerOn() {
  powered_ = true;
  ++boot_id_;
  ++stats_.boots;
  const double m = MachineNow();
  exec_.Stop(m);
  offset_ = exec_.PositionAt(m);  // the controller wakes up believing it is at 0,0,0
  // HOMING_INIT_LOCK: Alarm at power-up with homing enabled.
  state_ =
      settings_.homing_enable && options_.homing_init_lock ? GrblState::kAlarm : GrblState::kIdle;
  homed_ = false;
  alarm_code_ = 0;
  rt_alarm_ = 0;  // RAM: anything pending from before the power loss is gone
  boot_at_ = Clock::now() + options_.boot_delay;
  cv_.notify_all();
}

void VirtualCnc::Impl::PowerOff() {
  powered_ = false;
  exec_.Stop(MachineNow());  // the machine stops dead where it is
  rx_.clear();
  rx_line_.clear();
  cv_.notify_all();
}

void VirtualCnc::Impl::Unplug(const UnplugOptions& unplug) {
  Lock lk(mu_);
  if (!plugged_ || stop_) return;
  close_request_ = true;  // the I/O thread owns the fd: it closes it
  WakeIo();
  io_cv_.wait(lk, [&] { return !close_request_ || stop_; });
  if (stop_) return;
  tx_.clear();
  wire_.clear();
  if (!options_.symlink_path.empty()) ::unlink(options_.symlink_path.c_str());
  if (unplug.power_loss) PowerOff();
  if (unplug.replug_after) replug_at_ = Clock::now() + *unplug.replug_after;
  WakeIo();
}

void VirtualCnc::Impl::ReplugLocked() {
  if (plugged_ || stop_) return;
  const std::string old_path = pty_.slave_path();
  Pty fresh = Pty::Open(old_path, options_.reset_on_open);
  pty_ = std::move(fresh);
  plugged_ = true;
  host_open_ = false;
  replug_at_.reset();
  if (!options_.symlink_path.empty()) ReplaceSymlink(pty_.slave_path(), options_.symlink_path);
  if (!powered_) PowerOn();
  WakeIo();
  cv_.notify_all();
}

// ---------------------------------------------------------------------------------------------
// Reset (mc_reset): what a soft reset does to a machine in motion.

void VirtualCnc::Impl::McReset() {
  if (rt_reset_) return;
  rt_reset_ = true;
  ++stats_.resets;
  const bool in_motion = state_ == GrblState::kRun || state_ == GrblState::kHome ||
                         state_ == GrblState::kJog ||
                         (state_ == GrblState::kHold && !hold_complete_);
  if (in_motion) {
    if (state_ == GrblState::kHome) {
      if (!rt_alarm_) rt_alarm_ = kGrblAlarmHomingFailReset;
    } else {
      rt_alarm_ = kGrblAlarmAbortCycle;
    }
    exec_.Stop(MachineNow());  // steppers killed: position likely lost
    homed_ = false;            // grblHAL: sys.position_lost clears the homed axes
    if (lose_position_) LosePosition();
  }
  cv_.notify_all();
}

void VirtualCnc::Impl::LosePosition() {
  std::uniform_real_distribution<double> u(-options_.lost_position_max_mm,
                                           options_.lost_position_max_mm);
  for (int i = 0; i < 3; ++i) offset_[i] += u(rng_);
}

// ---------------------------------------------------------------------------------------------
// Firmware thread: main() and protocol_main_loop().

void VirtualCnc::Impl::FirmwareMain() {
  Lock lk(mu_);
  while (!stop_) {
    if (!powered_) {
      cv_.wait(lk, [&] { return stop_ || powered_; });
      continue;
    }
    if (boot_at_) {
      const Clock::time_point boot = *boot_at_;
      boot_at_.reset();
      cv_.wait_until(lk, boot, [&] { return stop_ || !powered_ || boot_at_.has_value(); });
      continue;
    }
    InitAfterReset();
    if (Marlin()) {
      MarlinMainLoop(lk);
    } else {
      ProtocolMainLoop(lk);
    }
  }
}

void VirtualCnc::Impl::InitAfterReset() {
  running_boot_ = boot_id_;
  abort_ = false;
  rt_reset_ = rt_status_ = rt_cycle_start_ = rt_feed_hold_ = rt_motion_cancel_ = rt_sleep_ = false;
  rt_alarm_ = 0;
  hold_complete_ = jog_cancel_ = soft_limit_ = cycle_stop_ = false;
  rx_.clear();
  exec_.Stop(MachineNow());  // plan_reset(), st_reset()
  gc_ = GcodeState();
  gc_.coord_system = coords_.wcs[0];
  gc_.position = Belief();  // gc_sync_position()
  wco_counter_ = ovr_counter_ = 0;
  last_error_ = kGrblOk;
  if (Marlin()) {
    MarlinInit();
    Emit(MarlinBoot());
    return;
  }
  Emit(Welcome());
}

void VirtualCnc::Impl::ProtocolMainLoop(Lock& lk) {
  if (!EnterMainLoop(lk)) return;
  LineBuffer in;
  while (true) {
    while (!rx_.empty()) {
      const char c = rx_.front();
      rx_.pop_front();
      if (c != '\n' && c != '\r') {
        in.Add(c);
        continue;
      }
      if (GrblHal() && in.PairedTerminator(c)) continue;
      ExecuteRealtime(lk);
      if (abort_) return;
      const int status = ExecuteLine(lk, in);
      ++stats_.lines;
      if (status != kGrblOk) ++stats_.errors;
      Emit(StatusLine(status));
      in.Clear();
      if (abort_ || Aborting()) {
        ExecuteRealtime(lk);
        if (abort_) return;
      }
    }
    AutoCycleStart();
    ExecuteRealtime(lk);
    if (abort_) return;
    if (rx_.empty()) Wait(lk);
  }
}

void VirtualCnc::Impl::Wait(Lock& lk, double deadline) {
  if (stop_) return;
  if (Marlin()) deadline = std::min(deadline, MarlinNextIdleEvent());
  const double next = std::min(exec_.NextEventTime(), deadline);
  if (std::isfinite(next) && !clock_.instant()) {
    cv_.wait_until(lk, clock_.WallAt(next) + std::chrono::microseconds(20));
  } else if (std::isfinite(next)) {
    return;  // instant mode: the caller advances the clock
  } else {
    cv_.wait(lk);
  }
}

void VirtualCnc::Impl::UpdateMotion() {
  double m = MachineNow();
  if (clock_.instant() && exec_.Running()) {
    const double end = exec_.FinishTime();
    if (end > m) {
      clock_.JumpTo(Clock::now(), end);
      m = clock_.At(Clock::now());
    }
  }
  exec_.AdvanceTo(m);
  if (std::optional<FiredAlarm> fired = exec_.TakeFiredAlarm()) {
    // An injected fault (e.g. a limit switch) stopped the steppers dead: mc_reset() + alarm.
    rt_alarm_ = fired->code;
    if (!rt_reset_) ++stats_.resets;
    rt_reset_ = true;
    homed_ = false;
    if (lose_position_) LosePosition();
  }
  if ((state_ == GrblState::kRun || state_ == GrblState::kJog ||
       (state_ == GrblState::kHold && !hold_complete_)) &&
      !exec_.Busy()) {
    cycle_stop_ = true;
  }
}

void VirtualCnc::Impl::ExecuteRealtime(Lock& lk) {
  RtSystem(lk);
  if (abort_) return;
  while (Suspended() && !abort_) {
    Wait(lk);
    RtSystem(lk);
  }
}

void VirtualCnc::Impl::RtAlarm(Lock& lk) {
  if (Marlin()) return MarlinKill(lk);
  state_ = GrblState::kAlarm;
  ++stats_.alarms;
  Emit("ALARM:" + std::to_string(rt_alarm_) + "\r\n");
  alarm_code_ = rt_alarm_;
  if (rt_alarm_ == kGrblAlarmHardLimit || rt_alarm_ == kGrblAlarmSoftLimit) {
    Emit("[MSG:Reset to continue]\r\n");
    rt_reset_ = false;
    // Block everything (status reports included, as GRBL 1.1 does) until a reset.
    cv_.wait(lk, [&] { return Aborting(); });
  }
  rt_alarm_ = 0;
}

void VirtualCnc::Impl::RtSystem(Lock& lk) {
  if (Rebooted()) {  // power lost or restarted: unwind without running the old boot's events
    abort_ = true;
    return;
  }
  UpdateMotion();
  if (Marlin()) MarlinIdle();
  if (rt_alarm_) RtAlarm(lk);
  if (Aborting()) {
    abort_ = true;
    return;
  }
  const double m = MachineNow();
  if (rt_status_) {
    rt_status_ = false;
    ReportStatus();
  }
  const bool feed_hold = rt_feed_hold_, motion_cancel = rt_motion_cancel_, sleep = rt_sleep_;
  if (feed_hold || motion_cancel || sleep) {
    if (!(state_ == GrblState::kAlarm || state_ == GrblState::kCheck)) {
      if (state_ == GrblState::kRun || state_ == GrblState::kJog) {
        if (!jog_cancel_ && !exec_.Holding()) {
          exec_.FeedHold(m);
          if (state_ == GrblState::kJog && !sleep) jog_cancel_ = true;
        }
      }
      if (state_ == GrblState::kIdle) hold_complete_ = true;
      if (feed_hold && !(state_ == GrblState::kJog || state_ == GrblState::kSleep)) {
        state_ = GrblState::kHold;
      }
    }
    if (sleep) {
      state_ = GrblState::kSleep;
      Emit("[MSG:Sleeping]\r\n");
    }
    rt_feed_hold_ = rt_motion_cancel_ = rt_sleep_ = false;
  }
  if (rt_cycle_start_) {
    rt_cycle_start_ = false;
    if (!(feed_hold || motion_cancel)) {
      if (state_ == GrblState::kIdle || (state_ == GrblState::kHold && hold_complete_)) {
        hold_complete_ = false;
        if (exec_.BlockCount() > 0) {
          state_ = GrblState::kRun;
          if (exec_.Holding()) {
            exec_.Resume(m);
          } else {
            exec_.StartCycle(m);
          }
        } else {
          state_ = GrblState::kIdle;
        }
      }
    }
  }
  UpdateMotion();
  if (cycle_stop_) {
    cycle_stop_ = false;
    if (state_ == GrblState::kHold && !soft_limit_ && !jog_cancel_) {
      hold_complete_ = true;  // plan_cycle_reinitialize(): resume re-plans from rest
    } else if (state_ == GrblState::kRun || state_ == GrblState::kJog ||
               state_ == GrblState::kHold) {
      if (jog_cancel_) {
        exec_.Stop(MachineNow());  // flush the rest of the jog
        gc_.position = Belief();
      }
      hold_complete_ = false;
      jog_cancel_ = false;
      state_ = GrblState::kIdle;
    }
  }
}

void VirtualCnc::Impl::AutoCycleStart() {
  if (state_ == GrblState::kIdle && exec_.BlockCount() > 0 && !exec_.Running()) {
    state_ = GrblState::kRun;
    exec_.StartCycle(MachineNow());
  }
}

void VirtualCnc::Impl::Synchronize(Lock& lk) {
  AutoCycleStart();
  while (true) {
    ExecuteRealtime(lk);
    if (abort_) return;
    if (!(exec_.BlockCount() > 0 || state_ == GrblState::kRun)) return;
    AutoCycleStart();
    Wait(lk);
  }
}

// ---------------------------------------------------------------------------------------------
// '$' system commands (system_execute_line).

// `$RST=$`, `$RST=#`, `$RST=*`: settings, coordinates or everything back to the defaults.
int VirtualCnc::Impl::RestoreDefaults(char what) {
  switch (what) {
    case '$':
      settings_ = options_.settings;
      break;
    case '#':
      coords_ = CoordinateData();
      break;
    case '*':
      settings_ = options_.settings;
      coords_ = CoordinateData();
      startup_lines_ = {};
      build_info_.clear();
      break;
    default:
      return kGrblInvalidStatement;
  }
  exec_.SetLimits(settings_.Limits());
  Emit("[MSG:Restoring defaults]\r\n");
  McReset();
  return kGrblOk;
}

int VirtualCnc::Impl::SystemExecuteLine(Lock& lk, const std::string& line) {
  if (line.size() == 1) {
    Emit("[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]\r\n");
    return kGrblOk;
  }
  const char c1 = line[1];
  switch (c1) {
    case 'J':
      if (state_ != GrblState::kIdle && state_ != GrblState::kJog) return kGrblIdleError;
      if (line.size() < 3 || line[2] != '=') return kGrblInvalidStatement;
      return GcExecuteLine(lk, line);
    case '$':
    case 'G':
    case 'C':
    case 'X':
      if (line.size() != 2) return kGrblInvalidStatement;
      switch (c1) {
        case '$':
          if (state_ == GrblState::kRun || state_ == GrblState::kHold) return kGrblIdleError;
          Emit(settings_.Report());
          break;
        case 'G':
          Emit(FormatParserState(gc_, settings_.report_inches) + "\r\n");
          break;
        case 'C':
          if (state_ == GrblState::kCheck) {
            McReset();
            Emit("[MSG:Disabled]\r\n");
          } else {
            if (state_ != GrblState::kIdle) return kGrblIdleError;
            state_ = GrblState::kCheck;
            Emit("[MSG:Enabled]\r\n");
          }
          break;
        default:  // 'X'
          if (state_ == GrblState::kAlarm) {
            // grblHAL system.c disable_lock(): `else if(limits_homing_required()) retval =
            // Status_HomingRequired;` and the Alarm stays.
            if (HomingRequired()) return kGrblHalHomingRequired;
            Emit("[MSG:Caution: Unlocked]\r\n");
            state_ = GrblState::kIdle;
            alarm_code_ = 0;
          }
          break;
      }
      return kGrblOk;
    default:
      break;
  }
  if (!(state_ == GrblState::kIdle || state_ == GrblState::kAlarm)) return kGrblIdleError;
  switch (c1) {
    case '#':
      if (line.size() != 2) return kGrblInvalidStatement;
      ReportCoordinates();
      return kGrblOk;
    case 'H':
      if (!settings_.homing_enable) return kGrblSettingDisabled;
      if (line.size() != 2) return kGrblInvalidStatement;  // HOMING_SINGLE_AXIS_COMMANDS is off
      state_ = GrblState::kHome;
      HomingCycle(lk);
      if (!abort_ && !Aborting()) {
        state_ = GrblState::kIdle;
        alarm_code_ = 0;
        ExecuteStartupLines(lk);
      }
      return kGrblOk;
    case 'S':
      if (line != "$SLP") return kGrblInvalidStatement;
      rt_sleep_ = true;
      return kGrblOk;
    case 'I':
      if (line.size() == 2) {
        ReportBuildInfo();
        return kGrblOk;
      }
      if (line[2] != '=') return kGrblInvalidStatement;
      Synchronize(lk);  // FORCE_BUFFER_SYNC_DURING_EEPROM_WRITE
      build_info_ = line.substr(3);
      return kGrblOk;
    case 'R':
      if (line.size() != 6 || line.compare(2, 3, "ST=") != 0) return kGrblInvalidStatement;
      return RestoreDefaults(line[5]);
    case 'N':
      if (line.size() == 2) {
        for (std::size_t n = 0; n < startup_lines_.size(); ++n) {
          Emit("$N" + std::to_string(n) + "=" + startup_lines_[n] + "\r\n");
        }
        return kGrblOk;
      }
      if (state_ != GrblState::kIdle) return kGrblIdleError;
      [[fallthrough]];
    default: {
      const bool startup = c1 == 'N';
      std::size_t pos = startup ? 2 : 1;
      double parameter = 0.0;
      if (!ReadGrblFloat(line, pos, parameter)) return kGrblBadNumberFormat;
      if (pos >= line.size() || line[pos++] != '=') return kGrblInvalidStatement;
      if (startup) {
        const std::string block = line.substr(pos);
        const int status = GcExecuteLine(lk, block);
        if (status != kGrblOk) return status;
        const int n = static_cast<int>(std::trunc(parameter));
        if (n < 0 || n >= static_cast<int>(startup_lines_.size())) return kGrblInvalidStatement;
        Synchronize(lk);
        startup_lines_[static_cast<std::size_t>(n)] = block;
        return kGrblOk;
      }
      double value = 0.0;
      if (!ReadGrblFloat(line, pos, value)) return kGrblBadNumberFormat;
      if (pos != line.size() || parameter > 255) return kGrblInvalidStatement;
      const int status = settings_.Store(static_cast<int>(parameter), value);
      if (status == kGrblOk) {
        exec_.SetLimits(settings_.Limits());
        if (static_cast<int>(parameter) == 13) wco_counter_ = 0;
      }
      return status;
    }
  }
}

void VirtualCnc::Impl::ExecuteStartupLines(Lock& lk) {
  for (std::size_t n = 0; n < startup_lines_.size(); ++n) {
    if (startup_lines_[n].empty()) continue;
    const std::string block = startup_lines_[n];
    const int status = GcExecuteLine(lk, block);
    Emit(">" + block + ":" + StatusLine(status));
    if (abort_ || Aborting()) return;
  }
}

// ---------------------------------------------------------------------------------------------
// G-code execution (gc_execute_line step 4).

int VirtualCnc::Impl::GcExecuteLine(Lock& lk, const std::string& line) {
  GcodeBlock blk;
  const int status = ParseGcodeLine(line, gc_, coords_, &blk);
  if (status != kGrblOk) return status;

  if (blk.jog) {  // jog_execute()
    if (settings_.soft_limits && !TravelOk(blk.xyz)) return kGrblTravelExceeded;
    MoveRate rate;
    rate.rapid = false;
    rate.feed_mm_per_min = blk.feed_rate;
    McLine(lk, blk.xyz, rate);
    if (abort_ || Aborting()) return kGrblOk;
    if (state_ == GrblState::kIdle && exec_.BlockCount() > 0) {
      state_ = GrblState::kJog;
      exec_.StartCycle(MachineNow());
    }
    gc_.position = blk.xyz;
    return kGrblOk;
  }

  gc_.line_number = blk.line_number;
  gc_.modal.inverse_time = blk.modal.inverse_time;
  gc_.feed_rate = blk.feed_rate;
  if (gc_.spindle_speed != blk.spindle_speed) {
    if (gc_.modal.spindle != 0 && state_ != GrblState::kCheck) Synchronize(lk);  // spindle_sync()
    gc_.spindle_speed = blk.spindle_speed;
  }
  gc_.tool = blk.tool;
  if (gc_.modal.spindle != blk.modal.spindle) {
    if (state_ != GrblState::kCheck) Synchronize(lk);
    gc_.modal.spindle = blk.modal.spindle;
  }
  if (gc_.modal.coolant != blk.modal.coolant) {
    if (state_ != GrblState::kCheck) Synchronize(lk);  // coolant_sync()
    gc_.modal.coolant = blk.modal.coolant;
  }
  if (blk.non_modal == kNonModalDwell) McDwell(lk, blk.dwell_s);
  if (abort_ || Aborting()) return kGrblOk;
  gc_.modal.plane = blk.modal.plane;
  gc_.modal.inches = blk.modal.inches;
  if (blk.axis_command == kAxisCommandToolLengthOffset) {
    gc_.modal.tool_length_dynamic = blk.modal.tool_length_dynamic;
    const double tlo = blk.modal.tool_length_dynamic ? blk.xyz[2] : 0.0;
    if (gc_.tool_length_offset != tlo) {
      gc_.tool_length_offset = tlo;
      FlagWcoChange(lk);
    }
  }
  if (gc_.modal.coord_select != blk.modal.coord_select) {
    gc_.modal.coord_select = blk.modal.coord_select;
    gc_.coord_system = blk.block_coord_system;
    FlagWcoChange(lk);
  }
  gc_.modal.incremental = blk.modal.incremental;
  MoveRate rapid;
  rapid.rapid = true;
  switch (blk.non_modal) {
    case kNonModalSetCoordinateData:
      Synchronize(lk);  // settings_write_coord_data(): FORCE_BUFFER_SYNC_DURING_EEPROM_WRITE
      coords_.wcs[static_cast<std::size_t>(blk.coord_data_index)] = blk.ijk;
      if (gc_.modal.coord_select == blk.coord_data_index) {
        gc_.coord_system = blk.ijk;
        FlagWcoChange(lk);
      }
      break;
    case kNonModalGoHome0:
    case kNonModalGoHome1:
      if (blk.axis_command) McLine(lk, blk.xyz, rapid);
      McLine(lk, blk.ijk, rapid);
      gc_.position = blk.ijk;
      break;
    case kNonModalSetHome0:
      Synchronize(lk);
      coords_.g28 = gc_.position;
      break;
    case kNonModalSetHome1:
      Synchronize(lk);
      coords_.g30 = gc_.position;
      break;
    case kNonModalSetCoordinateOffset:
      gc_.coord_offset = blk.xyz;
      FlagWcoChange(lk);
      break;
    case kNonModalResetCoordinateOffset:
      gc_.coord_offset.setZero();
      FlagWcoChange(lk);
      break;
    default:
      break;
  }
  if (abort_ || Aborting()) return kGrblOk;

  gc_.modal.motion = blk.modal.motion;
  if (gc_.modal.motion != kMotionNone && blk.axis_command == kAxisCommandMotionMode) {
    MoveRate rate;
    rate.rapid = gc_.modal.motion == kMotionSeek;
    rate.feed_mm_per_min = gc_.feed_rate;
    rate.inverse_time = gc_.modal.inverse_time;
    int update = 0;  // GC_UPDATE_POS_TARGET
    if (gc_.modal.motion == kMotionLinear || gc_.modal.motion == kMotionSeek) {
      McLine(lk, blk.xyz, rate);
    } else if (gc_.modal.motion == kMotionCwArc || gc_.modal.motion == kMotionCcwArc) {
      McArc(lk, blk, rate);
    } else {
      update = McProbeCycle(lk, blk, rate);
    }
    if (update == 0) {
      gc_.position = blk.xyz;
    } else if (update == 1) {
      gc_.position = Belief();
    }
  }
  if (abort_ || Aborting()) return kGrblOk;

  gc_.modal.program_flow = blk.modal.program_flow;
  if (gc_.modal.program_flow) {
    Synchronize(lk);
    if (abort_ || Aborting()) return kGrblOk;
    if (gc_.modal.program_flow == 3) {  // M0
      if (state_ != GrblState::kCheck) {
        rt_feed_hold_ = true;
        ExecuteRealtime(lk);
      }
    } else {  // M2, M30
      gc_.modal.motion = kMotionLinear;
      gc_.modal.plane = 0;
      gc_.modal.incremental = false;
      gc_.modal.inverse_time = false;
      gc_.modal.coord_select = 0;
      gc_.modal.spindle = 0;
      gc_.modal.coolant = 0;
      if (state_ != GrblState::kCheck) {
        gc_.coord_system = coords_.wcs[0];
        FlagWcoChange(lk);
      }
      Emit("[MSG:Pgm End]\r\n");
    }
    gc_.modal.program_flow = 0;
  }
  return kGrblOk;
}

// ---------------------------------------------------------------------------------------------
// Public wrapper.

VirtualCnc::VirtualCnc(const VirtualCncOptions& options) {
  options.Check();
  impl_ = std::make_unique<Impl>(options);
}
VirtualCnc::~VirtualCnc() = default;
void VirtualCnc::Stop() {
  impl_->Stop();
}
std::string VirtualCnc::PtyPath() const {
  return impl_->PtyPath();
}
const VirtualCncOptions& VirtualCnc::options() const {
  return impl_->options();
}
Eigen::Vector3d VirtualCnc::TruePosition(Clock::time_point t) const {
  return impl_->TruePosition(t);
}
double VirtualCnc::TrueSpeed(Clock::time_point t) const {
  return impl_->TrueSpeed(t);
}
std::vector<MotionPiece> VirtualCnc::TrueTrajectory(Clock::time_point from,
                                                    Clock::time_point to) const {
  return impl_->TrueTrajectory(from, to);
}
double VirtualCnc::MachineTime(Clock::time_point t) const {
  return impl_->MachineTime(t);
}
Eigen::Vector3d VirtualCnc::ReportedPosition() const {
  return impl_->ReportedPosition();
}
GrblState VirtualCnc::State() const {
  return impl_->State();
}
GrblSettings VirtualCnc::Settings() const {
  return impl_->Settings();
}
int VirtualCnc::PlannerBlocksQueued() const {
  return impl_->PlannerBlocksQueued();
}
int VirtualCnc::RxBufferUsed() const {
  return impl_->RxBufferUsed();
}
VirtualCncStats VirtualCnc::Stats() const {
  return impl_->Stats();
}
void VirtualCnc::DropNextBytes(std::size_t n, FaultDirection direction) {
  impl_->DropNextBytes(n, direction);
}
void VirtualCnc::SetDropProbability(double p, FaultDirection direction) {
  impl_->SetDropProbability(p, direction);
}
void VirtualCnc::GarbleNextBytes(std::size_t n, FaultDirection direction) {
  impl_->GarbleNextBytes(n, direction);
}
void VirtualCnc::StallReplies(std::chrono::milliseconds duration) {
  impl_->StallReplies(duration);
}
void VirtualCnc::Unplug(const UnplugOptions& options) {
  impl_->Unplug(options);
}
void VirtualCnc::Replug() {
  impl_->Replug();
}
bool VirtualCnc::Plugged() const {
  return impl_->Plugged();
}
bool VirtualCnc::HostAttached() const {
  return impl_->HostAttached();
}
void VirtualCnc::RaiseAlarmDuringNextMove(int alarm_code, double fraction) {
  impl_->RaiseAlarmDuringNextMove(alarm_code, fraction);
}
void VirtualCnc::LosePositionOnReset(bool lose) {
  impl_->LosePositionOnReset(lose);
}

int RunVirtualCncForeground(const VirtualCncOptions& options) {
  // Block the signals before the threads start so that they inherit the mask and only sigwait()
  // below receives them.
  sigset_t signals, previous;
  sigemptyset(&signals);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &signals, &previous);
  try {
    VirtualCnc cnc(options);
    std::cout << cnc.PtyPath() << "\n";
    if (!options.symlink_path.empty()) std::cout << options.symlink_path << "\n";
    std::cout.flush();
    std::cerr << "virtual "
              << (options.firmware == CncFirmware::kGrblHal ? "grblHAL 1.1f" : "GRBL 1.1h")
              << " on " << cnc.PtyPath() << " (time scale " << options.time_scale << ", RX "
              << options.rx_buffer_bytes << " bytes, " << options.planner_blocks
              << " planner blocks); Ctrl-C to stop\n";
    int sig = 0;
    sigwait(&signals, &sig);
    cnc.Stop();
  } catch (...) {
    pthread_sigmask(SIG_SETMASK, &previous, nullptr);
    throw;
  }
  pthread_sigmask(SIG_SETMASK, &previous, nullptr);
  return 0;
}

}  // namespace gs360
