#include "gcode/grbl_messages.h"

#include <charconv>
#include <system_error>

namespace gs360 {
namespace {

bool StartsWith(std::string_view s, std::string_view p) {
  return s.substr(0, p.size()) == p;
}

bool EndsWith(std::string_view s, std::string_view p) {
  return s.size() >= p.size() && s.substr(s.size() - p.size()) == p;
}

std::string_view Trim(std::string_view s) {
  while (!s.empty() && s.front() == ' ') s.remove_prefix(1);
  while (!s.empty() && s.back() == ' ') s.remove_suffix(1);
  return s;
}

template <typename T>
std::optional<T> ParseNumber(std::string_view s) {
  s = Trim(s);
  if (s.empty()) return std::nullopt;
  // from_chars rejects a leading '+'; GRBL never sends one but other firmwares might.
  if (s.front() == '+') s.remove_prefix(1);
  T value{};
  const auto [ptr, ec] = std::from_chars(s.data(), s.data() + s.size(), value);
  if (ec != std::errc() || ptr != s.data() + s.size()) return std::nullopt;
  return value;
}

std::vector<std::string_view> Split(std::string_view s, char sep) {
  std::vector<std::string_view> parts;
  std::size_t start = 0;
  while (true) {
    const auto pos = s.find(sep, start);
    if (pos == std::string_view::npos) {
      parts.push_back(s.substr(start));
      return parts;
    }
    parts.push_back(s.substr(start, pos - start));
    start = pos + 1;
  }
}

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

GrblMessage ParseGrblLine(std::string_view line) {
  GrblMessage msg;
  msg.raw = SanitizeGrblLine(line);
  const std::string_view s = msg.raw;
  if (s.empty()) {
    msg.kind = GrblMessageKind::kEmpty;
    return msg;
  }
  if (s == "ok") {
    msg.kind = GrblMessageKind::kOk;
    return msg;
  }
  if (StartsWith(s, "error:") || StartsWith(s, "ALARM:")) {
    const bool error = s[0] == 'e';
    msg.kind = error ? GrblMessageKind::kError : GrblMessageKind::kAlarm;
    const std::string_view rest = Trim(s.substr(6));
    const auto code = ParseNumber<int>(rest);
    msg.code = code.value_or(-1);
    // A non-numeric code (GRBL 0.9 style "error: Bad number format") is still an error reply:
    // it must resolve its line or the character count would drift.
    msg.text = code ? (error ? GrblErrorText(*code) : GrblAlarmText(*code)) : std::string(rest);
    return msg;
  }
  if (s.front() == '<') {
    if (s.back() == '>' && ParseStatus(s.substr(1, s.size() - 2), &msg)) {
      msg.kind = GrblMessageKind::kStatus;
    } else {
      msg.kind = GrblMessageKind::kUnknown;
      msg.status = GrblStatusReport{};
    }
    return msg;
  }
  if (s.front() == '[') {
    if (s.back() == ']') {
      ParseBracket(s.substr(1, s.size() - 2), &msg);
    } else {
      msg.kind = GrblMessageKind::kUnknown;
    }
    return msg;
  }
  if (s.front() == '$') {
    const auto eq = s.find('=');
    if (eq != std::string_view::npos && eq > 1) {
      const std::string_view key = s.substr(1, eq - 1);
      const std::string_view value = s.substr(eq + 1);
      if (key[0] == 'N' && key.size() > 1) {
        if (const auto n = ParseNumber<int>(key.substr(1))) {
          msg.kind = GrblMessageKind::kStartupLineSetting;
          msg.setting = *n;
          msg.text = std::string(value);
          return msg;
        }
      } else if (const auto n = ParseNumber<int>(key)) {
        msg.kind = GrblMessageKind::kSetting;
        msg.setting = *n;
        // GRBL 0.9 appended "(description)" after the value.
        const std::string_view v = Trim(value.substr(0, value.find(" (")));
        msg.text = std::string(v);
        msg.setting_value = ParseNumber<double>(v);
        return msg;
      }
    }
    msg.kind = GrblMessageKind::kUnknown;
    return msg;
  }
  if (s.front() == '>') {
    const std::string_view body = s.substr(1);
    if (EndsWith(body, ":ok")) {
      msg.kind = GrblMessageKind::kStartupLineResult;
      msg.text = std::string(body.substr(0, body.size() - 3));
      msg.code = 0;
      return msg;
    }
    const auto e = body.rfind(":error:");
    if (e != std::string_view::npos) {
      if (const auto code = ParseNumber<int>(body.substr(e + 7))) {
        msg.kind = GrblMessageKind::kStartupLineResult;
        msg.text = std::string(body.substr(0, e));
        msg.code = *code;
        return msg;
      }
    }
    msg.kind = GrblMessageKind::kUnknown;
    return msg;
  }
  // Welcome: "Grbl 1.1h ['$' for help]", "GrblHAL 1.1f ['$' or '$HELP' for help]",
  // "Grbl 3.7 [FluidNC v3.7.8 (wifi) '$' for help]". Searched anywhere in the line, because a
  // reset is what the client must never miss, even behind noise.
  const auto g = s.find("Grbl");
  if (g != std::string_view::npos && EndsWith(s, "for help]")) {
    const std::string_view rest = s.substr(g);
    const auto sp = rest.find(' ');
    if (sp != std::string_view::npos) {
      const std::string_view after = rest.substr(sp + 1);
      const auto sp2 = after.find(' ');
      msg.kind = GrblMessageKind::kWelcome;
      msg.name = std::string(rest.substr(0, sp));
      msg.version = std::string(after.substr(0, sp2));
      msg.text = sp2 == std::string_view::npos ? std::string() : std::string(after.substr(sp2 + 1));
      return msg;
    }
  }
  msg.kind = GrblMessageKind::kUnknown;
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

std::string GrblErrorText(int code) {
  switch (code) {
    case 1:
      return "G-code words consist of a letter and a value. Letter was not found.";
    case 2:
      return "Numeric value format is not valid or missing an expected value.";
    case 3:
      return "Grbl '$' system command was not recognized or supported.";
    case 4:
      return "Negative value received for an expected positive value.";
    case 5:
      return "Homing cycle is not enabled via settings.";
    case 6:
      return "Minimum step pulse time must be greater than 3usec.";
    case 7:
      return "EEPROM read failed. Reset and restored to default values.";
    case 8:
      return "Grbl '$' command cannot be used unless Grbl is IDLE.";
    case 9:
      return "G-code locked out during alarm or jog state.";
    case 10:
      return "Soft limits cannot be enabled without homing also enabled.";
    case 11:
      return "Max characters per line exceeded. Line was not processed and executed.";
    case 12:
      return "Grbl '$' setting value exceeds the maximum step rate supported.";
    case 13:
      return "Safety door detected as opened and door state initiated.";
    case 14:
      return "Build info or startup line exceeded EEPROM line length limit.";
    case 15:
      return "Jog target exceeds machine travel. Command ignored.";
    case 16:
      return "Jog command with no '=' or contains prohibited g-code.";
    case 17:
      return "Laser mode requires PWM output.";
    case 20:
      return "Unsupported or invalid g-code command found in block.";
    case 21:
      return "More than one g-code command from same modal group found in block.";
    case 22:
      return "Feed rate has not yet been set or is undefined.";
    case 23:
      return "G-code command in block requires an integer value.";
    case 24:
      return "Two G-code commands that both require the use of the XYZ axis words were "
             "detected in the block.";
    case 25:
      return "A G-code word was repeated in the block.";
    case 26:
      return "A G-code command implicitly or explicitly requires XYZ axis words in the "
             "block, but none were detected.";
    case 27:
      return "N line number value is not within the valid range of 1 - 9,999,999.";
    case 28:
      return "A G-code command was sent, but is missing some required P or L value words "
             "in the line.";
    case 29:
      return "Grbl supports six work coordinate systems G54-G59. G59.1, G59.2, and G59.3 "
             "are not supported.";
    case 30:
      return "The G53 G-code command requires either a G0 seek or G1 feed motion mode to "
             "be active.";
    case 31:
      return "There are unused axis words in the block and G80 motion mode cancel is "
             "active.";
    case 32:
      return "A G2 or G3 arc was commanded but there are no XYZ axis words in the "
             "selected plane to trace the arc.";
    case 33:
      return "The motion command has an invalid target.";
    case 34:
      return "A G2 or G3 arc, traced with the radius definition, had a mathematical error "
             "when computing the arc geometry.";
    case 35:
      return "A G2 or G3 arc, traced with the offset definition, is missing the IJK "
             "offset word in the selected plane to trace the arc.";
    case 36:
      return "There are unused, leftover G-code words that aren't used by any command in "
             "the block.";
    case 37:
      return "The G43.1 dynamic tool length offset command cannot apply an offset to an "
             "axis other than its configured axis.";
    case 38:
      return "Tool number greater than max supported value.";
    default:
      break;
  }
  return "unknown error " + std::to_string(code);
}

std::string GrblAlarmText(int code) {
  switch (code) {
    case 1:
      return "Hard limit triggered. Machine position is likely lost due to sudden and "
             "immediate halt. Re-homing is highly recommended.";
    case 2:
      return "G-code motion target exceeds machine travel. Machine position safely "
             "retained. Alarm may be unlocked.";
    case 3:
      return "Reset while in motion. Grbl cannot guarantee position. Lost steps are "
             "likely. Re-homing is highly recommended.";
    case 4:
      return "Probe fail. The probe is not in the expected initial state before starting "
             "probe cycle.";
    case 5:
      return "Probe fail. Probe did not contact the workpiece within the programmed travel.";
    case 6:
      return "Homing fail. Reset during active homing cycle.";
    case 7:
      return "Homing fail. Safety door was opened during active homing cycle.";
    case 8:
      return "Homing fail. Cycle failed to clear limit switch when pulling off.";
    case 9:
      return "Homing fail. Could not find limit switch within search distance.";
    case 10:
      return "Homing fail. On dual axis machines, could not find the second limit switch "
             "for self-squaring.";
    default:
      break;
  }
  return "unknown alarm " + std::to_string(code);
}

bool GrblAlarmLosesPosition(int code) {
  // 2 (soft limit: the target was refused before any motion) and 4/5 (probe fail: the probe
  // move stops under control) keep the position; everything else, including unknown codes,
  // does not.
  return !(code == 2 || code == 4 || code == 5);
}

}  // namespace gs360
