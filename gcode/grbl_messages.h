#pragma once
// Parsing of every GRBL 1.1 message kind (gnea/grbl doc/markdown/interface.md), plus the human
// text of GRBL's error and alarm codes. Parsing never throws: a line that is not understood is
// returned as kUnknown with its text kept, so garbage on the serial line can be logged and
// skipped without desynchronising the stream. Positions are in the firmware's report units
// (mm unless $13=1), machine frame for MPos.

#include <array>
#include <cstddef>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include <Eigen/Core>

namespace gs360 {

enum class GrblMessageKind {
  kOk,                  // "ok": the line was parsed and queued (not executed)
  kError,               // "error:N": the line was discarded; code = N (-1 if not a number)
  kAlarm,               // "ALARM:N": the machine entered the alarm state; code = N
  kWelcome,             // "Grbl 1.1h ['$' for help]": a (re)start; everything in flight is void
  kStatus,              // "<Idle|MPos:...|...>": status report (answer to '?')
  kMessage,             // "[MSG:text]": non-queried feedback
  kGcState,             // "[GC:G0 G54 ...]": $G parser state
  kHelp,                // "[HLP:...]": $ help
  kVersion,             // "[VER:1.1h.20190830:string]": $I build info
  kOptions,             // "[OPT:V,15,128]": $I compile options, planner blocks, RX buffer bytes
  kEcho,                // "[echo:G1X0...]": line echo (compile option)
  kParameter,           // "[G54:x,y,z]", "[G28:...]", "[G92:...]", "[TLO:z]", "[PRB:x,y,z:1]"
  kFeedback,            // any other "[NAME:...]" (grblHAL / FluidNC extensions)
  kSetting,             // "$110=500.000": a setting value ($$ printout)
  kStartupLineSetting,  // "$N0=G54": a stored startup line ($N printout)
  kStartupLineResult,   // ">G54G20:ok" / ">G54G20:error:N": a startup line was executed
  kEmpty,               // blank line (nothing printable)
  kUnknown,             // anything else, kept in `raw`
};

enum class GrblMachineState {
  kUnknown,
  kIdle,
  kRun,
  kHold,
  kJog,
  kAlarm,
  kDoor,
  kCheck,
  kHome,
  kSleep,
  kTool
};

struct GrblStatusReport {
  GrblMachineState state = GrblMachineState::kUnknown;
  std::string state_text;                       // as reported, e.g. "Hold"
  int substate = -1;                            // "Hold:0" -> 0; -1 when absent
  std::optional<Eigen::Vector3d> mpos;          // machine position (x, y, z)
  std::optional<Eigen::Vector3d> wpos;          // work position
  std::optional<Eigen::Vector3d> wco;           // work coordinate offset: WPos = MPos - WCO
  int axis_count = 0;                           // position values reported (3 on a 3-axis machine)
  std::optional<double> feed;                   // current feed rate (mm/min with $13=0)
  std::optional<double> spindle;                // spindle speed (rpm), FS field only
  std::optional<int> planner_blocks_free;       // Bf first value
  std::optional<int> rx_bytes_free;             // Bf second value
  std::optional<long> line_number;              // Ln
  std::optional<std::array<int, 3>> overrides;  // Ov: feed, rapid, spindle (percent)
  std::string pins;                             // Pn letters, e.g. "PZ"
  std::string accessories;                      // A letters, e.g. "SF"
  std::vector<std::pair<std::string, std::string>> other_fields;  // unrecognised, kept

  // MPos if reported, else WPos + WCO using this report's WCO or `last_wco` (WCO appears only
  // in some reports). nullopt when neither works.
  std::optional<Eigen::Vector3d> MachinePosition(
      const std::optional<Eigen::Vector3d>& last_wco = std::nullopt) const;
};

struct GrblMessage {
  GrblMessageKind kind = GrblMessageKind::kUnknown;
  std::string raw;      // the line, sanitised (printable ASCII only, trimmed)
  int code = 0;         // kError / kAlarm code; kStartupLineResult: 0 = ok, else the error code
  std::string name;     // [NAME:...] name (kParameter, kFeedback); kWelcome: firmware ("Grbl")
  std::string text;     // payload: MSG/GC/HLP/echo/feedback text, startup line, setting value,
                        // VER build string, welcome rest of line
  std::string version;  // kWelcome "1.1h"; kVersion "1.1h.20190830"
  int setting = -1;     // kSetting: $N; kStartupLineSetting: N of $NN=
  std::optional<double> setting_value;  // kSetting: numeric value when it is a number
  std::vector<double> values;           // kParameter values
  std::optional<bool> probe_success;    // kParameter PRB
  std::string option_codes;             // kOptions: the letter codes ("V")
  std::optional<int> planner_blocks;    // kOptions: planner blocks (15 on classic GRBL)
  std::optional<int> rx_buffer_bytes;   // kOptions: serial RX buffer (128; grblHAL 1024)
  GrblStatusReport status;              // kStatus
};

// Parses one line (without its line terminator; a trailing '\r' is tolerated). Never throws.
GrblMessage ParseGrblLine(std::string_view line);

// Keeps printable ASCII (0x20..0x7e) and trims spaces: noise bytes around a reply are dropped.
std::string SanitizeGrblLine(std::string_view bytes);

// Splits a byte stream into lines at '\n' or '\r'. Blank lines are skipped. A line longer than
// kMaxLine bytes is garbage: it is cut and delivered as one (unknown) line, the rest up to the
// next terminator discarded, so a flood without newlines cannot grow memory.
class GrblLineSplitter {
 public:
  static constexpr std::size_t kMaxLine = 1024;
  // Appends completed lines to `lines`.
  void Feed(const char* data, std::size_t n, std::vector<std::string>* lines);
  void Clear() {
    partial_.clear();
    discarding_ = false;
  }
  std::size_t OverlongLines() const { return overlong_; }

 private:
  std::string partial_;
  bool discarding_ = false;
  std::size_t overlong_ = 0;
};

std::string_view GrblMachineStateName(GrblMachineState state);
std::string_view GrblMessageKindName(GrblMessageKind kind);
// The text of "error:N": GRBL 1.1's table (gnea/grbl doc/csv/error_codes_en_US.csv) extended by
// grblHAL's (grblHAL/core errors.c and plugins: 18-19, 39-58, 60-66, 70-84, 253). GRBL 1.1's
// wording wins where both define a code. Otherwise "unknown error N (not in the GRBL 1.1 or grblHAL
// tables)".
std::string GrblErrorText(int code);
// The text of "ALARM:N": GRBL 1.1's table (doc/csv/alarm_codes_en_US.csv, 1-10) extended by
// grblHAL's (grblHAL/core alarms.c, 11-18). Alarm 10 differs: GRBL 1.1 dual-axis homing fail,
// grblHAL E-stop; GRBL 1.1's text is given. Otherwise "unknown alarm N (not in the ... tables)".
std::string GrblAlarmText(int code);
// True for alarms after which the machine position cannot be trusted and the machine must be
// re-homed: every alarm (GRBL 1.1 and grblHAL, unknown codes too) except 2 (soft limit, position
// retained) and 4/5 (probe fail, no sudden halt).
bool GrblAlarmLosesPosition(int code);

}  // namespace gs360
