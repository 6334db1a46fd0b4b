#pragma once
// A Marlin 2.x printer (or Klipper's G-code pseudo-terminal) over a transport: connecting (a board
// that reboots when the port opens is waited for, never streamed into while it boots), one line
// at a time with line numbers, checksums, resends and retries (gcode/marlin_stream.h), and the
// position after the machine has stopped (M400, then M114, or M114 R where the firmware has it).
// Nothing that heats is ever sent. Synchronous: each call returns when its line is answered or
// throws; one thread at a time. Positions in the printer's own coordinates, mm.

#include <chrono>
#include <map>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "gcode/grbl_messages.h"  // GrblLineSplitter: lines from a byte stream
#include "gcode/marlin_messages.h"
#include "gcode/marlin_stream.h"
#include "gcode/transport.h"

namespace gs360 {

// The printer halted or rebooted, or stopped answering: what was in flight may or may not have
// run, and nothing moves again until the position is verified. what() says which and what to do.
class MarlinError : public std::runtime_error {
 public:
  enum class Kind { kHalted, kRebooted, kTimeout, kProtocol };
  MarlinError(Kind kind, const std::string& what) : std::runtime_error(what), kind_(kind) {}
  Kind kind() const { return kind_; }

 private:
  Kind kind_;
};

struct MarlinClientOptions {
  // After opening the port: how long to wait for a board that reboots on open (DTR) to print
  // "start", and then for its boot messages to end (no line for boot_quiet).
  std::chrono::milliseconds boot_timeout{3000};
  std::chrono::milliseconds boot_quiet{300};
  // No reply at all (not even "echo:busy:") for this long: the line is written again.
  std::chrono::milliseconds reply_timeout{3000};
  int max_retries = 4;  // of one line, then MarlinError kTimeout
  void Check() const;   // throws std::invalid_argument naming the field and value
};

struct MarlinInfo {
  bool rebooted_on_open = false;             // "start" came after the port opened
  std::string firmware;                      // M115 FIRMWARE_NAME, e.g. "Marlin 2.1.2.1 (...)"
  std::string machine_type;                  // M115 MACHINE_TYPE (may be empty)
  std::map<std::string, bool> capabilities;  // M115 "Cap:NAME:0/1"
  bool soft_endstops = false;                // M211
  std::optional<Eigen::Vector3d> soft_min, soft_max;
  bool Has(const std::string& capability) const;
};

// What the printer said while a line ran, besides its ok.
struct MarlinReply {
  std::vector<MarlinMessage> messages;  // echoes, reports, positions, errors (in order)
  int busy = 0;                         // "echo:busy:" keep-alives
};

class MarlinClient {
 public:
  MarlinClient(std::unique_ptr<Transport> transport, const MarlinClientOptions& options = {});

  // Waits out a reboot on open, starts the numbering (M110 N0), asks M115 and M211. Throws
  // MarlinError (and TransportError from the transport).
  MarlinInfo Connect();
  const MarlinInfo& Info() const { return info_; }

  // Sends one command and waits for its ok (resending and retrying as the stream says); the
  // command is refused (std::invalid_argument) when it would heat (M104 M109 M140 M190 M141 M191)
  // or cannot be framed. `timeout`: how long it may run with busy keep-alives. Throws MarlinError.
  MarlinReply Execute(std::string_view command, std::chrono::milliseconds timeout);
  // The position once every move has ended: M400, then M114 (`real`: M114 R, the steppers' own
  // position, on firmware built with M114_REALTIME; M115 does not tell). Throws MarlinError
  // kProtocol when the answer holds no position.
  Eigen::Vector3d StoppedPosition(std::chrono::milliseconds timeout, bool real = false);
  // M112, unnumbered (the emergency parser takes it as it arrives, ahead of the queue).
  void EmergencyStop();

  const MarlinStream& Stream() const { return stream_; }

 private:
  // Reads for at most `wait`: the next complete reply line, or nothing.
  std::optional<MarlinMessage> ReadLine(std::chrono::milliseconds wait);
  void WriteLine(const std::string& line);
  // After "start": waits for the boot to go quiet, dropping what arrives, then numbers anew.
  void AwaitBootEnd();

  std::unique_ptr<Transport> transport_;
  MarlinClientOptions options_;
  MarlinStream stream_;
  MarlinInfo info_;
  GrblLineSplitter splitter_;
  std::vector<std::string> lines_;  // split, not yet read
};

}  // namespace gs360
