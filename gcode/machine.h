#pragma once
// The machine a run drives, whatever firmware it speaks: GRBL and grblHAL (gcode/grbl_machine.h)
// or Marlin and Klipper's G-code port (gcode/marlin_machine.h). The run engine talks only to this.
//
// Lines are the engine's own G-code (gcode/probe_program.h): "G21", "G90", "G53 G0|G1 X Y Z [F]",
// "G90 G53 G0 X Y Z", "G4 P<seconds>". Each implementation sends them as its firmware needs (GRBL
// as they are; Marlin without G53, G0 at the rapid rate, the dwell after M400 in milliseconds).
// A line's reply is the firmware's acknowledgement (GRBL: queued; Marlin: processed); the reply
// of "G4 P<s>" comes after every earlier move has ended and the dwell elapsed: the sync point of
// a press.
//
// Positions are machine coordinates in mm (GRBL MPos; Marlin's M114). Times are host steady_clock.
// Expected outcomes are statuses (MachineReply kinds, MachineWaitResult); Connect() throws for
// set-up errors (the firmware's own error type, TransportError). Every method is thread-safe.

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <Eigen/Core>

#include "plan/motion_estimate.h"

namespace gs360 {

// `[machine] firmware`.
enum class MachineFirmware {
  kAuto,    // from what the controller says when the port opens (a GRBL welcome, Marlin's start)
  kGrbl,    // GRBL 1.1, grblHAL, FluidNC
  kMarlin,  // Marlin 2.x, Klipper's G-code pseudo-terminal
};
std::string_view MachineFirmwareName(MachineFirmware firmware);
// "auto", "grbl", "marlin"; nullopt for anything else.
std::optional<MachineFirmware> ParseMachineFirmware(std::string_view name);

enum class MachineReplyKind {
  kOk,            // acknowledged
  kError,         // refused by the firmware (`error`)
  kReset,         // void: the controller reset or rebooted before answering
  kRefused,       // never sent: alarm, halt, reset pending, position not trusted, not connected
  kDisconnected,  // the transport vanished before the reply
  kClosed,        // the machine was closed before the reply
  kTimeout,       // no reply within the wait (the line may still be pending)
};
std::string_view MachineReplyKindName(MachineReplyKind kind);

struct MachineReply {
  MachineReplyKind kind = MachineReplyKind::kTimeout;
  std::string line;
  std::uint64_t sequence = 0;  // 1, 2, ... in Send() order
  // kError: the firmware's words ("error:9 (G-code locked out during alarm or jog state)").
  std::string error;
  int error_code = 0;  // GRBL's N of error:N; 0 for other firmware
  // An alarm that arrived while this line was the oldest unanswered one ("ALARM:2 (...)").
  std::optional<std::string> alarm;
  std::string detail;  // why the line was refused or voided
  std::chrono::steady_clock::time_point received_at{};

  bool Ok() const { return kind == MachineReplyKind::kOk; }
  std::string Describe() const;
};

// A line's future reply. Cheap to copy; all copies see the same reply.
class MachineHandle {
 public:
  // What an implementation waits on.
  struct Source {
    virtual ~Source() = default;
    virtual bool Done() const = 0;
    virtual MachineReply Wait(std::chrono::milliseconds timeout) const = 0;
  };
  MachineHandle() = default;
  explicit MachineHandle(std::shared_ptr<const Source> source) : source_(std::move(source)) {}
  bool Valid() const { return source_ != nullptr; }
  bool Done() const { return source_ && source_->Done(); }
  // The reply, or a kTimeout reply when none arrived within `timeout`.
  MachineReply Wait(std::chrono::milliseconds timeout) const;

 private:
  std::shared_ptr<const Source> source_;
};

enum class MachineState { kUnknown, kIdle, kRun, kHold, kAlarm, kHome, kOther };

struct MachineStatus {
  MachineState state = MachineState::kUnknown;
  std::string state_text;  // as the firmware says it ("Idle", "Hold:0"; Marlin: "Idle", "Run")
  std::optional<Eigen::Vector3d> machine_position;
  std::chrono::steady_clock::time_point received_at{};
};

// kHeld: stopped in a feed hold that only a resume or a reset ends.
enum class MachineWaitResult { kIdle, kTimeout, kAlarm, kDisconnected, kHeld };

struct MachineInfo {
  std::string firmware;     // "Grbl 1.1h", "GrblHAL 1.1f", "Marlin 2.1.2.1 (Jul 13 2023)"
  std::string description;  // one line for the run's events
  // The controller's motion settings, where it reports them (the defaults elsewhere).
  MachineSettings settings;
  bool rates_known = false;        // settings' rates and accelerations are the controller's
  bool travel_known = false;       // settings' travel is the controller's
  std::string rates_source;        // "$110-$112 / $120-$122", "M203 / M201 (M503)"
  std::string travel_source;       // "$130-$132", "M211"
  std::vector<std::string> notes;  // what happened on connect, for the run's events
};

class Machine {
 public:
  virtual ~Machine() = default;

  // Opens the port and learns the controller. The position is not trusted afterwards.
  virtual MachineInfo Connect() = 0;
  // Closes and opens the port again until the controller answers or `timeout` passes.
  virtual bool Reconnect(std::chrono::milliseconds timeout) = 0;
  virtual bool Connected() const = 0;

  // Queues a line (the engine's G-code, see above) and returns its handle at once. Refused
  // (resolved) while alarmed, halted, not connected, and for motion while the position is not
  // trusted. Throws std::invalid_argument for a line that can never be sent.
  virtual MachineHandle Send(std::string_view line) = 0;
  MachineReply WaitForOk(const MachineHandle& handle, std::chrono::milliseconds timeout) const {
    return handle.Wait(timeout);
  }

  // Homing ($H, G28): waits HomingTimeout(). On ok the position is trusted. `lift_mm`: on a
  // machine whose homing moves X and Y first (HomesZFirst() false: Marlin's G28), Z is first
  // raised that far, relative to wherever the tool is (its position may be unknown); GRBL's $H
  // seeks Z first and ignores it.
  virtual MachineReply Home(double lift_mm) = 0;
  virtual bool HomesZFirst() const = 0;
  virtual std::chrono::milliseconds HomingTimeout() const = 0;
  // Leaves an alarm without homing ($X; after a Marlin reboot: nothing to send). The position is
  // not trusted by it.
  virtual MachineReply Unlock() = 0;
  // Voids whatever the controller still holds (GRBL 0x18; Marlin: the port reopened). True when it
  // answers again.
  virtual bool SoftReset() = 0;

  virtual std::optional<MachineStatus> LatestStatus() const = 0;
  // A fresh status (GRBL '?'; Marlin M114, after the lines already queued).
  virtual std::optional<MachineStatus> QueryStatus(std::chrono::milliseconds timeout) = 0;
  // Until every line sent has run and the machine stands still.
  virtual MachineWaitResult WaitIdle(std::chrono::milliseconds timeout) = 0;
  virtual bool Held() const = 0;
  // In alarm (GRBL) or halted (Marlin): nothing runs until it is unlocked, homed or reset.
  virtual bool Alarmed() const = 0;
  // The controller no longer knows where the tool is: in alarm (GRBL), or (Marlin) halted or
  // rebooted since the position was last established (Home(), MarkPositionTrusted()).
  virtual bool PositionLost() const = 0;
  // What the alarm or the loss is ("ALARM:3 (Reset while in motion)", "the printer rebooted:
  // ..."); "" if none.
  virtual std::string AlarmText() const = 0;

  virtual bool PositionTrusted() const = 0;
  // For machines without homing whose operator vouches for the position.
  virtual void MarkPositionTrusted() = 0;
  // Replies that belonged to no line since the controller last restarted: it executed lines the
  // host had counted void, so where it stands cannot be told from what was sent.
  virtual std::uint64_t StrayRepliesSinceWelcome() const = 0;
  // Whether a line or its reply can vanish on the serial line unnoticed (no checksums: GRBL), so
  // that a wait must watch for a controller standing idle with a line unanswered.
  virtual bool RepliesCanBeLost() const = 0;
  // Lines from the controller that could not be read (noise), since Connect().
  virtual std::uint64_t UnreadableLines() const = 0;
};

}  // namespace gs360
