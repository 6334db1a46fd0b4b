#pragma once
// Machine-time estimates for a GRBL 1.1 machine: closed-form trapezoidal velocity profiles from the
// machine's settings, GRBL's junction-deviation corners, and whole G-code programs.
//
// Units: positions and lengths in mm, speeds in mm/s, accelerations in mm/s^2, feed rates as
// G-code and GRBL settings give them (mm/min), times in seconds. Positions are machine
// coordinates (GRBL MPos) unless stated otherwise.
//
// Model (the firmware's, gnea/grbl planner.c):
// - a straight block along unit vector u runs at most at its nominal speed: the feed rate (G1)
//   or the rapid rate (G0), never above the rapid rate, which is the largest speed whose per-axis
//   components stay within $110-$112; its acceleration is the largest whose per-axis components
//   stay within $120-$122 (MaxAlongDirection);
// - each block is a trapezoid (accelerate, cruise, decelerate) or a triangle when too short;
// - junctions: JunctionModel::kStop stops at the end of every block (an upper bound of any
//   correct planner, independent of look-ahead and of when the lines arrive);
//   JunctionModel::kGrbl uses GRBL's junction-deviation speed limit ($11), the nominal speeds of
//   both blocks, and the reverse / forward passes, with GRBL's look-ahead of `planner_blocks`
//   blocks (the newest planned block always ends at rest). It is what GRBL executes when the
//   host keeps the planner fed (lines arrive faster than blocks finish).
// - G4 P<s> first waits until every earlier motion has finished (the planner runs empty, the
//   machine ends at rest), then dwells s seconds. The sync point of a press.
//
// Everything here is a pure function; thread-safe.

#include <Eigen/Core>
#include <map>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace gs360 {

// The GRBL settings that shape motion and travel, with the defaults of the virtual CNC
// (sim/grbl_settings.h: a 3018-class desktop mill): 2000/2000/800 mm/min, 150/150/80 mm/s^2,
// travel 300 x 180 x 45 mm, junction deviation 0.010 mm, 15 planner blocks. A real machine's
// values come from `$$` (FromGrblSettings).
struct MachineSettings {
  Eigen::Vector3d max_rate_mm_per_min{2000.0, 2000.0, 800.0};  // $110-$112
  Eigen::Vector3d acceleration_mm_per_s2{150.0, 150.0, 80.0};  // $120-$122
  // $130-$132, positive. After homing with GRBL's default directions ($23 = 0) the machine
  // position of axis i stays within [-max_travel_mm[i], 0] (soft limits, $20).
  Eigen::Vector3d max_travel_mm{300.0, 180.0, 45.0};
  // Where the travel starts on each axis when it is not GRBL's [-max_travel_mm, 0]: a printer's
  // [0, max] (Marlin's X_MIN_POS.., M211), or any other box (mm, machine frame).
  std::optional<Eigen::Vector3d> travel_min_mm;
  // The travel box: [TravelMin(), TravelMax()] per axis.
  Eigen::Vector3d TravelMin() const { return travel_min_mm.value_or(-max_travel_mm); }
  Eigen::Vector3d TravelMax() const { return TravelMin() + max_travel_mm; }
  double junction_deviation_mm = 0.010;  // $11
  int planner_blocks = 15;  // look-ahead (GRBL: BLOCK_BUFFER_SIZE - 1; $I [OPT:..,15,..])

  // Throws std::invalid_argument naming the field and its value: rates, accelerations and
  // travels must be finite and > 0, travel_min_mm finite, the junction deviation finite and
  // >= 0, planner_blocks >= 1.
  void Check() const;

  // From `$$` values (GrblMachineInfo::settings): $110-$112, $120-$122, $130-$132, $11; settings
  // absent from the map keep the defaults. Throws std::invalid_argument (via Check()) for
  // invalid values.
  static MachineSettings FromGrblSettings(const std::map<int, double>& settings);
};

enum class JunctionModel {
  kStop,  // every block starts and ends at rest: an upper bound
  kGrbl,  // GRBL's junction speeds and look-ahead
};
std::string_view JunctionModelName(JunctionModel model);

// GRBL's limit_value_by_axis_maximum(): the largest magnitude along `unit` (unit vector) whose
// per-axis components stay within `axis_max` (positive). +inf for a zero vector.
double MaxAlongDirection(const Eigen::Vector3d& axis_max, const Eigen::Vector3d& unit);

// Squared maximum junction speed ((mm/s)^2) between a block along `prev_unit` and the next
// along `unit` (GRBL's junction deviation): 0 for a reversal, +inf when going straight on.
double JunctionSpeedSqr(const Eigen::Vector3d& prev_unit, const Eigen::Vector3d& unit,
                        const MachineSettings& settings);

// Time (s) of one block of `length` mm entering at `entry_speed`, leaving at `exit_speed`,
// cruising at most at `nominal_speed`, with |acceleration| = `acceleration`. Speeds are clamped
// to the nominal speed; exit/entry speeds that cannot be met within the length are an error.
// Throws std::invalid_argument for length < 0, nominal_speed or acceleration <= 0, negative
// speeds, or |entry^2 - exit^2| > 2 a L (+1e-9 relative).
double TrapezoidTime(double length, double entry_speed, double nominal_speed, double exit_speed,
                     double acceleration);

// One straight move to `target` (machine mm). feed_mm_per_min <= 0 means rapid (G0).
struct Move {
  Eigen::Vector3d target = Eigen::Vector3d::Zero();
  double feed_mm_per_min = 0.0;
  bool Rapid() const { return feed_mm_per_min <= 0.0; }
};

// Rest-to-rest time (s) of a single straight move from `from` (0 for a zero-length move).
double MoveTime(const Eigen::Vector3d& from, const Move& move, const MachineSettings& settings);
// Same, for a rapid move (the planner's travel-time metric).
double RapidTime(const Eigen::Vector3d& from, const Eigen::Vector3d& to,
                 const MachineSettings& settings);

// Time (s) of a path of moves starting at rest at `start` and ending at rest at the last target
// (a sync follows it), under `model`. Zero-length moves are skipped (GRBL drops them).
double PathTime(const Eigen::Vector3d& start, const std::vector<Move>& moves,
                const MachineSettings& settings, JunctionModel model);

// Per-block detail of PathTime (for tests and diagnostics).
struct BlockProfile {
  double length = 0.0;         // mm
  double nominal_speed = 0.0;  // mm/s
  double acceleration = 0.0;   // mm/s^2
  double entry_speed = 0.0;    // mm/s
  double exit_speed = 0.0;     // mm/s
  double time = 0.0;           // s
};
std::vector<BlockProfile> PlanPath(const Eigen::Vector3d& start, const std::vector<Move>& moves,
                                   const MachineSettings& settings, JunctionModel model);

// Estimate of a G-code program's machine time.
struct ProgramEstimate {
  double motion_s = 0.0;  // time in motion
  double dwell_s = 0.0;   // sum of G4 dwells
  int moves = 0;          // non-zero-length G0/G1 blocks
  int syncs = 0;          // G4 lines (each ends the motion planned before it at rest)
  Eigen::Vector3d end_position = Eigen::Vector3d::Zero();  // machine mm
  double Total() const { return motion_s + dwell_s; }
};

// Machine time of `lines` executed from rest at `start` (machine coordinates). Understands what
// gs360 emits and common hand-written programs: G0, G1 (modal), G4 P<s>, G53 (machine
// coordinates, this line only), G90 / G91, G20 / G21, F (modal, mm/min or in/min), X Y Z words,
// comments in () or after ';', blank lines, '%' and $-commands (ignored). Coordinates without
// G53 are work coordinates: machine = work + `work_offset`. The program's motion after its last
// G4 also ends at rest. Throws std::invalid_argument naming the line number and text for a
// malformed line (bad number, unsupported G/M word that moves the machine: G2/G3/G28/G30/G38,
// G1 without a feed rate).
ProgramEstimate EstimateProgram(const std::vector<std::string>& lines, const Eigen::Vector3d& start,
                                const MachineSettings& settings, JunctionModel model,
                                const Eigen::Vector3d& work_offset = Eigen::Vector3d::Zero());

}  // namespace gs360
