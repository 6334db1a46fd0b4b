// The virtual CNC's line protocol where GRBL 1.1h and grblHAL differ: welcome, `$I`, the homing
// lock (ALARM:11 / error:46), line terminators and grblHAL's error latch. Sources are cited per
// function (github.com/grblHAL/core; gnea/grbl 1.1h for the GRBL side).

#include <string>

#include "sim/virtual_cnc_impl.h"

namespace gs360 {
namespace {

constexpr char kGrblWelcome[] = "\r\nGrbl 1.1h ['$' for help]\r\n";
constexpr char kGrblVersionBuild[] = "1.1h.20190825";
// grblHAL report.c report_init_message() at COMPATIBILITY_LEVEL 0:
//   hal.stream.write_all(ASCII_EOL "GrblHAL " GRBL_VERSION " ['$' or '$HELP' for help]" ASCII_EOL);
// grbl.h: #define GRBL_VERSION "1.1f".
constexpr char kGrblHalWelcome[] = "\r\nGrblHAL 1.1f ['$' or '$HELP' for help]\r\n";
// report.c report_build_info(): "[VER:" GRBL_VERSION "." GRBL_BUILD ":" ; GRBL_BUILD is the
// release date (grbl.h), fixed here.
constexpr char kGrblHalVersionBuild[] = "1.1f.20240101";
constexpr std::size_t kLineBufferSize = 80;  // GRBL 1.1h LINE_BUFFER_SIZE: 79 characters

}  // namespace

namespace virtual_cnc_internal {

// GRBL 1.1h protocol_main_loop(): whitespace and control characters dropped, '(' ... ')' and
// ';' comments dropped, '/' ignored, upper case, overflow past LINE_BUFFER_SIZE - 1.
void LineBuffer::Add(char c) {
  // grblHAL keeps every character but control characters and leading spaces:
  // `else if (c <= (char_counter > 0 ? ' ' - 1 : ' ')) continue;` (protocol.c).
  if (static_cast<unsigned char>(c) > ' ' || (c == ' ' && kept > 0)) ++kept;
  if (overflow || paren || semicolon) {
    if (c == ')' && paren) paren = false;
  } else if (static_cast<unsigned char>(c) <= ' ' || c == '/') {
    // whitespace, control characters; block delete is not supported and ignored
  } else if (c == '(') {
    paren = true;
  } else if (c == ';') {
    semicolon = true;
  } else if (line.size() >= kLineBufferSize - 1) {
    overflow = true;
  } else if (c >= 'a' && c <= 'z') {
    line.push_back(static_cast<char>(c - 'a' + 'A'));
  } else {
    line.push_back(c);
  }
}

// grblHAL protocol.c protocol_main_loop():
//   // Check for possible secondary end of line character, do not process as empty line
//   // if part of crlf (or lfcr pair) as this produces a possibly unwanted double response
//   if(char_counter == 0 && eol && eol != c) { eol = '\0'; continue; } else eol = (char)c;
bool LineBuffer::PairedTerminator(char c) {
  if (kept == 0 && eol != 0 && eol != c) {
    eol = 0;
    return true;
  }
  eol = c;
  return false;
}

void LineBuffer::Clear() {
  line.clear();
  overflow = paren = semicolon = false;
  kept = 0;
}

}  // namespace virtual_cnc_internal

const char* VirtualCnc::Impl::Welcome() const {
  return GrblHal() ? kGrblHalWelcome : kGrblWelcome;
}

// grblHAL machine_limits.c (049f0f13):
//   return settings.homing.flags.enabled && settings.homing.flags.init_lock &&
//          (sys.cold_start || !settings.homing.flags.override_locks) &&
//          sys.homing.mask && (sys.homing.mask & sys.homed.mask) != sys.homing.mask;
// override_locks ($22 bit 6) is off by default and not modelled; all three axes home.
bool VirtualCnc::Impl::HomingRequired() const {
  return GrblHal() && settings_.homing_enable && options_.homing_init_lock && !homed_;
}

// GRBL 1.1h protocol_main_loop(): in Alarm (or Sleep) `[MSG:'$H'|'$X' to unlock]`, otherwise
// Idle and the startup lines. grblHAL protocol.c checks the homing lock first:
//   } else if (limits_homing_required()) {
//       system_raise_alarm(Alarm_HomingRequried);
//       grbl.report.feedback_message(Message_HomingCycleRequired);
// and system_raise_alarm() prints ALARM:N only `if(sys.alarm != alarm)` (system.c), sys.alarm
// surviving soft resets (system.h: "not cleared upon soft reset"). messages.c:
// Message_HomingCycleRequired = "Homing cycle required".
bool VirtualCnc::Impl::EnterMainLoop(Lock& lk) {
  if (HomingRequired()) {
    if (alarm_code_ != kGrblHalAlarmHomingRequired) {
      Emit("ALARM:" + std::to_string(kGrblHalAlarmHomingRequired) + "\r\n");
      ++stats_.alarms;
      alarm_code_ = kGrblHalAlarmHomingRequired;
    }
    Emit("[MSG:Homing cycle required]\r\n");
    state_ = GrblState::kAlarm;
  } else if (state_ == GrblState::kAlarm || state_ == GrblState::kSleep) {
    Emit("[MSG:'$H'|'$X' to unlock]\r\n");
    state_ = GrblState::kAlarm;
  } else {
    state_ = GrblState::kIdle;
    ExecuteStartupLines(lk);
    if (abort_ || Aborting()) return false;
  }
  return true;
}

// GRBL 1.1h: overflow -> error:11; empty line -> ok; '$' -> system command; G-code is locked
// in Alarm and Jog (error:9). grblHAL protocol.c (COMPATIBILITY_LEVEL 0) adds the latch:
//   else if(line[0] == '\0') gc_state.last_error = Status_OK;           // empty line
//   else if (line[0] == '$') gc_state.last_error = system_execute_line(line) ...
//   else if (state_get() & (STATE_ALARM|STATE_ESTOP|STATE_JOG)) ... = Status_SystemGClock;
//   else if(gc_state.last_error == Status_OK || ...) gc_state.last_error = gc_execute_block(line);
//   grbl.report.status_message(gc_state.last_error);
// so a G-code line after a failed one is not executed and gets the same error again. grblHAL
// keeps comments in `line`: a comment-only line is not empty there (it is G-code, ok if the
// latch is clear).
int VirtualCnc::Impl::ExecuteLine(Lock& lk, const LineBuffer& in) {
  int status = kGrblOk;
  if (in.overflow) {
    status = kGrblOverflow;
  } else if (GrblHal() ? in.kept == 0 : in.line.empty()) {
    status = kGrblOk;  // empty (GRBL: or comment-only) line
  } else if (!in.line.empty() && in.line[0] == '$') {
    status = SystemExecuteLine(lk, in.line);
  } else if (state_ == GrblState::kAlarm || state_ == GrblState::kJog) {
    status = kGrblSystemGcLock;
  } else if (GrblHal() && last_error_ != kGrblOk) {
    status = last_error_;  // the latch: not executed
  } else if (!in.line.empty()) {
    status = GcExecuteLine(lk, in.line);
  }
  last_error_ = status;
  return status;
}

// GRBL 1.1h report_build_info(): `[VER:1.1h.20190825:<info>]`, `[OPT:V[Z][L],<blocks>,<rx>]`
// (`L` when HOMING_INIT_LOCK is off). grblHAL report.c report_build_info() at level 0
// (`extended = true`): [VER:], [OPT:] with 'V' (variable spindle), 'N' (always), 'Z'
// (force_set_origin), 'L' (`if(!settings.homing.flags.init_lock)`), then
// `,<plan_get_buffer_size()>,<hal.rx_buffer_size>,<N_AXIS>,<N_TOOLS>`; [AXS:3:XYZ];
// [NEWOPT:ENUMS,RT+,HOME] (RT+ legacy real-time characters, HOME with homing enabled; a
// trailing ',' is removed); [FIRMWARE:grblHAL]. Board lines ([DRIVER:] ...) are not modelled.
void VirtualCnc::Impl::ReportBuildInfo() {
  const bool hal = GrblHal();
  std::string opt = hal ? "VN" : "V";
  if (options_.homing_force_set_origin) opt += "Z";
  if (!options_.homing_init_lock) opt += "L";
  opt += "," + std::to_string(options_.planner_blocks) + "," +
         std::to_string(options_.rx_buffer_bytes);
  if (hal) opt += ",3,0";
  Emit("[VER:" + std::string(hal ? kGrblHalVersionBuild : kGrblVersionBuild) + ":" + build_info_ +
       "]\r\n");
  Emit("[OPT:" + opt + "]\r\n");
  if (!hal) return;
  Emit("[AXS:3:XYZ]\r\n");
  Emit(std::string("[NEWOPT:ENUMS,RT+") + (settings_.homing_enable ? ",HOME" : "") + "]\r\n");
  Emit("[FIRMWARE:grblHAL]\r\n");
}

}  // namespace gs360
