#pragma once
// The serial protocol of Marlin 2.x printers (and Klipper's G-code pseudo-terminal, which speaks
// the same): framing a command with its line number and checksum, and parsing every reply kind
// a host meets. Parsing never throws: a line not understood is kUnknown with its text kept, so
// garbage on the line is logged and skipped. Positions in the firmware's units (mm), the
// printer's own coordinates. Nothing here sends or times anything: that is the client's.

#include <optional>
#include <string>
#include <string_view>

#include <Eigen/Core>

namespace gs360 {

enum class MarlinMessageKind {
  kOk,            // "ok", "ok N12 P15 B3" (ADVANCED_OK), "ok T:20.0 /0.0 ..." (M105's answer)
  kResend,        // "Resend: 12", "rs N12", "rs 12": send again from `line` on
  kLineError,     // "Error:checksum mismatch, Last Line: 11" and the other framing errors: the
                  // line was dropped and a Resend follows; `line` = the last line it took
  kError,         // any other "Error:..." or Klipper's "!! ...": `text`
  kHalted,        // "Error:Printer halted. kill() called!", "...stopped due to errors...",
                  // Klipper's shutdown: nothing moves until the printer is reset (M999/restart)
  kBusy,          // "echo:busy: processing" (a keep-alive while a long command runs), "paused"
  kStart,         // "start": the board (re)booted; everything in flight is void
  kEcho,          // "echo:..." and Klipper's "// ...": `text`; unknown_command when it says so
  kAction,        // "//action:pause" and the like (a host action request): `text`
  kTemperature,   // " T:20.00 /0.00 B:20.00 /0.00 @:0" (an auto-report; nothing here heats)
  kPosition,      // "X:10.00 Y:20.00 Z:5.00 E:0.00 Count X:800 Y:1600 Z:2000" (M114, M154)
  kFirmware,      // "FIRMWARE_NAME:Marlin 2.1.2 (...) SOURCE_CODE_URL:... MACHINE_TYPE:..." (M115)
  kCapability,    // "Cap:AUTOREPORT_POS:1" (M115): `name`, `enabled`
  kSoftEndstops,  // "echo:Soft endstops: On  Min: X0.00 Y0.00 Z0.00  Max: X235.00 ..." (M211)
  kEmpty,         // nothing printable
  kUnknown,       // anything else, kept in `raw`
};

struct MarlinMessage {
  MarlinMessageKind kind = MarlinMessageKind::kUnknown;
  std::string raw;  // the line, printable ASCII only, trimmed
  // kOk: the line number acknowledged (ADVANCED_OK); kResend: the line to send again from;
  // kLineError: the last line the printer took.
  std::optional<long> line;
  std::optional<int> planner_free, buffer_free;  // kOk with ADVANCED_OK: "P15 B3"
  std::string text;  // kError, kHalted, kBusy, kEcho, kAction: the message; kFirmware: the name
  bool unknown_command = false;  // kEcho: "echo:Unknown command: ..."
  // kPosition: X, Y, Z (and E when given); `stepper_counts`: the report went on to "Count"
  // (M114's planned position followed by the steppers'; M114 R and M154 give only the first).
  std::optional<Eigen::Vector3d> position;
  std::optional<double> extruder;
  bool stepper_counts = false;
  std::string name;      // kCapability: "AUTOREPORT_POS"; kFirmware: MACHINE_TYPE if given
  bool enabled = false;  // kCapability's value, kSoftEndstops' On/Off
  std::optional<Eigen::Vector3d> soft_min, soft_max;  // kSoftEndstops
};

// Parses one line (without its terminator; a trailing '\r' is dropped as noise). Never throws.
MarlinMessage ParseMarlinLine(std::string_view line);

// The XOR of every byte of `text`: what Marlin compares with the number after '*'.
int MarlinChecksum(std::string_view text);

// `command` as Marlin takes it with error checking: "N<line_number> <command>*<checksum>", the
// command's comment (from ';') and surrounding spaces dropped. Throws std::invalid_argument
// naming the command for one that is empty after that, holds '*' or a byte that is not
// printable ASCII, or a negative line number.
std::string MarlinFrame(long line_number, std::string_view command);

}  // namespace gs360
