#pragma once
// Probe planning for the calibration run: where to press, how to get there, in which order, and
// how long it takes.
//
//  1. Candidates: `probe_count` points blue-noise sampled on the sensor surface (area-uniform,
//     geometry/sampling.h), snapped onto the exact surface when the built-in profile is known.
//  2. Filters, in this order (a point is counted under the first reason that rejects it):
//     kFov        outside the nominal camera's image circle (theta beyond the lens's valid field
//                 minus fov_margin_rad, or within image_margin_px of the image border);
//     kViewAngle  seen too obliquely: angle between the camera ray and the normal > max;
//     kFin        line of sight from the camera centre blocked by the LED fins;
//     kGel        line of sight blocked by the gel itself (the first hit is not the point);
//     kReach      the probe cannot press it: the ball at the approach position, or the vertical
//                 stylus (a cylinder of stylus_radius from the ball up to stylus_length, along
//                 machine +z) and its holder above it, at approach or along the press, would
//                 touch the sensor or the mount (the half-space below the base plane), the ball
//                 at full depth would touch the sensor a second time elsewhere or dip into the
//                 mount, or there is no collision-free way out (radially away from the axis, or
//                 straight up);
//     kTravel     a machine position (approach, press, escape) outside the soft-limit travel
//                 [-$13x + margin, -margin].
//  3. Positions, per kept point p (outward unit normal n, sensor frame), ball centre:
//        approach = retract = p + n (ball_radius + clearance)
//        press = p + n (ball_radius - press_depth)
//     and in machine coordinates (what G-code targets; GRBL MPos):
//        machine = machine_from_sensor * ball_centre_sensor - tool_offset.
//  4. Order: nearest-neighbour tour from the start position over the approach points, improved by
//     2-opt and Or-opt moves on K-nearest-neighbour candidate lists, with the machine-time cost
//     of each travel (trapezoidal, from the machine settings). Travel between approach points
//     goes straight when the whole tool stays travel_clearance away from the sensor and mount
//     along the segment, else through waypoints (out radially to a cylinder that clears the
//     sensor, around it, and in; or up over the top; whichever is faster).
//  5. Estimate: per press, the G-code motion (retract, travel, approach, press) planned as the
//     firmware plans it (plan/motion_estimate.h), the settle dwell, then the host's time before
//     it sends the retract (capture_time_s, the status-poll latency, the serial round trip). The
//     same for the sampling order gives the tour's gain.
//
// Frames: sensor (S, the mesh's frame), camera (OpenCV), machine (GRBL MPos); transforms named
// b_from_a (geometry/rigid3.h). Units: mm, rad, s; feeds in mm/min.
// Determinism: the same rig, options and seed give the same plan, bit for bit.

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <memory>
#include <nlohmann/json_fwd.hpp>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

#include "geometry/bvh.h"
#include "geometry/fisheye.h"
#include "geometry/mesh.h"
#include "geometry/rigid3.h"
#include "geometry/shapes.h"
#include "plan/coverage.h"
#include "plan/drop_reason.h"
#include "plan/imprint.h"
#include "plan/motion_estimate.h"
#include "plan/surface_distance.h"
#include "rig/rig_config.h"

namespace gs360 {

// What the planner needs to know about the rig (nominal values: production code never sees the
// simulator's truth).
struct RigGeometry {
  TriangleMesh sensor_mesh;  // outer gel surface, sensor frame, outward normals
  // The exact surface when the sensor is a built-in shape (points are snapped onto it and
  // collision checks use it); nullptr for a loaded mesh (the mesh is used).
  std::shared_ptr<const RevolutionProfile> profile;
  TriangleMesh fins;  // LED fins, sensor frame; may be empty
  FisheyeIntrinsics camera = FisheyeIntrinsics::Default160();
  Rigid3d cam_from_sensor;      // nominal (CAD) camera pose
  Rigid3d machine_from_sensor;  // the mount
  // Ball centre (machine frame) = machine position (MPos) + tool_offset.
  Eigen::Vector3d tool_offset = Eigen::Vector3d::Zero();

  // Throws std::invalid_argument: empty sensor mesh, non-finite transforms or offset, invalid
  // intrinsics.
  void Check() const;
};

// The planner's view of a rig described by `rig` (rig/rig_config.h, its defaults the only ones):
// the gel mesh (built or loaded), the exact profile of a built-in shape (none for a mesh), the
// fins, the nominal camera and the mount. The default rig centres the default sensor in the
// default travel (300 x 180 x 45 mm, positions in [-travel, 0]) with every press and the
// over-the-top plane inside the 45 mm of Z. Throws MeshError for a mesh that cannot be used,
// std::invalid_argument for an invalid rig.
RigGeometry MakeRigGeometry(const RigConfig& rig);
RigGeometry MakeRigGeometry();  // the default rig

struct PlanOptions {
  // Sampling.
  // Candidates drawn on the whole surface (> 0). The default is sized by `gs360 bench sweep`
  // (docs/benchmarks.md, "Run time against error"): the fewest at which the cylinder and the cone
  // meet every accuracy target with margin, about an hour of machine time at the default feeds.
  int probe_count = 2700;
  // > 0: the plan is sized in machine time rather than in candidates: it keeps as many probes as
  // fit in this many hours of estimated machine time (between 90 % and 100 % of it, unless even
  // 8 x probe_count candidates fall short), drawing probe_count x budget / estimate candidates
  // again until it does; probe_count is then only the first draw. 0: exactly probe_count
  // candidates (the default here; gs360d's configuration defaults to kDefaultMachineHours). An
  // explicit probe count (a request's "probes", a [plan] probe_count without machine_hours)
  // reads as 0 (run/run_config.h).
  double machine_hours = 0.0;
  // If true, probe_count counts KEPT probes: the blue-noise sampler draws candidates only where
  // every filter passes (drop counts then count rejected candidate draws).
  bool count_is_kept = false;
  std::uint64_t seed = 1;
  double candidate_factor = 5.0;  // blue-noise candidates per sample (>= 1)
  bool snap_to_profile = true;    // project samples onto the exact built-in surface

  // Probe and press.
  double ball_radius = 2.0;  // mm (a 4 mm steel ball)
  double press_depth = 1.0;  // mm into the gel (< ball_radius)
  double clearance = 1.0;    // mm between ball and surface at the approach position
  // Stylus: a 1.5 mm steel shaft (radius 0.75 mm) carrying the ball, 25 mm from the ball centre
  // to the holder; vertical (machine +z). Must be thinner than the ball.
  double stylus_radius = 0.75;
  double stylus_length = 25.0;
  // The holder the stylus is screwed into (collet / adapter): a vertical cylinder from the
  // stylus's top end up `holder_length` mm. holder_radius 0 disables it.
  double holder_radius = 4.0;
  double holder_length = 30.0;
  double press_feed_mm_per_min = 120.0;  // approach -> press (G1)
  double retract_feed_mm_per_min = 0.0;  // press -> approach; 0 = rapid (G0)
  double settle_dwell_s = 0.3;           // G4 at full depth before the frame

  // Host time per sync (each G4 whose ok the host waits for: every press, every reference).
  // capture_time_s: frames grabbed after the ok; status_poll_latency_s: the wait for a fresh
  // status report (MPos) requested at the ok, concurrent with the capture (at the GRBL limit of
  // 5 Hz a fresh report can take up to one 200 ms period); host_latency_s: the rest of the round
  // trip (ok to host, retract line to the machine's planner). Per sync the estimate adds
  // max(capture_time_s, status_poll_latency_s) + host_latency_s.
  double capture_time_s = 0.15;
  double status_poll_latency_s = 0.2;
  double host_latency_s = 0.01;
  // A no-contact reference frame before plan index 0 and then every reference_every probes
  // (0: only before the first), taken at the approach position after a G4 P<reference_dwell_s>.
  int reference_every = 100;
  double reference_dwell_s = 0.1;

  // Visibility.
  double fov_margin_rad = 0.0;   // keep theta <= the lens's valid field minus this
  double image_margin_px = 2.0;  // keep the pixel this far inside the image
  double max_view_angle_rad = 1.3089969389957472;  // 75 deg between camera ray and normal
  double occlusion_tolerance_mm = 0.05;            // a gel hit this close to the point is the point

  // Collisions.
  double travel_clearance = 0.5;        // min gap (ball and stylus) along travel, mm (<= clearance)
  double press_stylus_clearance = 0.1;  // min stylus gap from approach to full depth, mm
  // Second contact: at full depth, ball points more than (the flat-surface contact cap angle +
  // contact_margin_rad) away from -n must be outside the sensor.
  double contact_margin_rad = 0.2617993877991494;  // 15 deg
  bool base_is_obstacle = true;      // the mount fills the half-space below the base plane z < 0
  double travel_limit_margin = 0.5;  // mm kept inside the soft limits
  double escape_margin = 0.5;        // extra radius of the escape cylinder, mm
  double arc_step_rad = 0.2617993877991494;  // around-the-sensor waypoint spacing (15 deg)

  // Order and estimate.
  bool optimise_order = true;
  // 0: one tour over every probe (the fastest run). N > 0: the probes in rounds of N, each
  // round's probes chosen progressively (geometry/sampling.h FarthestPointOrder: the first N
  // cover the whole reachable surface sparsely, each later round fills in evenly) and toured
  // on their own, from where the last round ended. A run stopped after any round has probed the
  // surface evenly (for calibrating on what was captured so far); the rounds cost machine time
  // against the single tour, which the estimate shows. >= 0.
  int checkpoint_probes = 0;
  int neighbours = 10;              // candidate list size for 2-opt / Or-opt
  int max_improvement_passes = 50;  // full passes of the local search (deterministic cap)
  JunctionModel junction_model = JunctionModel::kGrbl;
  // Where the machine is when the run starts (machine frame), e.g. after homing; the plan
  // travels from here to the first probe and, if return_to_start, back at the end.
  Eigen::Vector3d start_machine = Eigen::Vector3d::Zero();
  bool return_to_start = true;

  MachineSettings machine;

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

// What would bring more of the surface within the probe's reach, measured by MakeProbePlan on
// the plan's own geometry (not stored with a plan: PlanFromJson leaves it empty).
struct PlanReach {
  // Travel (set when the tool can press any candidate): the machine-position bounds of every
  // candidate the tool can press, kept or dropped for travel (its approach, its press and its
  // escape: radial if it has one, else up), and of the plane over the sensor's top that travel
  // passes over it at (over_z_machine, TravelPlanner::OverZMachine); the travel they must fit
  // in, [travel_min + travel_margin, travel_min + max_travel_mm - travel_margin] per axis
  // (travel_min: MachineSettings::TravelMin(), GRBL's -max_travel_mm); and where the sensor's base
  // sits (machine frame).
  bool travel_known = false;
  Eigen::Vector3d machine_min = Eigen::Vector3d::Zero();
  Eigen::Vector3d machine_max = Eigen::Vector3d::Zero();
  double over_z_machine = 0.0;
  Eigen::Vector3d max_travel_mm = Eigen::Vector3d::Zero();
  Eigen::Vector3d travel_min = Eigen::Vector3d::Zero();
  bool travel_min_set = false;  // [plan.machine] travel_min_mm given (else GRBL's -max_travel_mm)
  double travel_margin = 0.0;
  Eigen::Vector3d base_in_machine = Eigen::Vector3d::Zero();
  // Stylus (measured when PlanAdvice would speak of reach: a tenth of the candidates or more
  // dropped for reach, under half kept): of the candidates dropped for reach that a longer stylus
  // would press, the lowest (at z = stylus_lowest_z, sensor frame; looked for among the lowest
  // 400 dropped) and the few above it within 1 mm; the shortest stylus_length, in whole mm, that
  // presses them all. 0: not measured, or no longer stylus would press any.
  double stylus_length = 0.0;  // the plan's
  double stylus_length_needed = 0.0;
  double stylus_lowest_z = 0.0;
};

// What to change when a plan keeps little (under half its candidates, or none): for each reason
// that dropped at least a tenth of them, most frequent first, one sentence naming the config key
// ("[rig.fins] enabled = false", "[plan.machine] max_travel_mm", ...). Empty when the plan keeps
// at least half, except that a finger beyond the machine's Z reach (the tool cannot pass over it,
// reach.over_z_machine above the travel) is always said first: the run could find no way to a
// probe. `kept` and `candidates` as in ProbePlan. With `reach`, the travel and reach sentences say
// by how much: where to put [rig] base_in_machine and [plan.machine] max_travel_mm so that every
// position fits (rounded up to 0.1 mm), and the stylus_length that presses the lowest
// candidates dropped for reach.
std::vector<std::string> PlanAdvice(const DropCounts& dropped, int kept, int candidates,
                                    const PlanReach* reach = nullptr);

struct PlannedProbe {
  int plan_index = 0;    // position in the run order
  int sample_index = 0;  // position in the sampling order of the kept probes
  Eigen::Vector3d point_sensor = Eigen::Vector3d::Zero();    // surface point, sensor frame
  Eigen::Vector3d normal_sensor = Eigen::Vector3d::UnitZ();  // outward unit normal
  // Machine positions (G-code targets, machine frame). retract == approach.
  Eigen::Vector3d approach_machine = Eigen::Vector3d::Zero();
  Eigen::Vector3d press_machine = Eigen::Vector3d::Zero();
  Eigen::Vector3d retract_machine = Eigen::Vector3d::Zero();
  // Waypoints (machine frame) between the previous position (the previous probe's retract, or
  // the start) and this approach, both excluded. Empty when the straight move is clear.
  std::vector<Eigen::Vector3d> travel_machine;
  bool reference_before = false;  // take a no-contact reference frame at the approach first
};

// Estimated machine + host time of a run (seconds).
struct PlanEstimate {
  // Motion from a retract position to the next approach (the start and park paths included).
  double travel_s = 0.0;
  double press_s = 0.0;      // motion approach -> press
  double retract_s = 0.0;    // motion press -> approach
  double dwell_s = 0.0;      // settle dwells
  double host_s = 0.0;       // per press: capture, status, round trip
  double reference_s = 0.0;  // reference frames: dwell + host time
  double Total() const { return travel_s + press_s + retract_s + dwell_s + host_s + reference_s; }
  double Hours() const { return Total() / 3600.0; }
  // Travel (travel + retract) and press (press motion + dwell + host + references) shares.
  double TravelShare() const;
  double PressShare() const;
};

struct ProbePlan {
  std::vector<PlannedProbe> probes;  // in run order
  int candidates = 0;                // points tested
  DropCounts dropped;
  // Parts of the surface with candidates and no probe (plan/coverage.h), most candidates first.
  std::vector<CoverageGap> coverage_gaps;
  PlanReach reach;
  int checkpoint_probes = 0;                  // the options' rounds (0: one tour)
  int waypoints = 0;                          // total travel waypoints in the run order
  int detoured_moves = 0;                     // travels that needed waypoints
  std::vector<Eigen::Vector3d> park_machine;  // waypoints + final position back to the start
  Eigen::Vector3d start_machine = Eigen::Vector3d::Zero();
  PlanEstimate estimate;                 // the run order
  double machine_budget_s = 0.0;         // PlanOptions::machine_hours in s (0: not sized by time)
  PlanEstimate sampling_order_estimate;  // the same probes in sampling order
  double nearest_neighbour_s = 0.0;      // total estimate after the nearest-neighbour tour only
  double planning_seconds = 0.0;         // wall time of MakeProbePlan
  std::string options_hash;              // Hasher over rig + options (for storage keys)
  SmallImprints small_imprints;          // probes the nominal camera will see small (imprint.h)
  // Sampling-order total over run-order total (> 1: the tour is faster).
  double TourGain() const;
};

// PlanAdvice for this plan, with its reach; first, for a plan sized in machine time that presses
// fewer than kProbesForTargets probes, that the rig cannot be expected to meet the accuracy
// targets, and why (its machine-time budget, or how much of the surface the filters leave).
std::vector<std::string> PlanAdvice(const ProbePlan& plan);
// Probes below which the calibration misses its accuracy targets on the virtual rig
// (docs/benchmarks.md, "Run time against error" and "Held-out rigs").
inline constexpr int kProbesForTargets = 1000;

// Plans the run. Throws std::invalid_argument for invalid options or rig, std::runtime_error
// when no point survives the filters (with PlanAdvice's sentences) or no collision-free travel
// exists between two probes (naming them).
ProbePlan MakeProbePlan(const RigGeometry& rig, const PlanOptions& options);

// The machine-time estimate of `probes` in the given order, from options.start_machine, with
// their travel waypoints as stored, then the last retract and `park_machine` (empty: none).
// Motion between two syncs (retract, travel, approach, press) is planned as one path under
// options.junction_model; every sync adds its dwell and the host time. Against the virtual CNC
// executing the same G-code in real time, the kGrbl motion time matches the machine's (within
// 0.5% or 5 ms: tests/gcode/plan_sim_timing_test.cc); kStop is an upper bound. Measured
// agreement: docs/benchmarks.md, "Virtual rig".
PlanEstimate EstimatePlan(const std::vector<PlannedProbe>& probes,
                          const std::vector<Eigen::Vector3d>& park_machine,
                          const PlanOptions& options);

// Soft-limit check of every position a plan sends, as the G-code writes it (rounded to 0.001
// mm): each must lie in [-max_travel + margin, -margin] on every axis.
class TravelLimitError : public std::runtime_error {
 public:
  TravelLimitError(const std::string& what, int plan_index, int axis)
      : std::runtime_error(what), plan_index_(plan_index), axis_(axis) {}
  int plan_index() const { return plan_index_; }  // -1 for the park path
  int axis() const { return axis_; }              // 0 = X, 1 = Y, 2 = Z
 private:
  int plan_index_;
  int axis_;
};
// Throws TravelLimitError naming the probe's plan index, the position (approach, press, retract,
// waypoint k, park), the axis and the value.
void CheckTravel(const ProbePlan& plan, const MachineSettings& settings, double margin);

// Collision model of the probe (ball + vertical stylus) against the sensor and its mount, and
// collision-free travel between machine positions. Built once per rig and options; const methods
// are thread-safe. Used by MakeProbePlan and by the run loop (e.g. the travel from wherever the
// machine is after a resume to the next probe).
class TravelPlanner {
 public:
  TravelPlanner(const RigGeometry& rig, const PlanOptions& options);

  // Gaps (mm) between the sensor / mount and the ball (centre at `ball_sensor`), and between
  // them and the stylus and holder above it (the smaller). Negative = collision. For a surface
  // of revolution with its axis along machine z the stylus / holder gap is exact (distance of a
  // flat-ended vertical cylinder to the solid); otherwise it is a lower bound from spheres along
  // the axis (conservative by up to the part's radius at its two ends).
  struct Gaps {
    double ball = 0.0;
    double stylus = 0.0;
    double Min() const { return ball < stylus ? ball : stylus; }
  };
  Gaps ToolGaps(const Eigen::Vector3d& ball_sensor) const;
  // True if min(ball, stylus) gap >= `gap` - 1e-6 along the whole segment (ball centres, sensor
  // frame); `stylus_only` ignores the ball (the press move).
  bool SegmentClear(const Eigen::Vector3d& a_sensor, const Eigen::Vector3d& b_sensor, double gap,
                    bool stylus_only = false) const;

  // Collision-free waypoints (machine frame, excluding both ends) from machine position `from` to
  // `to` (both must be clear), the fastest of: straight, via the escape cylinder, over the top.
  // A `from` whose ball the base plane holds closer than travel_clearance, away from the sensor
  // (a printer's ball on its bed after homing), first rises straight up; one inside the travel
  // but within travel_limit_margin of its end (a printer homed at 0) then steps straight in to
  // the nearest point the margin allows. nullopt when none is clear.
  std::optional<std::vector<Eigen::Vector3d>> Path(const Eigen::Vector3d& from_machine,
                                                   const Eigen::Vector3d& to_machine) const;
  // Rapid time (s) of the path from `from` through `waypoints` to `to` (stops at each waypoint).
  double PathTimeStop(const Eigen::Vector3d& from_machine,
                      const std::vector<Eigen::Vector3d>& waypoints,
                      const Eigen::Vector3d& to_machine) const;

  Eigen::Vector3d MachineFromBall(const Eigen::Vector3d& ball_sensor) const;
  Eigen::Vector3d BallFromMachine(const Eigen::Vector3d& machine) const;
  const SurfaceDistance& Distance() const { return distance_; }
  // Radius (sensor frame, about the z axis) outside which the tool is clear at any height above
  // the mount; machine z above which (machine position) the tool clears the sensor's top.
  double EscapeRadius() const { return escape_radius_; }
  double OverZMachine() const { return over_z_machine_; }
  // The tool's smallest gap to the sensor itself with the ball at `ball` (sensor frame), the
  // mount's plane left out (a printer's bed is no gel): ball and stylus, mm.
  double SensorGap(const Eigen::Vector3d& ball) const;
  bool VerticalStylusOnRevolution() const { return exact_stylus_; }

  // Escape points of a machine position: radially out (about the sensor axis; upright sensor
  // only) to the escape cylinder, or straight up to OverZMachine(); the position itself when it
  // is already there; nullopt when that segment is not clear.
  std::optional<Eigen::Vector3d> RadialEscape(const Eigen::Vector3d& machine) const;
  std::optional<Eigen::Vector3d> UpEscape(const Eigen::Vector3d& machine) const;

  // A position with its clearance and escapes, precomputed once per probe.
  struct Node {
    Eigen::Vector3d machine = Eigen::Vector3d::Zero();
    Eigen::Vector3d ball = Eigen::Vector3d::Zero();  // ball centre, sensor frame
    double gap = 0.0;                                // ToolGaps(ball).Min()
    std::optional<Eigen::Vector3d> radial;           // RadialEscape (within travel if filtered)
    std::optional<Eigen::Vector3d> up;               // UpEscape (within travel if filtered)
  };
  Node MakeNode(const Eigen::Vector3d& machine, bool filter_travel) const;
  struct Route {
    std::vector<Eigen::Vector3d> waypoints;  // machine frame, ends excluded
    double time = 0.0;                       // rapid, stopping at each waypoint (s)
  };
  // The fastest clear route between two nodes (see Path), or nullopt.
  std::optional<Route> BestRoute(const Node& a, const Node& b) const;
  // Within the soft limits with options.travel_limit_margin (as the G-code rounds it).
  bool InTravel(const Eigen::Vector3d& machine) const;
  // Distance from a point (sensor frame) to the sensor and the mount (signed, mm).
  double ObstacleDistance(const Eigen::Vector3d& sensor_point) const;
  const PlanOptions& Options() const { return options_; }

 private:
  // A vertical cylinder of the tool: radius, from `lo` to `hi` mm above the ball centre.
  struct Part {
    double radius = 0.0;
    double lo = 0.0;
    double hi = 0.0;
    double step = 0.0;        // sampling step along the axis (non-exact case)
    double radius_eff = 0.0;  // radius inflated to cover the gaps between samples
  };

  bool SegmentClearRec(const Eigen::Vector3d& a, const Eigen::Vector3d& b, double ga, double gb,
                       double gap, bool stylus_only, int depth) const;
  bool StraightClear(const Node& a, const Node& b) const;
  double GapOf(const Gaps& g, bool stylus_only) const { return stylus_only ? g.stylus : g.Min(); }
  // Waypoints around the escape cylinder from escape point a to escape point b (machine frame).
  std::vector<Eigen::Vector3d> ArcWaypoints(const Eigen::Vector3d& a_machine,
                                            const Eigen::Vector3d& b_machine) const;

  PlanOptions options_;
  SurfaceDistance distance_;
  Rigid3d machine_from_sensor_;
  Rigid3d sensor_from_machine_;
  Eigen::Vector3d tool_offset_;
  Eigen::Vector3d stylus_dir_sensor_;  // machine +z in the sensor frame
  bool exact_stylus_ = false;
  bool vertical_axis_ = false;  // sensor z parallel to machine z (escape cylinder argument)
  double stylus_exit_ = 0.0;    // height above the ball centre where the stylus leaves the ball
  std::vector<Part> parts_;     // stylus, holder
  double escape_radius_ = 0.0;
  double over_z_machine_ = 0.0;
};

// The per-point filters of MakeProbePlan (step 2) and the probe positions (step 3), for one
// surface point at a time. Owns its TravelPlanner and acceleration structures (copies of the
// rig's meshes); Classify is const and thread-safe.
class ProbePointFilter {
 public:
  // Throws std::invalid_argument for invalid options or rig.
  ProbePointFilter(const RigGeometry& rig, const PlanOptions& options);

  struct Result {
    std::optional<DropReason> reason;  // nullopt: the point is kept
    // The point and outward unit normal after snapping onto the exact surface (sensor frame).
    Eigen::Vector3d point = Eigen::Vector3d::Zero();
    Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();
    // Machine positions (valid when kept).
    Eigen::Vector3d approach_machine = Eigen::Vector3d::Zero();
    Eigen::Vector3d press_machine = Eigen::Vector3d::Zero();
    // The approach position's clearance and escapes: when kept, the escapes inside the travel;
    // when dropped for travel, all of them.
    TravelPlanner::Node node;
  };
  // `point` on the sensor surface with outward unit `normal` (sensor frame).
  Result Classify(const Eigen::Vector3d& point, const Eigen::Vector3d& normal) const;

  const TravelPlanner& travel() const { return travel_; }

 private:
  PlanOptions options_;
  std::shared_ptr<const RevolutionProfile> profile_;
  Rigid3d cam_from_sensor_;
  TravelPlanner travel_;
  FisheyeCamera camera_;
  Bvh sensor_bvh_;
  std::optional<Bvh> fins_bvh_;
  Eigen::Vector3d camera_center_ = Eigen::Vector3d::Zero();  // sensor frame
  std::vector<Eigen::Vector3d> contact_dirs_;
  double cos_contact_ = 0.0;
};

// JSON summary: counts, drops per reason, advice, coverage gaps, waypoints, estimate (s, h,
// shares), sampling-order estimate, tour gain, planning time, key options and machine settings.
nlohmann::json PlanSummaryJson(const ProbePlan& plan, const PlanOptions& options);
// The gaps as an array of CoverageGap::ToJson() (the summary's "coverage_gaps").
nlohmann::json CoverageGapsJson(const std::vector<CoverageGap>& gaps);
// Full plan (summary + every probe, plain numbers) and back, for storage. FromJson throws
// std::invalid_argument for a malformed document.
nlohmann::json PlanToJson(const ProbePlan& plan, const PlanOptions& options);
// The stage name under which a run database keeps a run's plan (PlanToJson as the artifact,
// PlanSummaryJson as its metrics).
inline constexpr const char* kPlanArtifactStage = "plan";
ProbePlan PlanFromJson(const nlohmann::json& json);

}  // namespace gs360
