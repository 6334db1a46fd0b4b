#pragma once
// GRBL 1.1's motion model, for the virtual CNC: the look-ahead planner (gnea/grbl planner.c) and
// an exact, analytic stand-in for its stepper module.
//
// Units: positions and lengths in mm, speeds in mm/s, accelerations in mm/s^2, rates given by
// G-code and settings in mm/min (converted here), times in seconds of *machine* time (the virtual
// CNC maps wall time to machine time with its time scale). Positions are in whatever frame the
// caller uses consistently (the virtual CNC uses the true machine frame).
//
// Planner semantics follow GRBL: a block's acceleration and rapid rate are the largest values
// whose per-axis components stay within $120-$122 and $110-$112; its nominal speed is the feed
// rate (G1) or the rapid rate (G0), never above the rapid rate; the maximum entry speed at a
// junction comes from the junction-deviation model ($11); a new block after an empty planner
// starts from rest; the newest block always ends at rest; a reverse pass then a forward pass
// maximise every junction speed; each block runs a trapezoid (or triangle) between its entry and
// exit speeds. The executing block is re-planned from its current speed whenever the plan changes
// (new block, feed hold, resume), as GRBL's segment generator does.

#include <cstddef>
#include <cstdint>
#include <deque>
#include <limits>
#include <optional>
#include <vector>

#include <Eigen/Core>

namespace gs360 {

struct MotionLimits {
  Eigen::Vector3d max_rate_mm_per_min{500.0, 500.0, 500.0};  // $110-$112
  Eigen::Vector3d acceleration_mm_per_s2{10.0, 10.0, 10.0};  // $120-$122
  double junction_deviation_mm = 0.010;                      // $11

  // Throws std::invalid_argument naming the field when a rate or acceleration is not > 0 or the
  // junction deviation is negative.
  void Check() const;
};

// GRBL's limit_value_by_axis_maximum(): the largest magnitude along `unit` (a unit vector) whose
// per-axis components stay within `axis_max`.
double LimitByAxisMaximum(const Eigen::Vector3d& axis_max, const Eigen::Vector3d& unit);

// Maximum speed (mm/s) through the junction from direction `prev_unit` into `unit` (both unit
// vectors), GRBL's junction-deviation model. +infinity when the path continues straight; 0 for a
// full reversal.
double JunctionSpeedLimit(const Eigen::Vector3d& prev_unit, const Eigen::Vector3d& unit,
                          const MotionLimits& limits);

// Closed form: time (s) to cover `length_mm` entering at `entry_speed` and leaving at
// `exit_speed`, cruising at most at `nominal_speed`, with |acceleration| <= `acceleration`
// (accelerate, cruise, decelerate; a triangle when the block is too short to reach the nominal
// speed). An entry above the nominal speed first decelerates to it. Throws std::invalid_argument
// when the speeds cannot be met within the length (|entry^2 - exit^2| > 2 a L) or an argument is
// not positive.
double TrapezoidDuration(double length_mm, double entry_speed, double nominal_speed,
                         double exit_speed, double acceleration);

// How a move's speed is programmed.
struct MoveRate {
  bool rapid = true;             // G0: the block's rapid rate
  double feed_mm_per_min = 0.0;  // G1 (mm/min), or the inverse-time value when inverse_time
  bool inverse_time = false;     // G93: the move takes 1/feed minutes
};

struct MoveRequest {
  Eigen::Vector3d target = Eigen::Vector3d::Zero();
  MoveRate rate;
};

// Nominal speed (mm/s) GRBL gives a straight block of `length_mm` along `unit` at `rate`.
double NominalSpeed(const Eigen::Vector3d& unit, double length_mm, const MoveRate& rate,
                    const MotionLimits& limits);

// Rest-to-rest duration (s) of one isolated straight move.
double IsolatedMoveDuration(const Eigen::Vector3d& from, const MoveRequest& move,
                            const MotionLimits& limits);

// Duration (s) of a whole path planned at once, from rest at `start` to rest at the last target,
// with GRBL's junction speeds and the reverse / forward passes over every block (unbounded
// look-ahead: equal to what GRBL does when the path fits its planner or the look-ahead does not
// bind). Zero-length moves are skipped, as GRBL drops them.
double PlannedPathDuration(const Eigen::Vector3d& start, const std::vector<MoveRequest>& moves,
                           const MotionLimits& limits);

// One constant-acceleration piece of executed (or predicted) motion along a straight line.
struct MotionPiece {
  double t0 = 0.0;  // machine seconds
  double t1 = 0.0;
  Eigen::Vector3d p0 = Eigen::Vector3d::Zero();    // position at t0
  Eigen::Vector3d dir = Eigen::Vector3d::UnitX();  // unit direction of travel
  double v0 = 0.0;                                 // speed at t0, mm/s
  double accel = 0.0;                              // signed, along dir, mm/s^2

  Eigen::Vector3d PositionAt(double t) const;  // clamped to [t0, t1]
  double SpeedAt(double t) const;              // clamped to [t0, t1]
  Eigen::Vector3d End() const { return PositionAt(t1); }
  double Length() const;
};

// An alarm armed on a block: fires when the block has covered `fraction` of its length.
struct ArmedAlarm {
  int code = 1;
  double fraction = 0.5;
};

struct FiredAlarm {
  int code = 0;
  double time = 0.0;  // machine seconds
  Eigen::Vector3d position = Eigen::Vector3d::Zero();
};

// The planner buffer plus the motion it produces over time. Not thread-safe: the virtual CNC
// guards it with its own mutex. Time passed to any method must not go backwards.
class MotionExecutor {
 public:
  struct Options {
    int planner_blocks = 15;                // GRBL: BLOCK_BUFFER_SIZE - 1
    std::size_t history_pieces = 1u << 15;  // executed pieces kept for PositionAt() in the past
  };

  MotionExecutor(const Options& options, const Eigen::Vector3d& position, double t);

  void SetLimits(const MotionLimits& limits) { limits_ = limits; }
  const MotionLimits& Limits() const { return limits_; }

  int BlockCount() const { return static_cast<int>(state_.blocks.size()); }
  int PlannerCapacity() const { return options_.planner_blocks; }
  bool PlannerFull() const { return BlockCount() >= options_.planner_blocks; }
  // End of the last queued block (GRBL's planner position), or the current position.
  Eigen::Vector3d PlannerPosition() const;

  // Queues a straight move to `target` at machine time `t` (the time the block is planned).
  // Returns false, queuing nothing, when the move has zero length. Precondition: !PlannerFull().
  bool AddLine(const Eigen::Vector3d& target, const MoveRate& rate, double t,
               std::optional<ArmedAlarm> alarm = std::nullopt);
  // Queues a system motion (homing): starts and ends at rest, `rate_mm_per_min` capped by the
  // rapid rate. With `abrupt_end` it never decelerates: it stops dead at the target (a limit
  // switch). Precondition: no queued blocks.
  void AddSystemLine(const Eigen::Vector3d& target, double rate_mm_per_min, bool abrupt_end,
                     double t);

  // Starts executing the queued blocks at time t (GRBL's cycle start). No effect when running.
  void StartCycle(double t);
  // Feed hold at t: decelerate at each block's acceleration to a stop (possibly across blocks).
  void FeedHold(double t);
  // Resume after a completed hold: re-plan from rest and run.
  void Resume(double t);
  // Abrupt stop at t (steppers killed): speed 0, every block discarded, planner memory cleared.
  void Stop(double t);

  // Executes up to machine time t, recording the pieces that finished.
  void AdvanceTo(double t);

  bool Running() const { return state_.running; }
  bool Holding() const { return state_.holding; }
  // True once a hold has brought the machine to rest (GRBL "Hold:0").
  bool HoldComplete() const { return state_.holding && state_.speed == 0.0; }
  // Running with blocks left, not held at rest.
  bool Busy() const { return state_.running && !state_.blocks.empty() && !HoldComplete(); }
  // An armed alarm that fired (the executor stopped dead at its position); cleared by the call.
  std::optional<FiredAlarm> TakeFiredAlarm();

  // Time of the last state change (the executor's clock).
  double StateTime() const { return state_.t; }
  // Position and speed at any time: from the recorded history for the past, predicted from the
  // current plan for the future. Before the oldest recorded piece: the starting position if no
  // piece was ever evicted, else PositionAt throws std::out_of_range (the past is forgotten).
  Eigen::Vector3d PositionAt(double t) const;
  double SpeedAt(double t) const;
  // End time of the piece being executed (when something next changes), +inf when nothing runs.
  double NextEventTime() const;
  // Time at which the current plan finishes (or a hold completes) if nothing else happens; the
  // state time when idle; +inf never (bounded by the plan).
  double FinishTime() const;

  // Executed pieces overlapping [t0, t1], oldest first (ground truth for tests and rendering).
  std::vector<MotionPiece> History(double t0, double t1) const;

 private:
  struct Block {
    Eigen::Vector3d start = Eigen::Vector3d::Zero();  // current start (advances while executing)
    Eigen::Vector3d target = Eigen::Vector3d::Zero();
    Eigen::Vector3d unit = Eigen::Vector3d::UnitX();
    double remaining = 0.0;  // mm left
    double length = 0.0;     // original length, mm
    double accel = 0.0;
    double nominal = 0.0;  // mm/s
    double max_entry_sqr = 0.0;
    double entry_sqr = 0.0;
    bool abrupt_end = false;
    std::optional<ArmedAlarm> alarm;
  };
  struct Step {
    MotionPiece piece;
    double end_speed = 0.0;  // speed when the piece ends (exact, as designed)
    bool ends_block = false;
    bool fires_alarm = false;
  };
  struct State {
    std::deque<Block> blocks;
    Eigen::Vector3d position = Eigen::Vector3d::Zero();
    double speed = 0.0;
    double t = 0.0;
    bool running = false;
    bool holding = false;
  };

  static std::optional<Step> NextStep(const State& s);
  // Applies a finished step; returns the fired alarm, if any (and stops the state).
  static std::optional<FiredAlarm> ApplyStep(State& s, const Step& step);
  void Replan();
  void SplitAt(double t);
  void Record(const MotionPiece& piece);

  Options options_;
  MotionLimits limits_;
  State state_;
  Eigen::Vector3d previous_unit_ = Eigen::Vector3d::Zero();
  double previous_nominal_ = 0.0;
  std::optional<FiredAlarm> fired_;
  std::deque<MotionPiece> history_;
  bool history_truncated_ = false;  // pieces were evicted: the past before front() is unknown
};

}  // namespace gs360
