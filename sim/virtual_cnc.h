#pragma once
// The virtual CNC: a GRBL 1.1h controller (or grblHAL, or a Marlin printer) served on a
// pseudo-terminal, for tests, the demo and benchmarks (production code never includes sim/). A host
// opens PtyPath() exactly as it would open /dev/ttyUSB0 and talks the GRBL 1.1 line protocol; the
// machine moves along GRBL's planned trapezoidal profiles in (scaled) real time, and TruePosition()
// tells where the tool really is.
//
// Faithful where a host can tell the difference (gnea/grbl 1.1h protocol.c, serial.c, gcode.c,
// planner.c, limits.c, report.c):
// - An "ISR" thread reads the pty master as bytes arrive. Real-time bytes (`?` `!` `~` 0x18;
//   0x85 jog cancel; other bytes >= 0x80 are discarded) never enter the RX buffer; the others go
//   into a ring of `rx_buffer_bytes` (128) and are DROPPED when it is full.
// - The firmware thread consumes characters only while it is not blocked: a motion line waits
//   for room in the 15-block planner, G4 waits for the planner to empty and then dwells (in
//   50 ms steps, as delay_sec() does), a feed hold suspends it, `$H` blocks it. `ok` is sent
//   when a line is parsed and queued; `error:N` with GRBL's codes; every line terminator counts,
//   so "\r\n" yields a second `ok` (for the empty line), as on the firmware.
// - Welcome `\r\nGrbl 1.1h ['$' for help]` after power-up and every reset, then
//   `[MSG:'$H'|'$X' to unlock]` while in Alarm (homing enabled and `homing_init_lock`: Alarm
//   at power-up).
// - Reset (0x18) while moving (Run, Jog, Home, Hold:1): steppers stop dead, `ALARM:3`
//   (`ALARM:6` while homing) is reported *before* the welcome; a reset in Hold:0 keeps position.
// - Soft limits ($20): the target is checked before queuing; a violation stops motion with a
//   controlled hold, prints `ALARM:2` and `[MSG:Reset to continue]`, then ignores everything but
//   a reset (even `?`, as GRBL 1.1 does); after the reset comes the `ok` of the offending line,
//   the welcome, and Alarm state where G-code gets `error:9` until `$X` or `$H`. Hard limits
//   (injected ALARM:1) behave the same way, with steppers stopped dead.
// - Homing ($H): Z then X+Y, seek / pull-off / locate / pull-off with debounce delays, timed
//   from $24-$27; afterwards MPos is -$27 on each axis homed toward + ($23 bit clear; toward -:
//   -$13x + $27), exactly as a stock GRBL build; 0,0,0 with `homing_force_set_origin`.
//   Soft limits then allow -$13x..0. A pull-off of 0 fails with ALARM:8 and a switch farther
//   than 1.5 x $13x with ALARM:9, as on the firmware. Status requests during homing are
//   answered once homing ends (state Home), as on the firmware.
// - `?` gives `<State|MPos:x,y,z|FS:f,s>` (WPos per $10, `|Bf:` with $10 bit 1), plus `|WCO:`
//   and `|Ov:` at GRBL's refresh cadence when `report_wco_and_overrides`.
// - Positions are reported in whole steps ($100-$102); work offsets (G10 L2/L20, G54-G59, G92)
//   force a buffer sync, as FORCE_BUFFER_SYNC_DURING_WCO_CHANGE does.
// - Bytes cross the "UART" at `baud_rate` in both directions (a status report takes ~5 ms).
//
// G-code: G0 G1 G2 G3 (arcs split into chords by $12), G4, G10 L2/L20, G17-G19, G20/G21,
// G28/G30 (.1), G38.2-G38.5 (no probe is wired: ALARM:5 / ALARM:4 as on a board without one),
// G40, G43.1/G49, G53, G54-G59, G61, G80, G90/G91, G91.1, G92/G92.1, G93/G94, M0 M1 M2 M30,
// M3-M5, M8/M9, F S T N. System: $ $$ $# $G $I $I= $N $Nx= $x= $C $X $H $J= $SLP $RST=.
// Not modelled: feed/rapid/spindle overrides (0x90-0x9D are discarded, Ov stays 100), safety
// door, parking, laser mode, spindle and coolant effects.
//
// Ground truth vs. belief: the machine has a true position (TruePosition, machine frame, mm) and
// the controller's belief (what MPos reports). They agree unless position is lost: a power loss
// (Unplug with power_loss, reset_on_open, PowerCycle) restarts the controller at MPos 0,0,0
// wherever the machine stands, and whatever the interrupted run would still have printed (the
// `ok` of a line cut short, say) is never sent; LosePositionOnReset(true) shifts the belief by a
// random offset whenever the steppers are stopped dead (reset in motion, hard limit, injected
// alarm). Homing restores agreement. The true frame is the machine frame of a correct homing: the
// switches sit one pull-off beyond the homed position (at 0 or -$13x on a stock build).
//
// Board-side faults (the USB link stays up; see the methods for what a host sees):
// - PowerCycle(): the board restarts at once (brown-out, watchdog, a reset button wired to the
//   MCU's RESET line): steppers stop dead, no ALARM is printed, pending output is lost, the
//   controller believes MPos 0,0,0 wherever the tool is, and it boots as at power-up.
// - ResetNow(): GRBL's own reset input (the reset/abort pin of the CNC shield), which runs
//   mc_reset() exactly as 0x18 does: ALARM:3 in motion, nothing at rest (a G4 dwell included).
// - SendRaw(): bytes that reach the host as they are, e.g. replies left over from an earlier
//   session sitting in the pty when a new host opens it.
//
// grblHAL dialect (`firmware = CncFirmware::kGrblHal`), as grblHAL/core (COMPATIBILITY_LEVEL
// 0, its default) behaves in github.com/grblHAL/core: report.c, protocol.c, gcode.c, grbllib.c,
// alarms.h at 04ce2c5c (2023), system.c at 0488a614 and machine_limits.c at 049f0f13 (2025),
// errors.h at 02b45f86, messages.c at 28711ee5:
// - Welcome `\r\nGrblHAL 1.1f ['$' or '$HELP' for help]` (report.c report_init_message()).
// - `$I`: `[VER:1.1f.20240101:<info>]`, `[OPT:VN<flags>,<planner blocks>,<RX bytes>,3,0]`,
//   `[AXS:3:XYZ]`, `[NEWOPT:ENUMS,RT+[,HOME]]`, `[FIRMWARE:grblHAL]` (report.c
//   report_build_info(), extended at level 0). The RX-buffer field stays third.
// - Homing lock ($22 bit 2, `homing_init_lock`): while homing is enabled and the machine has not
//   been homed since power-up (or since position was lost), every boot and reset raises `ALARM:11`
//   (printed once while it lasts, system_raise_alarm() prints only a change) then `[MSG:Homing
//   cycle required]` (protocol.c protocol_main_loop(), machine_limits.c limits_homing_required());
//   `$X` is refused with `error:46` and the Alarm stays (system.c disable_lock()); only `$H`
//   unlocks. G-code gets `error:9` meanwhile (alarm lock), never error:46: gcode.c has no homing
//   check for motion. Homed status survives a reset at rest and is lost when the steppers stop dead
//   (reset in motion, hard limit, injected alarm: mc_reset() sets sys.position_lost, and grbllib.c
//   grbl_enter() then clears sys.homed).
// - Line endings: the second character of a "\r\n" (or "\n\r") pair is not an empty line, so
//   "\r\n" gets one reply, not two (protocol.c: "do not process as empty line if part of crlf").
// - Error latch: after a G-code line fails, every following G-code line is answered with the
//   same error:N WITHOUT being executed, until an empty line, a `$` command (which sets the
//   latch to its own status) or a reset (protocol.c: `gc_state.last_error == Status_OK`).
// Not modelled for grblHAL: its longer lines (LINE_BUFFER_SIZE), its extra status fields
// (|Pn:, |H:, ...), $$ (GRBL 1.1's list is printed, $22 as 0/1), $HELP and the other new `$`
// commands, board-specific $I lines ([DRIVER:], [BOARD:], [NVS STORAGE:]), tool change, soft
// limits on homed axes only (machine_limits.c check_travel_limits(): they apply to all here).
//
// Marlin dialect (`firmware = CncFirmware::kMarlin`), a 3D printer as Marlin 2.1 drives one
// (MarlinFirmware/Marlin src/gcode/queue.cpp, gcode.cpp, feature/e_parser.h, module/motion.cpp),
// sharing the serial side, the planner, the clock, the ground truth and the faults above:
// - Boot: `start`, then a few `echo:` lines; no alarm, no homing lock: Idle, believing 0,0,0
//   wherever the tool stands. Output with no host attached is lost (a USB-serial bridge drops it),
//   reset_on_open or not: a host sees `start` only when the board boots while it listens. A reboot
//   (PowerCycle, reset_on_open, unplug with power loss) is the only reset: ResetNow() and
//   ResetDuringNextDwell() reboot the board (its reset pin is the MCU's).
// - Lines end at '\n' or '\r'; empty lines are skipped without a reply; `;` starts a comment.
//   A line starting `N<n>` must be the last number + 1 (M110 excepted) and end in `*<checksum>`
//   (XOR of the bytes before '*'): otherwise `Error:Line Number is not Last Line Number+1, Last
//   Line: <n>` / `Error:checksum mismatch, Last Line: <n>` / `Error:No Checksum with line number,
//   Last Line: <n>`, the bytes waiting in the RX buffer are discarded, then `Resend: <n+1>` and
//   `ok`. A checksum without a number: `Error:No Line Number with checksum, Last Line: <n>`.
// - `ok` once a command has been processed: a move once it is in the planner (waiting for room),
//   G4 and M400 once every move has ended (and the dwell elapsed), G28 once homed. Blocking
//   commands print `echo:busy: processing` every keepalive_s (machine time).
// - G0/G1 X Y Z E F (F modal, mm/min, shared by G0 and G1, 1500 at boot; clamped by the axes'
//   $110-$112), G4 P<ms>/S<s>, G21, G28 [X Y Z] (each axis in turn X, Y, Z toward its minimum
//   endstop, which sits at true 0, at $25 then $24 after a bump back of 2 mm; more than 1.5 x
//   $13x away: `Error:Homing Failed`, then halted as kill()), G90/G91, M17/M18/M84 and M82/M83
//   (acknowledged, no effect: the steppers stay on), M105 (`ok T:..`), M110 N, M114 (`X:.. Y:..
//   Z:.. E:.. Count X:.. Y:.. Z:..`, the planned position, 2 decimals), M114 R (the steppers'
//   position, 3 decimals) with m114_realtime, M115 (FIRMWARE_NAME, Cap: lines), M154 S<s> with
//   auto_report_position, M155 S<s> (temperature reports `T:.. /.. B:.. /.. @:0 B@:0`), M211
//   [S0|S1] (`echo:Soft endstops: On  Min:  X.. Y.. Z..   Max:  X.. Y.. Z..`: 0..$13x), M400, M503
//   (M92 M203 M201 M204 M205 lines from the settings). Heating (M104 M109 M140 M190) is
//   acknowledged and does nothing. Anything else: `echo:Unknown command: "<line>"`, then ok.
// - Soft endstops clamp a move's target into 0..$13x on homed axes, without a message.
// - Emergency parser: `M112`, `M410`, `M108` act as their bytes arrive, ahead of the queue (the
//   line itself is then acknowledged as a no-op). M112: the steppers stop dead, `Error:Printer
//   halted. kill() called!`, and the board ignores everything until it reboots. M410: every
//   planned move is dropped and the steppers stop dead where they are (position kept).
// - RaiseAlarmDuringNextMove() halts the printer as kill() does (a thermal runaway, a driver
//   fault): steppers stopped dead, the kill message, nothing more until a reboot. FeedHoldPin()
//   does nothing (a printer has no hold input).
// Not modelled for Marlin: the command ring read ahead while a command runs (lines are taken one
// at a time from the RX buffer), ADVANCED_OK, G2/G3, G92 and workspace offsets, bed levelling,
// temperatures that change, M999, host prompts, SD cards, parenthesised comments.
//
// Thread-safe: every public method may be called from any thread.

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "sim/grbl_planner.h"
#include "sim/grbl_settings.h"

namespace gs360 {

enum class GrblState { kIdle, kRun, kHold, kJog, kAlarm, kDoor, kCheck, kHome, kSleep };
// "Idle", "Run", "Hold", ... (without sub-state).
const char* GrblStateName(GrblState state);

// Which firmware the virtual controller speaks.
enum class CncFirmware {
  kGrbl11h,  // gnea/grbl 1.1h
  kGrblHal,  // grblHAL core, COMPATIBILITY_LEVEL 0 (see the header comment)
  kMarlin,   // Marlin 2.1 on a 3D printer (see the header comment)
};

// The virtual printer's Marlin build (only with firmware = kMarlin).
struct VirtualMarlinOptions {
  // HOST_KEEPALIVE_FEATURE: "echo:busy: processing" every this many machine seconds while a
  // command blocks (G28, G4, M400, a full planner); 0: off.
  double keepalive_s = 2.0;
  bool m114_realtime = true;         // M114_REALTIME: `M114 R` reports the steppers' position
  bool auto_report_position = true;  // AUTO_REPORT_POSITION: M154 (Cap:AUTOREPORT_POS)
  // Temperature auto-report interval at boot (as after `M155 S<n>`), machine seconds; 0: off.
  double temperature_report_s = 0.0;
  bool soft_endstops = true;  // M211 state at boot (travel 0..$13x on each homed axis)
  std::string machine_type = "Virtual Ender-3";

  void Check() const;  // throws std::invalid_argument naming the field and its value
};

struct VirtualCncOptions {
  // Machine seconds per wall second: 1 = real time, 20 = twenty times faster. 0 = instant:
  // motion and dwells complete at once, ordering and replies unchanged.
  double time_scale = 1.0;
  int rx_buffer_bytes = 128;  // reported in $I [OPT:V,15,128]
  // Serial line speed: bytes enter and leave the controller's UART at baud/10 bytes per second
  // (a 128-byte burst takes 11 ms at 115200), so the firmware consumes lines while they
  // arrive, as on a real board. 0 = no pacing (a whole chunk lands at once).
  int baud_rate = 115200;
  int planner_blocks = 15;
  GrblSettings settings;  // the EEPROM at power-up; also what $RST=$ restores
  CncFirmware firmware = CncFirmware::kGrbl11h;
  VirtualMarlinOptions marlin;  // firmware = kMarlin
  // HOMING_INIT_LOCK (a GRBL 1.1h build option, on in the stock build; grblHAL's $22 bit 2):
  // with homing enabled the controller boots into Alarm (grblHAL: ALARM:11 until homed).
  // Without it, it boots Idle and `$I` shows `L` in [OPT:].
  bool homing_init_lock = true;
  // GRBL's HOMING_FORCE_SET_ORIGIN build option (`Z` in [OPT:]): homing leaves MPos at 0 on
  // each axis instead of the pull-off position, and an axis homed toward - travels 0..+$13x.
  bool homing_force_set_origin = false;
  // True machine position at power-up (the controller believes 0,0,0).
  Eigen::Vector3d initial_true_position = Eigen::Vector3d::Zero();
  // If set, a symlink kept pointing at the current pty slave (removed while unplugged).
  std::string symlink_path;
  // Arduino-style auto-reset: the controller power-cycles when a host opens the port, and
  // output sent while no host has the port open is lost. Without it, such output (the
  // power-up welcome, say) waits in the pty for the next host to open the port.
  bool reset_on_open = false;
  // Wall time from power-up to the welcome line (a bootloader's delay).
  std::chrono::milliseconds boot_delay{0};
  // `|WCO:` / `|Ov:` fields in status reports at GRBL's cadence (default build).
  bool report_wco_and_overrides = true;
  // Largest per-axis belief error (mm) when position is lost (LosePositionOnReset).
  double lost_position_max_mm = 0.5;
  // Executed motion pieces kept for TruePosition(), and in instant mode as many jumps of the
  // machine clock (one per executed motion batch and per 50 ms dwell step, as GRBL's
  // DWELL_TIME_STEP; VirtualCncStats::clock_jumps counts them). Older times throw
  // std::out_of_range once either was evicted.
  std::size_t history_pieces = 1u << 15;
  std::uint64_t seed = 1;  // fault-injection randomness

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

enum class FaultDirection { kHostToCnc, kCncToHost, kBoth };

struct UnplugOptions {
  // The controller loses power with the cable (USB-powered Arduino): motion stops dead, and
  // at replug it boots again (welcome, Alarm with homing enabled, MPos 0,0,0).
  bool power_loss = true;
  // Re-create the pty (under a new path) after this wall time; otherwise call Replug().
  std::optional<std::chrono::milliseconds> replug_after;
};

struct VirtualCncStats {
  std::uint64_t bytes_from_host = 0;      // read from the pty (before injected faults)
  std::uint64_t rx_overflow_dropped = 0;  // lost because the RX buffer was full
  std::uint64_t injected_drops = 0;       // both directions
  std::uint64_t injected_garbles = 0;     // both directions
  std::uint64_t lines = 0;                // lines executed (ok or error)
  std::uint64_t dwells = 0;               // G4 dwells begun (a probe's press has one)
  std::uint64_t errors = 0;
  std::uint64_t alarms = 0;
  std::uint64_t resets = 0;  // soft resets (0x18 and internal)
  std::uint64_t boots = 0;   // power-ups
  std::uint64_t blocks_planned = 0;
  std::uint64_t clock_jumps = 0;  // instant mode: machine-clock jumps recorded so far
  std::uint64_t unheard = 0;      // replies lost because no host had the port open (reset_on_open)
  std::uint64_t keepalives = 0;   // Marlin: "echo:busy: processing" lines sent
};

class VirtualCnc {
 public:
  using Clock = std::chrono::steady_clock;

  // Checks the options, opens the pty (and symlink) and starts the threads; the welcome line is
  // sent once `boot_delay` has passed. Throws std::invalid_argument for bad options and
  // std::runtime_error when the pty or symlink cannot be created.
  explicit VirtualCnc(const VirtualCncOptions& options = VirtualCncOptions());
  ~VirtualCnc();
  VirtualCnc(const VirtualCnc&) = delete;
  VirtualCnc& operator=(const VirtualCnc&) = delete;

  // Stops the threads, closes the pty, removes the symlink. Idempotent.
  void Stop();

  // The pty slave path a host opens ("" while unplugged).
  std::string PtyPath() const;
  const VirtualCncOptions& options() const;

  // --- Ground truth ---
  // Tool position (true machine frame, mm) at a steady_clock instant: exact interpolation of the
  // executed profile for the past (as far back as the kept history), the current plan's
  // prediction for the future. Throws std::out_of_range for an instant older than the kept
  // history (history_pieces); so do TrueSpeed, TrueTrajectory and MachineTime.
  Eigen::Vector3d TruePosition(Clock::time_point t) const;
  Eigen::Vector3d TruePositionNow() const { return TruePosition(Clock::now()); }
  double TrueSpeed(Clock::time_point t) const;  // mm/s
  // Executed motion pieces overlapping [from, to] (machine-time fields; see MachineTime()).
  std::vector<MotionPiece> TrueTrajectory(Clock::time_point from, Clock::time_point to) const;
  // Machine seconds since start at a wall instant (scaled; jumps in instant mode).
  double MachineTime(Clock::time_point t) const;
  // What MPos would report now (the controller's belief, in whole steps).
  Eigen::Vector3d ReportedPosition() const;
  GrblState State() const;
  GrblSettings Settings() const;
  int PlannerBlocksQueued() const;
  int RxBufferUsed() const;
  VirtualCncStats Stats() const;

  // --- Fault injection ---
  // Lose the next n bytes on the wire in `direction`.
  void DropNextBytes(std::size_t n, FaultDirection direction = FaultDirection::kHostToCnc);
  // Lose each byte with probability p (seeded), until set back to 0.
  void SetDropProbability(double p, FaultDirection direction = FaultDirection::kHostToCnc);
  // Flip one random bit (of the low 7) in each of the next n bytes.
  void GarbleNextBytes(std::size_t n, FaultDirection direction = FaultDirection::kHostToCnc);
  // Hold every byte to the host for `duration` (wall time); nothing is lost.
  void StallReplies(std::chrono::milliseconds duration);
  // USB unplug: closes the pty (a host sees EOF / EIO), drops pending output.
  void Unplug(const UnplugOptions& options = UnplugOptions());
  // The device comes back under a NEW pty path (PtyPath() and the symlink follow). Throws
  // std::runtime_error if the pty cannot be created. No effect when plugged.
  void Replug();
  bool Plugged() const;
  // Whether a host has the port open (as the I/O thread last saw it: a close is noticed within
  // a poll interval). Lets a test wait for the controller to see a host come or go.
  bool HostAttached() const;
  // The next queued motion block stops dead after covering `fraction` of its length and the
  // controller raises ALARM:code. Codes 1 and 2 are critical events (reset required); other
  // codes are followed by an automatic reset (welcome), as an abort is.
  void RaiseAlarmDuringNextMove(int alarm_code, double fraction);
  // While true, every dead stop (reset in motion, hard limit, injected alarm) also shifts the
  // controller's belief by up to `lost_position_max_mm` per axis.
  void LosePositionOnReset(bool lose);

  // --- Board-side faults (the USB link stays up, PtyPath() unchanged) ---
  // The board restarts now (brown-out, watchdog, reset button on the MCU's RESET line), as
  // Unplug(power_loss) + Replug() and reset_on_open do, without the link going away: motion
  // stops dead where it is (no ALARM line), output not yet sent is lost, lines in flight get no
  // reply, and after `boot_delay` the host reads the welcome of a fresh power-up: MPos 0,0,0
  // wherever the tool stands, Alarm with homing enabled (and homing_init_lock), settings kept.
  // No effect while unpowered (unplugged with power loss).
  void PowerCycle();
  // GRBL's reset input pin (or anything acting as 0x18): mc_reset() as for a received 0x18, so
  // a host sees what a soft reset gives: in motion (Run, Jog, Home, Hold:1) the steppers stop
  // dead, `ALARM:3` (homing: ALARM:6) then the welcome and the Alarm unlock message; position is
  // then lost (belief shifted with LosePositionOnReset, else MPos = where the steppers stopped).
  // At rest (Idle, Hold:0, a G4 dwell: the planner is empty) no alarm and position kept: the
  // line being executed completes with its `ok` (a dwell is cut short), then the welcome; lines
  // still in the RX buffer are discarded and never answered. No effect while unpowered.
  void ResetNow();
  // ResetNow() at the start of the next G4 dwell the controller executes (the planner just
  // emptied, the tool at rest where the motion before it ended: at the bottom of a press).
  void ResetDuringNextDwell();
  // GRBL's feed-hold input pin (a hold button on the machine): as a received '!'.
  void FeedHoldPin();
  // The next `ok` or `error:N` reply is never sent (noise destroyed it; the line was executed);
  // `instead` is sent in its place (what noise left of it: "" for nothing).
  void LoseNextReply(const std::string& instead = "");
  // The controller sends `bytes` to the host as they are (paced, and subject to the CncToHost
  // faults, like any output). Without reset_on_open, bytes sent while no host has the port open
  // wait in the pty and are the first thing the next host reads (stale "ok", "error:9" or
  // status reports from an earlier session); with reset_on_open they are lost, like all output
  // with nobody listening. Dropped while unplugged or unpowered.
  void SendRaw(const std::string& bytes);
  // Bytes the controller has produced but not yet written into the pty (0 once all output,
  // SendRaw's included, is readable by a host or waits in the pty for one).
  std::size_t PendingOutputBytes() const;

 private:
  class Impl;
  std::unique_ptr<Impl> impl_;
};

// `gs360 sim-cnc`: starts a VirtualCnc, prints the pty path on the first line of stdout (and
// the symlink on the second when configured), serves until SIGINT or SIGTERM, then stops.
// Returns 0. Throws what the VirtualCnc constructor throws.
int RunVirtualCncForeground(const VirtualCncOptions& options);

}  // namespace gs360
