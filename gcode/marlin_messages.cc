#include "gcode/marlin_messages.h"

#include <stdexcept>
#include <string>
#include <vector>

#include "gcode/grbl_messages.h"  // SanitizeGrblLine: printable ASCII, trimmed
#include "gcode/reply_text.h"

namespace gs360 {
namespace {

using reply_text::ParseNumber;
using reply_text::Split;
using reply_text::StartsWith;
using reply_text::Trim;

bool Contains(std::string_view s, std::string_view p) {
  return s.find(p) != std::string_view::npos;
}

// The spaces-separated words of `s`, empty ones left out ("Min:  X0" has two spaces).
std::vector<std::string_view> Words(std::string_view s) {
  std::vector<std::string_view> out;
  for (std::string_view w : Split(s, ' ')) {
    if (!w.empty()) out.push_back(w);
  }
  return out;
}

// "ok", "ok N12 P15 B3", "ok T:..." (anything after "ok " that is not N/P/B is left alone).
MarlinMessage ParseOk(MarlinMessage m, std::string_view rest) {
  m.kind = MarlinMessageKind::kOk;
  for (std::string_view w : Words(rest)) {
    if (w.size() < 2) continue;
    if (w[0] == 'N') m.line = ParseNumber<long>(w.substr(1));
    if (w[0] == 'P') m.planner_free = ParseNumber<int>(w.substr(1));
    if (w[0] == 'B') m.buffer_free = ParseNumber<int>(w.substr(1));
  }
  return m;
}

// "Resend: 12", "Resend:12", "rs N12", "rs 12".
MarlinMessage ParseResend(MarlinMessage m, std::string_view number) {
  number = Trim(number);
  if (!number.empty() && number.front() == 'N') number.remove_prefix(1);
  m.line = ParseNumber<long>(number);
  m.kind = m.line ? MarlinMessageKind::kResend : MarlinMessageKind::kUnknown;
  return m;
}

bool IsHalt(std::string_view text) {
  return Contains(text, "kill() called") || Contains(text, "Printer halted") ||
         Contains(text, "Printer stopped due to errors") || Contains(text, "Shutdown");
}

// "Error:..." (Marlin) or "!! ..." (Klipper).
MarlinMessage ParseError(MarlinMessage m, std::string_view text) {
  m.text = std::string(Trim(text));
  if (IsHalt(text)) {
    m.kind = MarlinMessageKind::kHalted;
    return m;
  }
  // The framing errors name the last line taken; a Resend of the next follows.
  const auto last = text.find("Last Line:");
  if (last != std::string_view::npos) {
    m.kind = MarlinMessageKind::kLineError;
    m.line = ParseNumber<long>(text.substr(last + 10));
    return m;
  }
  m.kind = MarlinMessageKind::kError;
  return m;
}

// "X:10.00 Y:20.00 Z:5.00 E:0.00 Count X:800 Y:1600 Z:2000"; nothing unless X, Y and Z parse.
MarlinMessage ParsePosition(MarlinMessage m, std::string_view line) {
  std::optional<double> axis[3];
  std::optional<double> e;
  bool counts = false;
  // "X:10.00Y:20.00" (older builds leave the spaces out) reads the same once split before each
  // axis letter.
  std::string spaced;
  for (char c : line) {
    if ((c == 'X' || c == 'Y' || c == 'Z' || c == 'E') && !spaced.empty() && spaced.back() != ' ') {
      spaced.push_back(' ');
    }
    spaced.push_back(c);
  }
  for (std::string_view w : Words(spaced)) {
    if (w == "Count") {
      counts = true;
      break;  // the steppers' counts, not a position
    }
    if (w.size() < 3 || w[1] != ':') return m;
    const auto v = ParseNumber<double>(w.substr(2));
    if (!v) return m;
    if (w[0] == 'X') axis[0] = v;
    if (w[0] == 'Y') axis[1] = v;
    if (w[0] == 'Z') axis[2] = v;
    if (w[0] == 'E') e = v;
  }
  if (!axis[0] || !axis[1] || !axis[2]) return m;
  m.kind = MarlinMessageKind::kPosition;
  m.position = Eigen::Vector3d(*axis[0], *axis[1], *axis[2]);
  m.extruder = e;
  m.stepper_counts = counts;
  return m;
}

// "X0.00 Y0.00 Z0.00" after "Min:" or "Max:".
std::optional<Eigen::Vector3d> ParseLimits(std::string_view s) {
  std::optional<double> axis[3];
  for (std::string_view w : Words(s)) {
    if (w.size() < 2) return std::nullopt;
    const int k = w[0] == 'X' ? 0 : w[0] == 'Y' ? 1 : w[0] == 'Z' ? 2 : -1;
    if (k < 0) break;
    axis[k] = ParseNumber<double>(w.substr(1));
    if (!axis[k]) return std::nullopt;
  }
  if (!axis[0] || !axis[1] || !axis[2]) return std::nullopt;
  return Eigen::Vector3d(*axis[0], *axis[1], *axis[2]);
}

// "Soft endstops: On  Min:  X0.00 Y0.00 Z0.00   Max:  X235.00 Y235.00 Z250.00".
MarlinMessage ParseSoftEndstops(MarlinMessage m, std::string_view text) {
  m.kind = MarlinMessageKind::kSoftEndstops;
  m.text = std::string(Trim(text));
  m.enabled = Contains(text, "Soft endstops: On");
  const auto min = text.find("Min:"), max = text.find("Max:");
  if (min != std::string_view::npos) m.soft_min = ParseLimits(text.substr(min + 4));
  if (max != std::string_view::npos) m.soft_max = ParseLimits(text.substr(max + 4));
  return m;
}

// The value of "KEY:" in an M115 line, up to the next " KEY2:" (an upper-case word and a colon).
std::string FirmwareField(std::string_view line, std::string_view key) {
  const auto at = line.find(key);
  if (at == std::string_view::npos) return {};
  std::string_view rest = line.substr(at + key.size());
  for (std::size_t i = 0; i < rest.size(); ++i) {
    if (rest[i] != ' ') continue;
    std::size_t j = i + 1;
    while (j < rest.size() && ((rest[j] >= 'A' && rest[j] <= 'Z') || rest[j] == '_')) ++j;
    if (j > i + 1 && j < rest.size() && rest[j] == ':') return std::string(Trim(rest.substr(0, i)));
  }
  return std::string(Trim(rest));
}

MarlinMessage ParseEcho(MarlinMessage m, std::string_view text) {
  text = Trim(text);
  if (StartsWith(text, "busy:")) {
    m.kind = MarlinMessageKind::kBusy;
    m.text = std::string(Trim(text.substr(5)));
    return m;
  }
  if (StartsWith(text, "Soft endstops:")) return ParseSoftEndstops(m, text);
  m.kind = MarlinMessageKind::kEcho;
  m.text = std::string(text);
  m.unknown_command = StartsWith(text, "Unknown command");
  return m;
}

// Klipper's "// ..." lines: information, or its state when it shut down.
MarlinMessage ParseComment(MarlinMessage m, std::string_view text) {
  text = Trim(text);
  if (StartsWith(text, "Klipper state:") && !Contains(text, "Ready")) {
    m.kind = MarlinMessageKind::kHalted;
    m.text = std::string(text);
    return m;
  }
  m.kind = MarlinMessageKind::kEcho;
  m.text = std::string(text);
  return m;
}

}  // namespace

MarlinMessage ParseMarlinLine(std::string_view line) {
  MarlinMessage m;
  m.raw = SanitizeGrblLine(line);
  const std::string_view s = m.raw;
  if (s.empty()) {
    m.kind = MarlinMessageKind::kEmpty;
    return m;
  }
  if (s == "ok" || StartsWith(s, "ok ")) return ParseOk(std::move(m), s.substr(2));
  if (StartsWith(s, "Resend:")) return ParseResend(std::move(m), s.substr(7));
  if (StartsWith(s, "rs ")) return ParseResend(std::move(m), s.substr(3));
  if (StartsWith(s, "Error:")) return ParseError(std::move(m), s.substr(6));
  if (StartsWith(s, "!!")) return ParseError(std::move(m), s.substr(2));
  if (s == "start") {
    m.kind = MarlinMessageKind::kStart;
    return m;
  }
  if (StartsWith(s, "//action:")) {
    m.kind = MarlinMessageKind::kAction;
    m.text = std::string(Trim(s.substr(9)));
    return m;
  }
  if (StartsWith(s, "echo:")) return ParseEcho(std::move(m), s.substr(5));
  if (StartsWith(s, "//")) return ParseComment(std::move(m), s.substr(2));
  if (StartsWith(s, "FIRMWARE_NAME:")) {
    m.kind = MarlinMessageKind::kFirmware;
    m.text = FirmwareField(s, "FIRMWARE_NAME:");
    m.name = FirmwareField(s, "MACHINE_TYPE:");
    return m;
  }
  if (StartsWith(s, "Cap:")) {
    const auto colon = s.rfind(':');
    m.kind = MarlinMessageKind::kCapability;
    m.name = std::string(s.substr(4, colon - 4));
    m.enabled = s.substr(colon + 1) == "1";
    return m;
  }
  if (StartsWith(s, "T:") || StartsWith(s, "B:")) {
    m.kind = MarlinMessageKind::kTemperature;
    return m;
  }
  if (StartsWith(s, "X:")) return ParsePosition(std::move(m), s);
  return m;
}

int MarlinChecksum(std::string_view text) {
  int sum = 0;
  for (char c : text) sum ^= static_cast<unsigned char>(c);
  return sum;
}

std::string MarlinFrame(long line_number, std::string_view command) {
  const std::string_view bare = Trim(command.substr(0, command.find(';')));
  const auto bad = [&](const std::string& why) {
    throw std::invalid_argument("MarlinFrame: the command \"" + SanitizeGrblLine(command) + "\" " +
                                why);
  };
  if (line_number < 0) bad("has a negative line number " + std::to_string(line_number));
  if (bare.empty()) bad("is empty");
  for (char c : bare) {
    const auto u = static_cast<unsigned char>(c);
    if (u < 0x20 || u > 0x7e) bad("holds a byte that is not printable ASCII");
    if (c == '*') bad("holds '*', which would end it early");
  }
  std::string framed = "N" + std::to_string(line_number) + " " + std::string(bare);
  const int sum = MarlinChecksum(framed);
  return framed + "*" + std::to_string(sum);
}

}  // namespace gs360
