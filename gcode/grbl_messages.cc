#include "gcode/grbl_messages.h"

#include <algorithm>
#include <span>

#include "gcode/reply_text.h"

namespace gs360 {
namespace {

using reply_text::EndsWith;
using reply_text::ParseNumber;
using reply_text::Split;
using reply_text::StartsWith;
using reply_text::Trim;

std::optional<std::vector<double>> ParseNumberList(std::string_view s) {
  std::vector<double> values;
  for (std::string_view part : Split(s, ',')) {
    const auto v = ParseNumber<double>(part);
    if (!v) return std::nullopt;
    values.push_back(*v);
  }
  return values;
}

// "x,y,z[,a...]" -> first three; nullopt when fewer than three or malformed.
std::optional<Eigen::Vector3d> ParsePosition(std::string_view s, int* axis_count) {
  const auto values = ParseNumberList(s);
  if (!values || values->size() < 3) return std::nullopt;
  if (axis_count != nullptr) *axis_count = static_cast<int>(values->size());
  return Eigen::Vector3d((*values)[0], (*values)[1], (*values)[2]);
}

GrblMachineState StateFromName(std::string_view name) {
  if (name == "Idle") return GrblMachineState::kIdle;
  if (name == "Run") return GrblMachineState::kRun;
  if (name == "Hold") return GrblMachineState::kHold;
  if (name == "Jog") return GrblMachineState::kJog;
  if (name == "Alarm") return GrblMachineState::kAlarm;
  if (name == "Door") return GrblMachineState::kDoor;
  if (name == "Check") return GrblMachineState::kCheck;
  if (name == "Home") return GrblMachineState::kHome;
  if (name == "Sleep") return GrblMachineState::kSleep;
  if (name == "Tool") return GrblMachineState::kTool;
  return GrblMachineState::kUnknown;
}

bool IsLetters(std::string_view s) {
  for (char c : s) {
    if (!((c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z'))) return false;
  }
  return true;
}

// Fills msg->status from "<...>" content; false when the report is malformed.
bool ParseStatus(std::string_view body, GrblMessage* msg) {
  GrblStatusReport& st = msg->status;
  const auto fields = Split(body, '|');
  if (fields.empty() || fields[0].empty()) return false;
  {
    std::string_view state = fields[0];
    const auto colon = state.find(':');
    if (colon != std::string_view::npos) {
      const auto sub = ParseNumber<int>(state.substr(colon + 1));
      if (!sub) return false;
      st.substate = *sub;
      state = state.substr(0, colon);
    }
    if (!IsLetters(state)) return false;
    st.state_text = std::string(state);
    st.state = StateFromName(state);
  }
  bool have_position = false;
  for (std::size_t i = 1; i < fields.size(); ++i) {
    const std::string_view field = fields[i];
    const auto colon = field.find(':');
    if (colon == std::string_view::npos || colon == 0) return false;
    const std::string_view key = field.substr(0, colon);
    const std::string_view value = field.substr(colon + 1);
    if (key == "MPos" || key == "WPos") {
      auto p = ParsePosition(value, &st.axis_count);
      if (!p) return false;
      (key == "MPos" ? st.mpos : st.wpos) = *p;
      have_position = true;
    } else if (key == "WCO") {
      auto p = ParsePosition(value, nullptr);
      if (!p) return false;
      st.wco = *p;
    } else if (key == "FS" || key == "F") {
      const auto v = ParseNumberList(value);
      if (!v || v->empty() || v->size() > 2 || (key == "FS" && v->size() != 2)) return false;
      st.feed = (*v)[0];
      if (v->size() == 2) st.spindle = (*v)[1];
    } else if (key == "Bf") {
      const auto parts = Split(value, ',');
      if (parts.size() != 2) return false;
      const auto blocks = ParseNumber<int>(parts[0]);
      const auto bytes = ParseNumber<int>(parts[1]);
      if (!blocks || !bytes) return false;
      st.planner_blocks_free = *blocks;
      st.rx_bytes_free = *bytes;
    } else if (key == "Ln") {
      const auto ln = ParseNumber<long>(value);
      if (!ln) return false;
      st.line_number = *ln;
    } else if (key == "Ov") {
      const auto parts = Split(value, ',');
      if (parts.size() != 3) return false;
      std::array<int, 3> ov{};
      for (int k = 0; k < 3; ++k) {
        const auto v = ParseNumber<int>(parts[static_cast<std::size_t>(k)]);
        if (!v) return false;
        ov[static_cast<std::size_t>(k)] = *v;
      }
      st.overrides = ov;
    } else if (key == "Pn") {
      if (!IsLetters(value)) return false;
      st.pins = std::string(value);
    } else if (key == "A") {
      if (!IsLetters(value)) return false;
      st.accessories = std::string(value);
    } else {
      st.other_fields.emplace_back(std::string(key), std::string(value));
    }
  }
  return have_position;
}

bool IsParameterName(std::string_view name) {
  if (name == "TLO" || name == "PRB") return true;
  if (name.size() < 2 || name[0] != 'G') return false;
  for (char c : name.substr(1)) {
    if (!((c >= '0' && c <= '9') || c == '.')) return false;
  }
  return true;
}

// "[NAME:body]".
void ParseBracket(std::string_view inner, GrblMessage* msg) {
  const auto colon = inner.find(':');
  if (colon == std::string_view::npos) {
    msg->kind = GrblMessageKind::kFeedback;
    msg->text = std::string(inner);
    return;
  }
  const std::string_view name = inner.substr(0, colon);
  const std::string_view body = inner.substr(colon + 1);
  msg->name = std::string(name);
  msg->text = std::string(body);
  if (name == "MSG") {
    msg->kind = GrblMessageKind::kMessage;
  } else if (name == "GC") {
    msg->kind = GrblMessageKind::kGcState;
  } else if (name == "HLP") {
    msg->kind = GrblMessageKind::kHelp;
  } else if (name == "echo") {
    msg->kind = GrblMessageKind::kEcho;
  } else if (name == "VER") {
    msg->kind = GrblMessageKind::kVersion;
    const auto c = body.find(':');
    msg->version = std::string(body.substr(0, c));
    msg->text = c == std::string_view::npos ? std::string() : std::string(body.substr(c + 1));
  } else if (name == "OPT") {
    msg->kind = GrblMessageKind::kOptions;
    const auto parts = Split(body, ',');
    msg->option_codes = std::string(parts[0]);
    if (parts.size() >= 2) msg->planner_blocks = ParseNumber<int>(parts[1]);
    if (parts.size() >= 3) msg->rx_buffer_bytes = ParseNumber<int>(parts[2]);
  } else if (IsParameterName(name)) {
    std::string_view values = body;
    if (name == "PRB") {
      const auto c = body.rfind(':');
      if (c != std::string_view::npos) {
        const std::string_view flag = body.substr(c + 1);
        if (flag == "1") msg->probe_success = true;
        if (flag == "0") msg->probe_success = false;
        values = body.substr(0, c);
      }
    }
    const auto list = ParseNumberList(values);
    if (!list) {
      msg->kind = GrblMessageKind::kFeedback;  // a bracket message we cannot read as numbers
      return;
    }
    msg->kind = GrblMessageKind::kParameter;
    msg->values = *list;
  } else {
    msg->kind = GrblMessageKind::kFeedback;
  }
}

}  // namespace

std::optional<Eigen::Vector3d> GrblStatusReport::MachinePosition(
    const std::optional<Eigen::Vector3d>& last_wco) const {
  if (mpos) return mpos;
  if (wpos) {
    if (wco) return Eigen::Vector3d(*wpos + *wco);
    if (last_wco) return Eigen::Vector3d(*wpos + *last_wco);
  }
  return std::nullopt;
}

std::string SanitizeGrblLine(std::string_view bytes) {
  std::string out;
  out.reserve(bytes.size());
  for (char c : bytes) {
    const auto u = static_cast<unsigned char>(c);
    if (u >= 0x20 && u <= 0x7e) out.push_back(c);
  }
  const std::string_view t = Trim(out);
  return std::string(t);
}

namespace {

// "error:N" or "ALARM:N" (`s` starts with one of them).
void ParseErrorOrAlarm(std::string_view s, GrblMessage* msg) {
  const bool error = s[0] == 'e';
  msg->kind = error ? GrblMessageKind::kError : GrblMessageKind::kAlarm;
  const std::string_view rest = Trim(s.substr(6));
  const auto code = ParseNumber<int>(rest);
  msg->code = code.value_or(-1);
  // A non-numeric code (GRBL 0.9 style "error: Bad number format") is still an error reply:
  // it must resolve its line or the character count would drift.
  msg->text = code ? (error ? GrblErrorText(*code) : GrblAlarmText(*code)) : std::string(rest);
}

// "$N=value" (a setting) or "$Nn=line" (a startup line); `s` starts with '$'.
void ParseSettingLine(std::string_view s, GrblMessage* msg) {
  msg->kind = GrblMessageKind::kUnknown;
  const auto eq = s.find('=');
  if (eq == std::string_view::npos || eq <= 1) return;
  const std::string_view key = s.substr(1, eq - 1);
  const std::string_view value = s.substr(eq + 1);
  if (key[0] == 'N' && key.size() > 1) {
    if (const auto n = ParseNumber<int>(key.substr(1))) {
      msg->kind = GrblMessageKind::kStartupLineSetting;
      msg->setting = *n;
      msg->text = std::string(value);
    }
  } else if (const auto n = ParseNumber<int>(key)) {
    msg->kind = GrblMessageKind::kSetting;
    msg->setting = *n;
    // GRBL 0.9 appended "(description)" after the value.
    const std::string_view v = Trim(value.substr(0, value.find(" (")));
    msg->text = std::string(v);
    msg->setting_value = ParseNumber<double>(v);
  }
}

// ">line:ok" or ">line:error:N", a startup line's result; `s` starts with '>'.
void ParseStartupLineResult(std::string_view s, GrblMessage* msg) {
  const std::string_view body = s.substr(1);
  if (EndsWith(body, ":ok")) {
    msg->kind = GrblMessageKind::kStartupLineResult;
    msg->text = std::string(body.substr(0, body.size() - 3));
    msg->code = 0;
    return;
  }
  const auto e = body.rfind(":error:");
  if (e != std::string_view::npos) {
    if (const auto code = ParseNumber<int>(body.substr(e + 7))) {
      msg->kind = GrblMessageKind::kStartupLineResult;
      msg->text = std::string(body.substr(0, e));
      msg->code = *code;
      return;
    }
  }
  msg->kind = GrblMessageKind::kUnknown;
}

// Welcome: "Grbl 1.1h ['$' for help]", "GrblHAL 1.1f ['$' or '$HELP' for help]",
// "Grbl 3.7 [FluidNC v3.7.8 (wifi) '$' for help]". Searched anywhere in the line, because a
// reset is what the client must never miss, even behind noise. Anything else is kUnknown.
void ParseWelcomeOrUnknown(std::string_view s, GrblMessage* msg) {
  msg->kind = GrblMessageKind::kUnknown;
  const auto g = s.find("Grbl");
  if (g == std::string_view::npos || !EndsWith(s, "for help]")) return;
  const std::string_view rest = s.substr(g);
  const auto sp = rest.find(' ');
  if (sp == std::string_view::npos) return;
  const std::string_view after = rest.substr(sp + 1);
  const auto sp2 = after.find(' ');
  msg->kind = GrblMessageKind::kWelcome;
  msg->name = std::string(rest.substr(0, sp));
  msg->version = std::string(after.substr(0, sp2));
  msg->text = sp2 == std::string_view::npos ? std::string() : std::string(after.substr(sp2 + 1));
}

}  // namespace

GrblMessage ParseGrblLine(std::string_view line) {
  GrblMessage msg;
  msg.raw = SanitizeGrblLine(line);
  const std::string_view s = msg.raw;
  if (s.empty()) {
    msg.kind = GrblMessageKind::kEmpty;
  } else if (s == "ok") {
    msg.kind = GrblMessageKind::kOk;
  } else if (StartsWith(s, "error:") || StartsWith(s, "ALARM:")) {
    ParseErrorOrAlarm(s, &msg);
  } else if (s.front() == '<') {
    if (s.back() == '>' && ParseStatus(s.substr(1, s.size() - 2), &msg)) {
      msg.kind = GrblMessageKind::kStatus;
    } else {
      msg.kind = GrblMessageKind::kUnknown;
      msg.status = GrblStatusReport{};
    }
  } else if (s.front() == '[') {
    if (s.back() == ']') {
      ParseBracket(s.substr(1, s.size() - 2), &msg);
    } else {
      msg.kind = GrblMessageKind::kUnknown;
    }
  } else if (s.front() == '$') {
    ParseSettingLine(s, &msg);
  } else if (s.front() == '>') {
    ParseStartupLineResult(s, &msg);
  } else {
    ParseWelcomeOrUnknown(s, &msg);
  }
  return msg;
}

void GrblLineSplitter::Feed(const char* data, std::size_t n, std::vector<std::string>* lines) {
  for (std::size_t i = 0; i < n; ++i) {
    const char c = data[i];
    if (c == '\n' || c == '\r') {
      if (discarding_) {
        discarding_ = false;
      } else if (!partial_.empty()) {
        lines->push_back(std::move(partial_));
      }
      partial_.clear();
      continue;
    }
    if (discarding_) continue;
    partial_.push_back(c);
    if (partial_.size() >= kMaxLine) {
      ++overlong_;
      lines->push_back(std::move(partial_));
      partial_.clear();
      discarding_ = true;
    }
  }
}

std::string_view GrblMachineStateName(GrblMachineState state) {
  switch (state) {
    case GrblMachineState::kIdle:
      return "Idle";
    case GrblMachineState::kRun:
      return "Run";
    case GrblMachineState::kHold:
      return "Hold";
    case GrblMachineState::kJog:
      return "Jog";
    case GrblMachineState::kAlarm:
      return "Alarm";
    case GrblMachineState::kDoor:
      return "Door";
    case GrblMachineState::kCheck:
      return "Check";
    case GrblMachineState::kHome:
      return "Home";
    case GrblMachineState::kSleep:
      return "Sleep";
    case GrblMachineState::kTool:
      return "Tool";
    case GrblMachineState::kUnknown:
      break;
  }
  return "Unknown";
}

std::string_view GrblMessageKindName(GrblMessageKind kind) {
  switch (kind) {
    case GrblMessageKind::kOk:
      return "ok";
    case GrblMessageKind::kError:
      return "error";
    case GrblMessageKind::kAlarm:
      return "alarm";
    case GrblMessageKind::kWelcome:
      return "welcome";
    case GrblMessageKind::kStatus:
      return "status";
    case GrblMessageKind::kMessage:
      return "message";
    case GrblMessageKind::kGcState:
      return "gc-state";
    case GrblMessageKind::kHelp:
      return "help";
    case GrblMessageKind::kVersion:
      return "version";
    case GrblMessageKind::kOptions:
      return "options";
    case GrblMessageKind::kEcho:
      return "echo";
    case GrblMessageKind::kParameter:
      return "parameter";
    case GrblMessageKind::kFeedback:
      return "feedback";
    case GrblMessageKind::kSetting:
      return "setting";
    case GrblMessageKind::kStartupLineSetting:
      return "startup-line-setting";
    case GrblMessageKind::kStartupLineResult:
      return "startup-line-result";
    case GrblMessageKind::kEmpty:
      return "empty";
    case GrblMessageKind::kUnknown:
      break;
  }
  return "unknown";
}

namespace {

struct CodeText {
  int code;
  std::string_view text;
};

// Error codes ("error:N"). Texts are verbatim from the sources, typos included:
//  - GRBL 1.1: gnea/grbl doc/csv/error_codes_en_US.csv (codes 1-17, 20-38).
//  - grblHAL: grblHAL/core errors.c (status_detail[]; enum status_code_t in errors.h) for the
//    codes GRBL 1.1 lacks; 60-66 and 70 are described by grblHAL plugins (Plugin_SD_card
//    sdcard.c / fs_stream.c, the Bluetooth plugin), which register them with the core.
// Where both define a code the meaning agrees but grblHAL rewords some texts (e.g. 6: "greater
// or equal to 2 microseconds", 7: "settings" for "EEPROM", 38: "... or undefined tool
// selected"); GRBL 1.1's text is kept for those. FluidNC numbers 18, 19 and 38 up differently
// (its Error.h), so its texts are not used.
constexpr CodeText kErrorTexts[] = {
    {1, "G-code words consist of a letter and a value. Letter was not found."},
    {2, "Missing the expected G-code word value or numeric value format is not valid."},
    {3, "Grbl '$' system command was not recognized or supported."},
    {4, "Negative value received for an expected positive value."},
    {5, "Homing cycle failure. Homing is not enabled via settings."},
    {6, "Minimum step pulse time must be greater than 3usec."},
    {7, "An EEPROM read failed. Auto-restoring affected EEPROM to default values."},
    {8,
     "Grbl '$' command cannot be used unless Grbl is IDLE. Ensures smooth operation during a "
     "job."},
    {9, "G-code commands are locked out during alarm or jog state."},
    {10, "Soft limits cannot be enabled without homing also enabled."},
    {11, "Max characters per line exceeded. Received command line was not executed."},
    {12, "Grbl '$' setting value cause the step rate to exceed the maximum supported."},
    {13, "Safety door detected as opened and door state initiated."},
    {14, "Build info or startup line exceeded EEPROM line length limit. Line not stored."},
    {15, "Jog target exceeds machine travel. Jog command has been ignored."},
    {16, "Jog command has no '=' or contains prohibited g-code."},
    {17, "Laser mode requires PWM output."},
    {18, "Reset asserted"},      // grblHAL
    {19, "Non positive value"},  // grblHAL
    {20, "Unsupported or invalid g-code command found in block."},
    {21, "More than one g-code command from same modal group found in block."},
    {22, "Feed rate has not yet been set or is undefined."},
    {23, "G-code command in block requires an integer value."},
    {24, "More than one g-code command that requires axis words found in block."},
    {25, "Repeated g-code word found in block."},
    {26,
     "No axis words found in block for g-code command or current modal state which requires "
     "them."},
    {27, "Line number value is invalid."},
    {28, "G-code command is missing a required value word."},
    {29, "G59.x work coordinate systems are not supported."},
    {30, "G53 only allowed with G0 and G1 motion modes."},
    {31, "Axis words found in block when no command or current modal state uses them."},
    {32, "G2 and G3 arcs require at least one in-plane axis word."},
    {33, "Motion command target is invalid."},
    {34, "Arc radius value is invalid."},
    {35, "G2 and G3 arcs require at least one in-plane offset word."},
    {36, "Unused value words found in block."},
    {37, "G43.1 dynamic tool length offset is not assigned to configured tool length axis."},
    {38, "Tool number greater than max supported value."},
    // grblHAL from here on.
    {39, "Value out of range."},
    {40, "G-code command not allowed when tool change is pending."},
    {41, "Spindle not running when motion commanded in CSS or spindle sync mode."},
    {42, "Plane must be ZX for threading."},
    {43, "Max. feed rate exceeded."},
    {44, "RPM out of range."},
    {45, "Only homing is allowed when a limit switch is engaged."},
    {46, "Home machine to continue."},
    {47, "ATC: current tool is not set. Set current tool with M61."},
    {48, "Value word conflict."},
    {49, "Power on self test failed. A hard reset is required."},
    {50, "Emergency stop active."},
    {51, "Motor fault."},
    {52, "Setting value is out of range."},
    {53, "Setting is not available, possibly due to limited driver support."},
    {54, "Retract position is less than drill depth."},
    {55, "Attempt to home two auto squared axes at the same time."},
    {56, "Coordinate system is locked."},
    {57, "Unexpected file demarcation."},
    {58, "Port is not available"},
    {60, "SD Card mount failed."},
    // Plugin_SD_card's current text; older versions (Status_SDReadError) said "SD Card file
    // open/read failed.".
    {61, "File delete failed."},
    {62, "Directory listing failed."},
    {63, "Directory not found."},
    {64, "SD Card not mounted."},
    {65, "File system not mounted."},
    {66, "File system is read only."},
    {70, "Bluetooth initialisation failed."},
    {71, "Unknown operation found in expression."},
    {72, "Divide by zero in expression attempted."},
    {73, "Too large or too small argrument provided."},
    {74, "Argument is not valid for the operation"},
    {75, "Expression is not valid."},
    {76, "Either NAN (not a number) or infinity was returned from expression."},
    {77, "Authentication required."},
    {78, "Access denied."},
    {79, "Not allowed while critical event is active."},
    {80, "Flow statement only allowed in filesystem macro."},
    {81, "Unknown flow statement."},
    {82, "Stack overflow while executing flow statement."},
    {83, "Out of memory while executing flow statement."},
    {84, "Could not open file."},
    {253, "User defined error occured."},
};

// Alarm codes ("ALARM:N"). GRBL 1.1: gnea/grbl doc/csv/alarm_codes_en_US.csv (1-10; 10 came
// with dual-axis homing in 1.1h). grblHAL: grblHAL/core alarms.c (alarm_detail[]; enum
// alarm_code_t in alarms.h); 1-9 are word for word GRBL's.
// CONFLICT: grblHAL's alarm 10 is Alarm_EStop, "EStop asserted. Clear and reset"; GRBL 1.1's
// text is kept for it, as for every code GRBL 1.1 defines.
constexpr CodeText kAlarmTexts[] = {
    {1,
     "Hard limit has been triggered. Machine position is likely lost due to sudden halt. "
     "Re-homing is highly recommended."},
    {2,
     "Soft limit alarm. G-code motion target exceeds machine travel. Machine position "
     "retained. Alarm may be safely unlocked."},
    {3,
     "Reset while in motion. Machine position is likely lost due to sudden halt. Re-homing "
     "is highly recommended."},
    {4,
     "Probe fail. Probe is not in the expected initial state before starting probe cycle "
     "when G38.2 and G38.3 is not triggered and G38.4 and G38.5 is triggered."},
    {5,
     "Probe fail. Probe did not contact the workpiece within the programmed travel for G38.2 "
     "and G38.4."},
    {6, "Homing fail. The active homing cycle was reset."},
    {7, "Homing fail. Safety door was opened during homing cycle."},
    {8,
     "Homing fail. Pull off travel failed to clear limit switch. Try increasing pull-off "
     "setting or check wiring."},
    {9,
     "Homing fail. Could not find limit switch within search distances. Try increasing max "
     "travel, decreasing pull-off distance, or check wiring."},
    {10,
     "Homing fail. Second dual axis limit switch failed to trigger within configured search "
     "distance after first. Try increasing trigger fail distance or check wiring."},
    // grblHAL from here on.
    {11, "Homing required. Execute homing command ($H) to continue."},
    {12, "Limit switch engaged. Clear before continuing."},
    {13, "Probe protection triggered. Clear before continuing."},
    {14, "Spindle at speed timeout. Clear before continuing."},
    {15,
     "Homing fail. Could not find second limit switch for auto squared axis within search "
     "distances. Try increasing max travel, decreasing pull-off distance, or check wiring."},
    {16, "Power on selftest (POS) failed."},
    {17, "Motor fault."},
    {18, "Homing fail. Bad configuration."},
};

// Sorted by code, no duplicates, no empty text: what LookUp relies on.
constexpr bool StrictlySorted(std::span<const CodeText> table) {
  for (std::size_t i = 0; i < table.size(); ++i) {
    if (table[i].text.empty() || (i > 0 && table[i - 1].code >= table[i].code)) return false;
  }
  return true;
}
static_assert(StrictlySorted(kErrorTexts) && StrictlySorted(kAlarmTexts));

std::optional<std::string_view> LookUp(std::span<const CodeText> table, int code) {
  const auto it = std::lower_bound(table.begin(), table.end(), code,
                                   [](const CodeText& e, int c) { return e.code < c; });
  if (it == table.end() || it->code != code) return std::nullopt;
  return it->text;
}

}  // namespace

std::string GrblErrorText(int code) {
  if (const auto text = LookUp(kErrorTexts, code)) return std::string(*text);
  return "unknown error " + std::to_string(code) + " (not in the GRBL 1.1 or grblHAL tables)";
}

std::string GrblAlarmText(int code) {
  if (const auto text = LookUp(kAlarmTexts, code)) return std::string(*text);
  return "unknown alarm " + std::to_string(code) + " (not in the GRBL 1.1 or grblHAL tables)";
}

bool GrblAlarmLosesPosition(int code) {
  // Only three alarms keep the position: 2 (soft limit: the target was refused before any
  // motion; the text says "Machine position retained") and 4/5 (probe fail: no motion, or the
  // probe move ran its programmed travel to the end). Everything else, including grblHAL's
  // 10-18 (E-stop, homing required or failed, limit switch engaged, probe protection, spindle,
  // self test, motor fault) and unknown codes, means the machine must be re-homed.
  return !(code == 2 || code == 4 || code == 5);
}

}  // namespace gs360
