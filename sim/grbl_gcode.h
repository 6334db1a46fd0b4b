#pragma once
// GRBL 1.1's g-code parser (gnea/grbl gcode.c, steps 1-3: import the words, error-check them,
// pre-compute targets) as a pure function, for the virtual CNC. Execution (step 4: planner,
// dwell, offsets) is the virtual CNC's job; GcodeBlock carries what it needs.
//
// Input lines are what GRBL's protocol layer hands the parser: spaces, control characters and
// comments removed, letters upper-cased, at most 79 characters. Positions are machine
// coordinates in mm (inch words are converted); feed rates in mm/min.

#include <array>
#include <cstddef>
#include <string>
#include <string_view>
#include <vector>

#include <Eigen/Core>

namespace gs360 {

// GRBL's read_float(): optional sign, digits with at most one '.', no exponent. Advances `pos`
// past the number and returns true, or returns false (bad number) leaving `pos` unspecified.
bool ReadGrblFloat(std::string_view line, std::size_t& pos, double& value);

// Motion modes as GRBL numbers them.
enum GcodeMotion : int {
  kMotionSeek = 0,                  // G0
  kMotionLinear = 1,                // G1
  kMotionCwArc = 2,                 // G2
  kMotionCcwArc = 3,                // G3
  kMotionNone = 80,                 // G80
  kMotionProbeToward = 140,         // G38.2
  kMotionProbeTowardNoError = 141,  // G38.3
  kMotionProbeAway = 142,           // G38.4
  kMotionProbeAwayNoError = 143,    // G38.5
};

// Non-modal commands as GRBL numbers them (G28.1 = 38, G30.1 = 40, G92.1 = 102).
enum GcodeNonModal : int {
  kNonModalNone = 0,
  kNonModalDwell = 4,
  kNonModalSetCoordinateData = 10,
  kNonModalGoHome0 = 28,
  kNonModalGoHome1 = 30,
  kNonModalSetHome0 = 38,
  kNonModalSetHome1 = 40,
  kNonModalAbsoluteOverride = 53,
  kNonModalSetCoordinateOffset = 92,
  kNonModalResetCoordinateOffset = 102,
};

enum GcodeAxisCommand : int {
  kAxisCommandNone = 0,
  kAxisCommandNonModal = 1,
  kAxisCommandMotionMode = 2,
  kAxisCommandToolLengthOffset = 3,
};

struct GcodeModal {
  int motion = kMotionSeek;
  int coord_select = 0;       // 0..5 = G54..G59
  int plane = 0;              // 0 G17 (XY), 1 G18 (ZX), 2 G19 (YZ)
  bool inches = false;        // G20 (else G21)
  bool incremental = false;   // G91 (else G90)
  bool inverse_time = false;  // G93 (else G94)
  int program_flow = 0;       // 0 running, 3 M0 pause, 2 M2, 30 M30
  int spindle = 0;            // 0 M5, 1 M3, 2 M4
  int coolant = 0;            // bit 0: M8 flood (M7 mist is not compiled in, as in GRBL 1.1h)
  bool tool_length_dynamic = false;  // G43.1 (else G49)
};

// The parser state (GRBL gc_state).
struct GcodeState {
  GcodeModal modal;
  double feed_rate = 0.0;  // mm/min (inverse-time value under G93)
  double spindle_speed = 0.0;
  int tool = 0;
  int line_number = 0;
  Eigen::Vector3d position = Eigen::Vector3d::Zero();      // where the parser thinks it is
  Eigen::Vector3d coord_system = Eigen::Vector3d::Zero();  // active G54..G59 offset
  Eigen::Vector3d coord_offset = Eigen::Vector3d::Zero();  // G92 offset
  double tool_length_offset = 0.0;                         // G43.1 (z)

  // Work coordinate offset: WPos = MPos - WCO.
  Eigen::Vector3d Wco() const;
};

// Persistent coordinate data ("EEPROM"): G54..G59, G28, G30, in machine mm.
struct CoordinateData {
  std::array<Eigen::Vector3d, 6> wcs{Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero(),
                                     Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero(),
                                     Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero()};
  Eigen::Vector3d g28 = Eigen::Vector3d::Zero();
  Eigen::Vector3d g30 = Eigen::Vector3d::Zero();
};

// A parsed, validated block (GRBL gc_block after step 3).
struct GcodeBlock {
  GcodeModal modal;  // modal state after the block
  int non_modal = kNonModalNone;
  int axis_command = kAxisCommandNone;
  bool jog = false;
  unsigned axis_words = 0;  // bit i: axis i given
  double feed_rate = 0.0;   // mm/min after unit conversion (or the inverse-time value)
  double spindle_speed = 0.0;
  int tool = 0;
  int line_number = 0;
  double dwell_s = 0.0;
  // Motion target (machine mm); for G43.1 the z value is the tool length offset; for G92 the new
  // G92 offsets.
  Eigen::Vector3d xyz = Eigen::Vector3d::Zero();
  // Arc centre offset from the current position; for G10 the new coordinate data; for G28/G30
  // the stored go-home position.
  Eigen::Vector3d ijk = Eigen::Vector3d::Zero();
  double radius = 0.0;  // arcs
  int axis_0 = 0, axis_1 = 1, axis_linear = 2;
  bool arc_clockwise = false;
  int coord_data_index = -1;  // G10: coordinate system written (0..5)
  Eigen::Vector3d block_coord_system = Eigen::Vector3d::Zero();  // G54..G59 offset in effect
};

// Parses and error-checks one line against the parser state, GRBL's steps 1-3. Returns the
// GrblStatus code (kGrblOk = 0) and, on success, fills `block`. A line starting with "$J=" is a
// jog (the caller has checked the "$J=" prefix and the machine state).
int ParseGcodeLine(std::string_view line, const GcodeState& state, const CoordinateData& coords,
                   GcodeBlock* block);

// The `[GC:...]` parser-state line of `$G` (without "\r\n"); rates in inch/min when
// `report_inches`.
std::string FormatParserState(const GcodeState& state, bool report_inches);

// GRBL's mc_arc(): the end points of the chords approximating the arc from `position` to
// `target` (last element == target), within `arc_tolerance_mm` of the circle.
std::vector<Eigen::Vector3d> ArcSegmentTargets(const Eigen::Vector3d& position,
                                               const Eigen::Vector3d& target,
                                               const Eigen::Vector3d& offset, double radius,
                                               int axis_0, int axis_1, int axis_linear,
                                               bool clockwise, double arc_tolerance_mm);

}  // namespace gs360
