// The virtual CNC's Marlin dialect (sim/virtual_cnc.h, "Marlin dialect"): a 3D printer's line
// protocol, G-code and reports over the same serial side, planner, clock and faults as GRBL.
// Marlin 2.1 sources it follows: src/gcode/queue.cpp (line numbers, checksums, resends),
// gcode.cpp (dispatch, unknown commands, the keep-alive), feature/e_parser.h (M112 M410 M108),
// module/motion.cpp (soft endstops), gcode/host/M114.cpp, M115.cpp, gcode/geometry/M211.

#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <optional>
#include <string>
#include <utility>

#include "sim/virtual_cnc_impl.h"

namespace gs360 {
namespace {

using virtual_cnc_internal::kMarlinKill;
using virtual_cnc_internal::MarlinState;

constexpr std::size_t kMaxCmdSize = 96;  // MAX_CMD_SIZE
constexpr double kBootFeedMmMin = 1500.0;
constexpr double kHomingBumpMm = 2.0;  // HOMING_BUMP_MM (Z's; X and Y use 5 on most configs)
constexpr double kHomingSearchScalar = 1.5;
constexpr char kKilled[] = "Error:Printer halted. kill() called!\n";

std::string Fixed(double v, int decimals) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.*f", decimals, v);
  return buf;
}

std::string Xyz(const Eigen::Vector3d& v, int decimals, const char* sep = " ") {
  return std::string("X") + Fixed(v.x(), decimals) + sep + "Y" + Fixed(v.y(), decimals) + sep +
         "Z" + Fixed(v.z(), decimals);
}

}  // namespace

namespace virtual_cnc_internal {

// A command's words: the letter, and its value when one follows ("G28 X" has X without one).
struct MarlinWords {
  char letter = 0;
  int code = -1;
  std::map<char, std::optional<double>> params;
  bool Has(char c) const { return params.count(c) > 0; }
  std::optional<double> Value(char c) const {
    const auto it = params.find(c);
    return it == params.end() ? std::nullopt : it->second;
  }
};

// Marlin's parser: the command letter and number, then parameters as letter + number, spaces
// optional ("G1X10Y5" parses). Nothing for a line that does not start with G, M or T + a number.
std::optional<MarlinWords> ParseWords(const std::string& command) {
  MarlinWords w;
  if (command.empty() || !(command[0] == 'G' || command[0] == 'M' || command[0] == 'T')) {
    return std::nullopt;
  }
  w.letter = command[0];
  char* end = nullptr;
  const long code = std::strtol(command.c_str() + 1, &end, 10);
  if (end == command.c_str() + 1) return std::nullopt;
  w.code = static_cast<int>(code);
  if (*end == '.') std::strtol(end + 1, &end, 10);  // G28.1-style subcodes: ignored
  for (const char* p = end; *p != '\0';) {
    if (!std::isupper(static_cast<unsigned char>(*p))) {
      ++p;
      continue;
    }
    const char letter = *p++;
    char* after = nullptr;
    const double v = std::strtod(p, &after);
    w.params[letter] = after == p ? std::nullopt : std::optional<double>(v);
    p = after;
  }
  return w;
}

}  // namespace virtual_cnc_internal

namespace {

// Strips "N<n> " and "*<checksum>" from a framed line; the command alone.
std::string CommandOf(const std::string& line) {
  std::size_t start = 0;
  if (!line.empty() && line[0] == 'N') {
    start = 1;
    while (start < line.size() && std::isdigit(static_cast<unsigned char>(line[start]))) ++start;
    while (start < line.size() && line[start] == ' ') ++start;
  }
  std::size_t end = line.rfind('*');
  if (end == std::string::npos || end < start) end = line.size();
  while (end > start && line[end - 1] == ' ') --end;
  return line.substr(start, end - start);
}

}  // namespace

std::string VirtualCnc::Impl::MarlinBoot() const {
  return "start\n"
         "echo:Marlin 2.1.2.1\n"
         "echo: Last Updated: 2023-07-13 | Author: (gs360 virtual printer)\n"
         "echo:Compiled: Jul 13 2023\n"
         "echo: Free Memory: 2891  PlannerBufferBytes: 1232\n"
         "echo:Hardcoded Default Settings Loaded\n";
}

void VirtualCnc::Impl::MarlinInit() {
  marlin_ = MarlinState();
  marlin_.soft_endstops = options_.marlin.soft_endstops;
  marlin_.feed_mm_min = kBootFeedMmMin;
  marlin_.temperature_s = options_.marlin.temperature_report_s;
  const double m = MachineNow();
  marlin_.next_temperature = m + marlin_.temperature_s;
  state_ = GrblState::kIdle;
}

// The serial ISR's emergency parser (e_parser.h): the command of a line, as its bytes arrive,
// acted on at its terminator; "N<n> " before it is skipped.
void VirtualCnc::Impl::MarlinEmergencyByte(char c) {
  if (c != '\n' && c != '\r') {
    if (marlin_.ep_line.size() < 32) marlin_.ep_line += c;
    return;
  }
  std::string line = std::exchange(marlin_.ep_line, std::string());
  const std::size_t first = line.find_first_not_of(' ');
  if (first == std::string::npos) return;
  const std::string command = CommandOf(line.substr(first));
  const std::string word = command.substr(0, command.find_first_of(" *"));
  if (word == "M112") {
    exec_.Stop(MachineNow());  // kill(): steppers off at once
    rt_alarm_ = kMarlinKill;
    cv_.notify_all();
  } else if (word == "M410") {
    exec_.Stop(MachineNow());  // quickstop_stepper(): no deceleration, the planner emptied
    if (lose_position_) LosePosition();
    gc_.position = Belief();  // set_current_from_steppers_for_axis(ALL_AXES)
    cv_.notify_all();
  }
}

void VirtualCnc::Impl::MarlinKill(Lock& lk) {
  state_ = GrblState::kAlarm;
  ++stats_.alarms;
  exec_.Stop(MachineNow());
  Emit(kKilled);
  rt_alarm_ = 0;
  rt_reset_ = false;
  // kill() -> minkill(): nothing runs, nothing is read, until the board restarts.
  cv_.wait(lk, [&] { return Aborting(); });
}

double VirtualCnc::Impl::MarlinNextIdleEvent() const {
  if (clock_.instant()) return std::numeric_limits<double>::infinity();  // time does not flow
  double next = std::numeric_limits<double>::infinity();
  if (marlin_.in_command && options_.marlin.keepalive_s > 0.0) next = marlin_.next_busy;
  if (marlin_.temperature_s > 0.0) next = std::min(next, marlin_.next_temperature);
  if (marlin_.position_s > 0.0) next = std::min(next, marlin_.next_position);
  return next;
}

// idle(): the keep-alive while a command blocks, and the auto-reports.
void VirtualCnc::Impl::MarlinIdle() {
  if (clock_.instant() || Rebooted()) return;
  const double m = MachineNow();
  if (marlin_.in_command && options_.marlin.keepalive_s > 0.0 && m >= marlin_.next_busy) {
    Emit("echo:busy: processing\n");
    ++stats_.keepalives;
    marlin_.next_busy = m + options_.marlin.keepalive_s;
  }
  if (marlin_.temperature_s > 0.0 && m >= marlin_.next_temperature) {
    Emit("T:25.00 /0.00 B:25.00 /0.00 @:0 B@:0\n");
    marlin_.next_temperature = m + marlin_.temperature_s;
  }
  if (marlin_.position_s > 0.0 && m >= marlin_.next_position) {
    Emit(MarlinPosition(true));
    marlin_.next_position = m + marlin_.position_s;
  }
}

void VirtualCnc::Impl::MarlinMainLoop(Lock& lk) {
  std::string line;
  bool comment = false;
  while (true) {
    while (!rx_.empty()) {
      const char c = rx_.front();
      rx_.pop_front();
      if (c == '\n' || c == '\r') {
        comment = false;
        if (line.empty()) continue;  // get_serial_commands(): "Skip empty lines"
        ExecuteRealtime(lk);
        if (abort_) return;
        MarlinLine(lk, std::exchange(line, std::string()));
        ++stats_.lines;
        ExecuteRealtime(lk);
        if (abort_) return;
        continue;
      }
      if (comment) continue;
      if (c == ';') {
        comment = true;
      } else if (line.size() < kMaxCmdSize - 1) {
        line += c;  // beyond MAX_CMD_SIZE - 1 characters are ignored, the line kept
      }
    }
    ExecuteRealtime(lk);
    if (abort_) return;
    if (rx_.empty()) Wait(lk);
  }
}

// gcode_line_error(): the error, the RX buffer flushed, then flush_and_request_resend().
void VirtualCnc::Impl::MarlinLineError(const char* error) {
  ++stats_.errors;
  Emit(std::string("Error:") + error + ", Last Line: " + std::to_string(marlin_.last_n) + "\n");
  rx_.clear();
  Emit("Resend: " + std::to_string(marlin_.last_n + 1) + "\n");
  Emit("ok\n");
}

// process_line(): the number and checksum of a framed line; false after a framing error.
bool VirtualCnc::Impl::MarlinFraming(const std::string& line) {
  if (line[0] != 'N') {
    if (line.find('*') == std::string::npos) return true;
    MarlinLineError("No Line Number with checksum");
    return false;
  }
  std::size_t npos = 0;
  const bool m110 = line.find("M110") != std::string::npos;
  if (m110) {
    const std::size_t n2 = line.find('N', line.find("M110") + 4);
    if (n2 != std::string::npos) npos = n2;
  }
  const long n = std::strtol(line.c_str() + npos + 1, nullptr, 10);
  if (n != marlin_.last_n + 1 && !m110) {
    MarlinLineError("Line Number is not Last Line Number+1");
    return false;
  }
  const std::size_t star = line.rfind('*');
  if (star == std::string::npos) {
    MarlinLineError("No Checksum with line number");
    return false;
  }
  int sum = 0;
  for (std::size_t i = 0; i < star; ++i) sum ^= static_cast<unsigned char>(line[i]);
  if (std::strtol(line.c_str() + star + 1, nullptr, 10) != sum) {
    MarlinLineError("checksum mismatch");
    return false;
  }
  marlin_.last_n = n;
  return true;
}

void VirtualCnc::Impl::MarlinLine(Lock& lk, const std::string& raw) {
  const std::size_t first = raw.find_first_not_of(' ');
  const std::string line = first == std::string::npos ? std::string() : raw.substr(first);
  if (!line.empty() && !MarlinFraming(line)) return;
  marlin_.in_command = true;  // KEEPALIVE_STATE(IN_HANDLER)
  marlin_.next_busy = MachineNow() + options_.marlin.keepalive_s;
  const bool ok = MarlinCommand(lk, CommandOf(line));
  marlin_.in_command = false;
  if (abort_ || Aborting()) return;
  if (ok) Emit("ok\n");
}

// One command, its output; false when it printed its own ok (M105).
bool VirtualCnc::Impl::MarlinCommand(Lock& lk, const std::string& command) {
  const std::optional<MarlinWords> w = virtual_cnc_internal::ParseWords(command);
  const auto unknown = [&] {
    Emit("echo:Unknown command: \"" + command + "\"\n");
    return true;
  };
  if (!w) return command.empty() ? true : unknown();
  if (w->letter == 'G') {
    switch (w->code) {
      case 0:
      case 1:
        MarlinMove(lk, w->Value('X'), w->Value('Y'), w->Value('Z'), w->Value('F'));
        return true;
      case 4: {
        const double s = w->Value('S').value_or(0.0) + w->Value('P').value_or(0.0) / 1000.0;
        McDwell(lk, s);  // dwell(): planner.synchronize() first
        return true;
      }
      case 21:
        return true;
      case 28:
        MarlinHome(lk, w->Has('X'), w->Has('Y'), w->Has('Z'));
        return true;
      case 90:
      case 91:
        marlin_.relative = w->code == 91;
        return true;
      default:
        return unknown();
    }
  }
  if (w->letter != 'M') return unknown();
  return MarlinMCode(lk, *w, command);
}

bool VirtualCnc::Impl::MarlinMCode(Lock& lk, const MarlinWords& w, const std::string& command) {
  switch (w.code) {
    case 17:
    case 18:
    case 84:  // steppers on / off
    case 82:
    case 83:  // extruder modes
    case 104:
    case 109:
    case 140:  // heaters (nothing heats here)
    case 190:
    case 141:
    case 191:
    case 106:
    case 107:  // fan
    case 108:
    case 112:
    case 410:  // taken by the emergency parser as they arrived
      return true;
    case 105:
      Emit("ok T:25.00 /0.00 B:25.00 /0.00 @:0 B@:0\n");
      return false;
    case 110:
      if (const auto n = w.Value('N')) marlin_.last_n = static_cast<long>(*n);
      return true;
    case 114:
      Emit(MarlinPosition(w.Has('R') && options_.marlin.m114_realtime));
      return true;
    case 115:
      MarlinReportFirmware();
      return true;
    case 154:
      if (!options_.marlin.auto_report_position) break;
      marlin_.position_s = w.Value('S').value_or(0.0);
      marlin_.next_position = MachineNow() + marlin_.position_s;
      return true;
    case 155:
      marlin_.temperature_s = w.Value('S').value_or(0.0);
      marlin_.next_temperature = MachineNow() + marlin_.temperature_s;
      return true;
    case 211:
      if (const auto s = w.Value('S')) marlin_.soft_endstops = *s != 0.0;
      Emit("echo:Soft endstops: " + std::string(marlin_.soft_endstops ? "On " : "Off") + " Min:  " +
           Xyz(Eigen::Vector3d::Zero(), 2) + "   Max:  " + Xyz(settings_.max_travel_mm, 2) + "\n");
      return true;
    case 400:
      Synchronize(lk);
      return true;
    case 503:
      MarlinReportSettings();
      return true;
    default:
      break;
  }
  Emit("echo:Unknown command: \"" + command + "\"\n");
  return true;
}

// prepare_line_to_destination() after apply_motion_limits(): the target clamped into the soft
// endstops on homed axes, then into the planner (waiting for room).
void VirtualCnc::Impl::MarlinMove(Lock& lk, std::optional<double> x, std::optional<double> y,
                                  std::optional<double> z, std::optional<double> f) {
  if (f && *f > 0.0) marlin_.feed_mm_min = *f;
  Eigen::Vector3d target = gc_.position;
  const std::optional<double> words[3] = {x, y, z};
  for (int a = 0; a < 3; ++a) {
    if (!words[a]) continue;
    target[a] = marlin_.relative ? target[a] + *words[a] : *words[a];
    if (marlin_.soft_endstops && ((marlin_.homed >> a) & 1)) {
      target[a] = std::clamp(target[a], 0.0, settings_.max_travel_mm[a]);
    }
  }
  while (true) {
    ExecuteRealtime(lk);
    if (abort_ || Aborting()) return;
    if (!exec_.PlannerFull()) break;
    AutoCycleStart();
    Wait(lk);
  }
  MoveRate rate;
  rate.rapid = false;
  rate.feed_mm_per_min = marlin_.feed_mm_min;
  if (exec_.AddLine(Quantize(target) + offset_, rate, MachineNow(), armed_alarm_)) {
    armed_alarm_.reset();
    ++stats_.blocks_planned;
  }
  gc_.position = target;
  AutoCycleStart();
}

// G28: each axis asked for (all without X, Y or Z) toward its minimum endstop at true 0: fast,
// a bump back, slowly again; the axis is then homed at 0.
void VirtualCnc::Impl::MarlinHome(Lock& lk, bool x, bool y, bool z) {
  Synchronize(lk);
  if (abort_ || Aborting()) return;
  const bool all = !x && !y && !z;
  const bool axes[3] = {all || x, all || y, all || z};
  for (int a = 0; a < 3; ++a) {
    if (!axes[a]) continue;
    if (!MarlinHomeAxis(lk, a)) return;
  }
  gc_.position = Belief();
}

bool VirtualCnc::Impl::MarlinHomeAxis(Lock& lk, int a) {
  Eigen::Vector3d here = exec_.PositionAt(MachineNow());
  const double limit = kHomingSearchScalar * settings_.max_travel_mm[a];
  Eigen::Vector3d target = here;
  target[a] = std::max(0.0, here[a] - limit);
  if (!HomingMove(lk, target, settings_.homing_seek_mm_per_min, true)) return false;
  if (target[a] > 0.0) {  // the endstop never triggered
    Emit("Error:Homing Failed\n");
    rt_alarm_ = kMarlinKill;
    ExecuteRealtime(lk);
    return false;
  }
  here = exec_.PositionAt(MachineNow());
  target = here;
  target[a] = kHomingBumpMm;
  if (!HomingMove(lk, target, settings_.homing_seek_mm_per_min, false)) return false;
  target[a] = 0.0;
  if (!HomingMove(lk, target, settings_.homing_feed_mm_per_min, true)) return false;
  offset_[a] = exec_.PositionAt(MachineNow())[a];  // belief 0 where the switch is
  marlin_.homed |= 1 << a;
  return true;
}

// M114: the planned position (current_position) and the steppers' counts; M114 R: the steppers'
// position as it is now.
std::string VirtualCnc::Impl::MarlinPosition(bool real) const {
  const Eigen::Vector3d steppers = Belief();
  const int decimals = real ? 3 : 2;
  const Eigen::Vector3d& p = real ? steppers : gc_.position;
  std::string s = "X:" + Fixed(p.x(), decimals) + " Y:" + Fixed(p.y(), decimals) +
                  " Z:" + Fixed(p.z(), decimals) + " E:" + Fixed(0.0, decimals);
  if (!real) {
    const auto count = [&](int a) {
      return std::to_string(std::lround(steppers[a] * settings_.steps_per_mm[a]));
    };
    s += " Count X:" + count(0) + " Y:" + count(1) + " Z:" + count(2);
  }
  return s + "\n";
}

void VirtualCnc::Impl::MarlinReportFirmware() {
  Emit(
      "FIRMWARE_NAME:Marlin 2.1.2.1 (Jul 13 2023 12:00:00) SOURCE_CODE_URL:github.com/"
      "MarlinFirmware/Marlin PROTOCOL_VERSION:1.0 MACHINE_TYPE:" +
      options_.marlin.machine_type +
      " EXTRUDER_COUNT:1 UUID:cede2a2f-41a2-4748-9b12-c55c62f367ff\n");
  const std::pair<const char*, bool> caps[] = {
      {"SERIAL_XON_XOFF", false},
      {"BINARY_FILE_TRANSFER", false},
      {"EEPROM", false},
      {"AUTOREPORT_POS", options_.marlin.auto_report_position},
      {"AUTOREPORT_TEMP", true},
      {"EMERGENCY_PARSER", true},
      {"HOST_ACTION_COMMANDS", false},
      {"SDCARD", false},
      {"THERMAL_PROTECTION", true},
      {"ARCS", false},
  };
  for (const auto& [name, on] : caps)
    Emit(std::string("Cap:") + name + ":" + (on ? "1" : "0") + "\n");
}

// M503 (settings.report()): the lines a host reads the machine's motion from.
void VirtualCnc::Impl::MarlinReportSettings() {
  const Eigen::Vector3d rate = settings_.max_rate_mm_per_min / 60.0;
  const Eigen::Vector3d& accel = settings_.acceleration_mm_per_s2;
  const std::string amax = Fixed(accel.maxCoeff(), 2);
  Emit(
      "echo:; Linear Units:\necho:  G21 ; (mm)\n"
      "echo:; Steps per unit:\necho:  M92 " +
      Xyz(settings_.steps_per_mm, 2) +
      " E93.00\n"
      "echo:; Max feedrates (units/s):\necho:  M203 " +
      Xyz(rate, 2) +
      " E25.00\n"
      "echo:; Max Acceleration (units/s2):\necho:  M201 " +
      Xyz(accel, 2) +
      " E5000.00\n"
      "echo:; Acceleration (units/s2) (P<print-accel> R<retract-accel> T<travel-accel>):\n"
      "echo:  M204 P" +
      amax + " R" + amax + " T" + amax +
      "\n"
      "echo:; Advanced (B<min_segment_time_us> S<min_feedrate> T<min_travel_feedrate> "
      "J<junc_dev>):\necho:  M205 B20000.00 S0.00 T0.00 J" +
      Fixed(settings_.junction_deviation_mm, 3) + "\n");
}

}  // namespace gs360
