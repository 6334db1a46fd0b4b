#include "plan/plan.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>
#include <nlohmann/json.hpp>
#include <numbers>
#include <sstream>
#include <unordered_map>

#include "base/field_error.h"
#include "base/format.h"
#include "base/hash.h"
#include "geometry/bvh.h"
#include "geometry/sampling.h"
#include "plan/tour.h"
#include "rig/rig_shape.h"

namespace gs360 {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kPi = std::numbers::pi;
constexpr double kGapTol = 1e-4;  // mm: "clear" means gap >= required - kGapTol everywhere

std::string Num(double v) {
  std::ostringstream os;
  os.precision(10);
  os << v;
  return os.str();
}

[[noreturn]] void BadField(const std::string& field, double value, const std::string& rule) {
  ThrowFieldError("PlanOptions." + field, value, rule);
}

void RequirePositive(const char* field, double v) {
  if (!(v > 0.0) || !std::isfinite(v)) BadField(field, v, "must be finite and > 0");
}
void RequireNonNegative(const char* field, double v) {
  if (!(v >= 0.0) || !std::isfinite(v)) BadField(field, v, "must be finite and >= 0");
}

double Round3(double v) {
  return std::round(v * 1000.0) / 1000.0;
}

// Lower bound of the signed distance to a surface inside `box`: the distance to the box from
// outside, -inf inside (the point may be inside the surface).
double BoxBound(const Eigen::AlignedBox3d& box, const Eigen::Vector3d& p) {
  return box.contains(p) ? -kInf : box.exteriorDistance(p);
}

// Quasi-uniform unit directions (Fibonacci sphere).
std::vector<Eigen::Vector3d> SphereDirections(int n) {
  std::vector<Eigen::Vector3d> dirs;
  dirs.reserve(n);
  const double golden = kPi * (3.0 - std::sqrt(5.0));
  for (int i = 0; i < n; ++i) {
    const double z = 1.0 - (2.0 * i + 1.0) / n;
    const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
    const double a = golden * i;
    dirs.emplace_back(r * std::cos(a), r * std::sin(a), z);
  }
  return dirs;
}

}  // namespace

// --- Small types ---------------------------------------------------------------------------------

namespace {

// Rounded up to 0.1 mm: a setting that is enough, printed with one decimal.
double UpTenth(double v) {
  return std::ceil(v * 10.0 - 1e-6) / 10.0;
}

std::string Fixed1(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.1f", v);
  return buf;
}

// For each machine axis the positions the tool can press do not fit in: where to put the sensor
// and how much travel it takes for all of them to fit. Empty when they all fit.
std::string TravelNumbers(const PlanReach& reach) {
  static const char* const kAxis[3] = {"x", "y", "z"};
  std::string out;
  for (int a = 0; a < 3; ++a) {
    const double top = reach.travel_min[a] + reach.max_travel_mm[a] - reach.travel_margin;
    const double bottom = reach.travel_min[a] + reach.travel_margin;
    const double over = reach.machine_max[a] - top;
    const double under = bottom - reach.machine_min[a];
    if (over <= 1e-3 && under <= 1e-3) continue;
    const double span = reach.machine_max[a] - reach.machine_min[a];
    const double room = top - bottom;
    const double more = span > room + 1e-3 ? UpTenth(span - room) : 0.0;
    const std::string axis = kAxis[a];
    // The daemon's safety envelope ([limits]) follows the travel.
    auto travel_to = [&](double extra) {
      const double travel = reach.max_travel_mm[a] + extra;
      return "[plan.machine] max_travel_mm " + axis + " to " + Fixed1(travel) + " (" +
             Fixed1(extra) + " mm more; [limits] envelope_" +
             (reach.travel_min_set ? "max " + axis + " to " + Fixed1(reach.travel_min[a] + travel)
                                   : "min " + axis + " to " + Fixed1(-travel)) +
             ")";
    };
    std::string s = "; along " + axis + " the probe's positions reach ";
    if (over > 1e-3) {
      const double d = UpTenth(over);
      s += Fixed1(d) + " mm above the top of the travel: set [rig] base_in_machine " + axis +
           " to " + Fixed1(reach.base_in_machine[a] - d) + " (" + Fixed1(d) + " mm " +
           (a == 2 ? std::string("lower") : "toward -" + axis) + ")";
      if (more > 0.0) {
        s += " and " + travel_to(more) + ": they span " + Fixed1(span) + " mm, the travel leaves " +
             Fixed1(room) + " mm";
      }
    } else {
      const double d = UpTenth(under);
      s += Fixed1(d) + " mm below the bottom of the travel: set " + travel_to(d);
      if (more == 0.0) {
        s += " or [rig] base_in_machine " + axis + " to " + Fixed1(reach.base_in_machine[a] + d) +
             " (" + Fixed1(d) + " mm " + (a == 2 ? std::string("higher") : "toward +" + axis) + ")";
      }
    }
    out += s;
  }
  return out;
}

// The highest machine z the tool may reach.
double TravelTopZ(const PlanReach& reach) {
  return reach.travel_min.z() + reach.max_travel_mm.z() - reach.travel_margin;
}

bool CannotPassOver(const PlanReach* reach) {
  return reach != nullptr && reach->travel_known &&
         reach->over_z_machine > TravelTopZ(*reach) + 1e-3;
}

std::string DropAdvice(DropReason reason, const PlanReach* reach) {
  switch (reason) {
    case DropReason::kFov:
      return "lie outside the camera's field of view: check [rig.camera] (the lens, camera_z) "
             "and that the sensor ([rig.shape] or its mesh: mm, +z along the finger, base at "
             "z = 0) is the size and in the place the camera expects";
    case DropReason::kViewAngle:
      return "are seen too edge-on from the camera: plan.max_view_angle_rad (75 deg) allows "
             "more, up to about 85 deg, at some cost in accuracy there";
    case DropReason::kFin:
      return "are hidden behind a fin: a sensor without fins needs [rig.fins] enabled = false; "
             "otherwise check the fins' inset and thickness";
    case DropReason::kGel:
      return "are hidden by the sensor's own surface as the camera sees it: check that the "
             "mesh is in the sensor frame (mm, +z along the finger, its base centred on z = 0) "
             "and [rig.camera] camera_z";
    case DropReason::kReach: {
      std::string what =
          "cannot be pressed: the ball or the stylus would hit the sensor or its base, or find "
          "no way out";
      if (reach == nullptr || reach->stylus_length_needed <= 0.0) {
        return what +
               ": check plan.press_depth, plan.travel_clearance and the stylus "
               "(plan.stylus_radius, stylus_length)";
      }
      return what + "; the stylus is too short for the lower part: plan.stylus_length = " +
             Fixed1(reach->stylus_length_needed) + " (now " + Fixed1(reach->stylus_length) +
             ", and [rig] tool_offset with it) presses down to z = " +
             Fixed1(reach->stylus_lowest_z) + " mm";
    }
    case DropReason::kTravel: {
      if (CannotPassOver(reach)) return "lie outside the machine's travel, for the same reason";
      const std::string numbers =
          reach != nullptr && reach->travel_known ? TravelNumbers(*reach) : std::string();
      if (!numbers.empty()) return "lie outside the machine's travel" + numbers;
      return "lie outside the machine's travel: check where the sensor sits ([rig] "
             "base_in_machine) and [plan.machine] max_travel_mm";
    }
  }
  return "";
}

// Said when at least 5 % of the probes will be seen too small to measure their depth well; over
// 10 % the peak target, a mean over probes, cannot be met (0.2 mm on that share alone).
std::string SmallImprintAdvice(const SmallImprints& s) {
  const double share = s.Share();
  if (s.probes == 0 || share < 0.05) return {};
  return std::to_string(s.probes) + " of " + std::to_string(s.seen) + " probes (" +
         FormatFixed(100.0 * share, 0) + " %), at z " + FormatFixed(s.z_min_mm, 1) + "-" +
         FormatFixed(s.z_max_mm, 1) + " mm, will leave imprints the camera sees in under " +
         FormatFixed(kMinImprintPixels, 0) + " px (median " + FormatFixed(s.median_px, 0) +
         " px): their peak depth is measured only to 0.1-0.3 mm, so " +
         (share > 0.1 ? "this rig cannot be expected to meet the peak target (0.05 mm, a mean "
                        "over probes)"
                      : "the peak target (0.05 mm) has little margin") +
         ". That part of the gel is far from the camera or seen edge-on; a camera nearer it, or "
         "a lens with a narrower field, shows it larger.";
}

}  // namespace

std::vector<std::string> PlanAdvice(const DropCounts& dropped, int kept, int candidates,
                                    const PlanReach* reach) {
  std::vector<std::string> advice;
  // Whatever the plan keeps, a tool that cannot pass over the sensor may find no way to a probe
  // from where the machine is when the run starts.
  if (CannotPassOver(reach)) {
    advice.push_back("The tool cannot pass over the sensor: that takes machine z = " +
                     Fixed1(reach->over_z_machine) + ", above the top of the travel (" +
                     Fixed1(TravelTopZ(*reach)) + ")" + TravelNumbers(*reach) + ".");
  }
  if (candidates <= 0 || 2 * kept >= candidates) return advice;
  std::vector<DropReason> reasons;
  for (int r = 0; r < kNumDropReasons; ++r) {
    const auto reason = static_cast<DropReason>(r);
    if (10 * dropped[reason] >= candidates) reasons.push_back(reason);
  }
  std::stable_sort(reasons.begin(), reasons.end(),
                   [&](DropReason a, DropReason b) { return dropped[a] > dropped[b]; });
  for (const DropReason reason : reasons) {
    advice.push_back(std::to_string(dropped[reason]) + " of " + std::to_string(candidates) +
                     " candidates " + DropAdvice(reason, reach) + ".");
  }
  return advice;
}

std::vector<std::string> PlanAdvice(const ProbePlan& plan) {
  const int kept = static_cast<int>(plan.probes.size());
  std::vector<std::string> advice;
  // Said of a plan sized in machine time (the rig's own limit), not of a count asked for.
  if (plan.machine_budget_s > 0.0 && kept > 0 && kept < kProbesForTargets) {
    advice.push_back(
        "This rig cannot be expected to meet the accuracy targets: " + std::to_string(kept) +
        " probes fit in plan.machine_hours = " + FormatFixed(plan.machine_budget_s / 3600.0, 2) +
        " h at [plan.machine]'s feeds, and the targets take about " +
        std::to_string(kProbesForTargets) +
        (2 * kept < plan.candidates
             ? "; most of the surface cannot be probed (below says why and what to change)."
             : ". A longer plan.machine_hours or faster feeds give more."));
  }
  for (std::string& line : PlanAdvice(plan.dropped, kept, plan.candidates, &plan.reach)) {
    advice.push_back(std::move(line));
  }
  if (std::string line = SmallImprintAdvice(plan.small_imprints); !line.empty()) {
    advice.push_back(std::move(line));
  }
  return advice;
}

double PlanEstimate::TravelShare() const {
  const double total = Total();
  return total > 0.0 ? (travel_s + retract_s) / total : 0.0;
}

double PlanEstimate::PressShare() const {
  const double total = Total();
  return total > 0.0 ? (press_s + dwell_s + host_s + reference_s) / total : 0.0;
}

double ProbePlan::TourGain() const {
  const double t = estimate.Total();
  return t > 0.0 ? sampling_order_estimate.Total() / t : 1.0;
}

void RigGeometry::Check() const {
  if (sensor_mesh.Empty()) throw std::invalid_argument("RigGeometry.sensor_mesh is empty");
  auto finite = [](const Rigid3d& t) {
    return t.rotation.coeffs().allFinite() && t.translation.allFinite();
  };
  if (!finite(cam_from_sensor))
    throw std::invalid_argument("RigGeometry.cam_from_sensor is not finite");
  if (!finite(machine_from_sensor)) {
    throw std::invalid_argument("RigGeometry.machine_from_sensor is not finite");
  }
  if (!tool_offset.allFinite())
    throw std::invalid_argument("RigGeometry.tool_offset is not finite");
  camera.Check();
}

RigGeometry MakeRigGeometry(const RigConfig& config) {
  RigShape shape = BuildRigShape(config);
  RigGeometry rig;
  rig.sensor_mesh = std::move(shape.gel);
  // For a mesh the fitted profile only places the fins; visibility and collisions use the mesh.
  if (shape.profile_is_exact) rig.profile = shape.profile;
  rig.fins = std::move(shape.fins);
  rig.camera = config.camera;
  rig.cam_from_sensor = config.cam_from_sensor();
  rig.machine_from_sensor = config.machine_from_sensor();
  rig.tool_offset = config.tool_offset;
  rig.Check();
  return rig;
}

RigGeometry MakeRigGeometry() {
  const RigConfig defaults;
  return MakeRigGeometry(defaults);
}

void PlanOptions::Check() const {
  if (probe_count < 1) BadField("probe_count", probe_count, "must be >= 1");
  if (!(machine_hours >= 0.0 && machine_hours <= 1000.0)) {
    BadField("machine_hours", machine_hours, "must be in [0, 1000]");
  }
  if (checkpoint_probes < 0) BadField("checkpoint_probes", checkpoint_probes, "must be >= 0");
  if (!(candidate_factor >= 1.0)) BadField("candidate_factor", candidate_factor, "must be >= 1");
  RequirePositive("ball_radius", ball_radius);
  RequirePositive("press_depth", press_depth);
  if (press_depth >= ball_radius) {
    BadField("press_depth", press_depth, "must be < ball_radius (" + Num(ball_radius) + ")");
  }
  RequirePositive("clearance", clearance);
  RequirePositive("stylus_radius", stylus_radius);
  if (stylus_radius >= ball_radius) {
    BadField("stylus_radius", stylus_radius, "must be < ball_radius (" + Num(ball_radius) + ")");
  }
  RequirePositive("stylus_length", stylus_length);
  if (stylus_length <= ball_radius) {
    BadField("stylus_length", stylus_length, "must be > ball_radius (" + Num(ball_radius) + ")");
  }
  RequireNonNegative("holder_radius", holder_radius);
  RequireNonNegative("holder_length", holder_length);
  RequirePositive("press_feed_mm_per_min", press_feed_mm_per_min);
  RequireNonNegative("retract_feed_mm_per_min", retract_feed_mm_per_min);
  RequireNonNegative("settle_dwell_s", settle_dwell_s);
  RequireNonNegative("capture_time_s", capture_time_s);
  RequireNonNegative("status_poll_latency_s", status_poll_latency_s);
  RequireNonNegative("host_latency_s", host_latency_s);
  if (reference_every < 0) BadField("reference_every", reference_every, "must be >= 0");
  RequireNonNegative("reference_dwell_s", reference_dwell_s);
  RequireNonNegative("fov_margin_rad", fov_margin_rad);
  RequireNonNegative("image_margin_px", image_margin_px);
  if (!(max_view_angle_rad > 0.0) || !(max_view_angle_rad <= 0.5 * kPi)) {
    BadField("max_view_angle_rad", max_view_angle_rad, "must be in (0, pi/2]");
  }
  RequireNonNegative("occlusion_tolerance_mm", occlusion_tolerance_mm);
  RequireNonNegative("travel_clearance", travel_clearance);
  if (travel_clearance > clearance) {
    BadField("travel_clearance", travel_clearance, "must be <= clearance (" + Num(clearance) + ")");
  }
  RequireNonNegative("press_stylus_clearance", press_stylus_clearance);
  if (!(contact_margin_rad >= 0.0) || !(contact_margin_rad < 0.5 * kPi)) {
    BadField("contact_margin_rad", contact_margin_rad, "must be in [0, pi/2)");
  }
  RequireNonNegative("travel_limit_margin", travel_limit_margin);
  RequireNonNegative("escape_margin", escape_margin);
  if (!(arc_step_rad > 0.0) || !(arc_step_rad <= kPi / 3.0)) {
    BadField("arc_step_rad", arc_step_rad, "must be in (0, pi/3]");
  }
  if (neighbours < 1) BadField("neighbours", neighbours, "must be >= 1");
  if (max_improvement_passes < 0) {
    BadField("max_improvement_passes", max_improvement_passes, "must be >= 0");
  }
  if (!start_machine.allFinite())
    throw std::invalid_argument("PlanOptions.start_machine is not finite");
  machine.Check();
}

// --- TravelPlanner -------------------------------------------------------------------------------

TravelPlanner::TravelPlanner(const RigGeometry& rig, const PlanOptions& options)
    : options_(options),
      distance_(rig.profile ? SurfaceDistance::FromProfile(rig.profile)
                            : SurfaceDistance::FromMesh(rig.sensor_mesh)),
      machine_from_sensor_(rig.machine_from_sensor),
      sensor_from_machine_(rig.machine_from_sensor.Inverse()),
      tool_offset_(rig.tool_offset) {
  options_.Check();
  rig.Check();
  stylus_dir_sensor_ = sensor_from_machine_.RotateDirection(Eigen::Vector3d::UnitZ()).normalized();
  vertical_axis_ = (stylus_dir_sensor_ - Eigen::Vector3d::UnitZ()).norm() < 1e-9;
  exact_stylus_ = vertical_axis_ && distance_.IsRevolution();
  const double r = options_.ball_radius;
  stylus_exit_ = std::sqrt(r * r - options_.stylus_radius * options_.stylus_radius);
  parts_.push_back({options_.stylus_radius, stylus_exit_, options_.stylus_length});
  if (options_.holder_radius > 0.0 && options_.holder_length > 0.0) {
    parts_.push_back({options_.holder_radius, options_.stylus_length,
                      options_.stylus_length + options_.holder_length});
  }
  double widest = r;
  for (Part& p : parts_) {
    p.step = std::min(p.radius, 0.5);
    p.radius_eff = std::sqrt(p.radius * p.radius + 0.25 * p.step * p.step);
    widest = std::max(widest, exact_stylus_ ? p.radius : p.radius_eff);
  }
  escape_radius_ =
      distance_.BoundingRadius() + widest + options_.travel_clearance + options_.escape_margin;
  // Highest point of the sensor in machine z; the ball above it by r + clearance + margin.
  const Eigen::AlignedBox3d& b = distance_.Bounds();
  double top = -kInf;
  for (int corner = 0; corner < 8; ++corner) {
    const Eigen::Vector3d c((corner & 1) ? b.max().x() : b.min().x(),
                            (corner & 2) ? b.max().y() : b.min().y(),
                            (corner & 4) ? b.max().z() : b.min().z());
    top = std::max(top, (machine_from_sensor_ * c).z());
  }
  over_z_machine_ = top + r + options_.travel_clearance + options_.escape_margin - tool_offset_.z();
}

Eigen::Vector3d TravelPlanner::MachineFromBall(const Eigen::Vector3d& ball_sensor) const {
  return machine_from_sensor_ * ball_sensor - tool_offset_;
}

Eigen::Vector3d TravelPlanner::BallFromMachine(const Eigen::Vector3d& machine) const {
  return sensor_from_machine_ * (machine + tool_offset_);
}

double TravelPlanner::SensorGap(const Eigen::Vector3d& ball) const {
  return std::min(distance_.Signed(ball) - options_.ball_radius, ToolGaps(ball).stylus);
}

double TravelPlanner::ObstacleDistance(const Eigen::Vector3d& s) const {
  double d = distance_.Signed(s);
  if (options_.base_is_obstacle) d = std::min(d, s.z());
  return d;
}

TravelPlanner::Gaps TravelPlanner::ToolGaps(const Eigen::Vector3d& q) const {
  Gaps g;
  g.ball = ObstacleDistance(q) - options_.ball_radius;
  g.stylus = kInf;
  const Eigen::AlignedBox3d& box = distance_.Bounds();
  for (const Part& part : parts_) {
    if (exact_stylus_) {
      // A vertical cylinder vs a solid of revolution (which contains every point closer to the
      // axis at the same height): the distance is that of the cylinder's inner edge, the
      // vertical segment at rho_e = rho - radius toward the axis, and for a vertical segment it
      // is min(distances of its end points, rho_e - the largest solid radius over its heights).
      const double rho = std::hypot(q.x(), q.y());
      const double rho_e = std::max(0.0, rho - part.radius);
      const double scale = rho > 0.0 ? rho_e / rho : 0.0;
      const Eigen::Vector3d e(q.x() * scale, q.y() * scale, q.z());
      const Eigen::Vector3d p1 = e + part.lo * Eigen::Vector3d::UnitZ();
      const Eigen::Vector3d p2 = e + part.hi * Eigen::Vector3d::UnitZ();
      double d = kInf;
      for (const Eigen::Vector3d& p : {p1, p2}) {
        // Skip the exact query when the box bound cannot lower the minimum.
        if (BoxBound(box, p) >= std::min(d, g.stylus)) continue;
        d = std::min(d, distance_.Signed(p));
      }
      const double m = distance_.MaxRadius(p1.z(), p2.z());
      if (m > -kInf) d = std::min(d, rho_e - m);
      g.stylus = std::min(g.stylus, d);
    } else {
      const double length = part.hi - part.lo;
      const int n = std::max(1, static_cast<int>(std::ceil(length / part.step)));
      const double step = length / n;
      double lipschitz = -kInf;  // lower bound from the last exact query (distance is 1-Lipschitz)
      for (int k = 0; k <= n; ++k, lipschitz -= step) {
        const Eigen::Vector3d s = q + (part.lo + step * k) * stylus_dir_sensor_;
        double bound = BoxBound(box, s);
        if (options_.base_is_obstacle) bound = std::min(bound, s.z());
        // Skip samples that cannot lower the minimum.
        if (std::max(bound, lipschitz) - part.radius_eff >= g.stylus) continue;
        lipschitz = ObstacleDistance(s);
        g.stylus = std::min(g.stylus, lipschitz - part.radius_eff);
      }
    }
  }
  return g;
}

bool TravelPlanner::SegmentClear(const Eigen::Vector3d& a, const Eigen::Vector3d& b, double gap,
                                 bool stylus_only) const {
  const double ga = GapOf(ToolGaps(a), stylus_only);
  const double gb = GapOf(ToolGaps(b), stylus_only);
  return SegmentClearRec(a, b, ga, gb, gap, stylus_only, 0);
}

bool TravelPlanner::SegmentClearRec(const Eigen::Vector3d& a, const Eigen::Vector3d& b, double ga,
                                    double gb, double gap, bool stylus_only, int depth) const {
  if (ga < gap - kGapTol || gb < gap - kGapTol) return false;
  const double length = (b - a).norm();
  // Gaps are 1-Lipschitz in the ball position: along the segment the gap is at least this.
  if (0.5 * (ga + gb - length) >= gap - kGapTol || depth >= 60) return true;
  const Eigen::Vector3d m = 0.5 * (a + b);
  const double gm = GapOf(ToolGaps(m), stylus_only);
  return SegmentClearRec(a, m, ga, gm, gap, stylus_only, depth + 1) &&
         SegmentClearRec(m, b, gm, gb, gap, stylus_only, depth + 1);
}

bool TravelPlanner::InTravel(const Eigen::Vector3d& machine) const {
  for (int a = 0; a < 3; ++a) {
    const double v = Round3(machine[a]);
    if (v > options_.machine.TravelMax()[a] - options_.travel_limit_margin + 1e-9 ||
        v < options_.machine.TravelMin()[a] + options_.travel_limit_margin - 1e-9) {
      return false;
    }
  }
  return true;
}

std::optional<Eigen::Vector3d> TravelPlanner::RadialEscape(const Eigen::Vector3d& machine) const {
  if (!vertical_axis_) return std::nullopt;
  const Eigen::Vector3d s = BallFromMachine(machine);
  const double rho = std::hypot(s.x(), s.y());
  if (rho >= escape_radius_) return machine;
  const Eigen::Vector2d dir =
      rho > 1e-9 ? Eigen::Vector2d(s.x() / rho, s.y() / rho) : Eigen::Vector2d(1.0, 0.0);
  const Eigen::Vector3d e(dir.x() * escape_radius_, dir.y() * escape_radius_, s.z());
  if (!SegmentClear(s, e, options_.travel_clearance)) return std::nullopt;
  return MachineFromBall(e);
}

std::optional<Eigen::Vector3d> TravelPlanner::UpEscape(const Eigen::Vector3d& machine) const {
  if (machine.z() >= over_z_machine_) return machine;
  const Eigen::Vector3d up(machine.x(), machine.y(), over_z_machine_);
  if (!SegmentClear(BallFromMachine(machine), BallFromMachine(up), options_.travel_clearance)) {
    return std::nullopt;
  }
  return up;
}

TravelPlanner::Node TravelPlanner::MakeNode(const Eigen::Vector3d& machine,
                                            bool filter_travel) const {
  Node node;
  node.machine = machine;
  node.ball = BallFromMachine(machine);
  node.gap = ToolGaps(node.ball).Min();
  node.radial = RadialEscape(machine);
  node.up = UpEscape(machine);
  if (filter_travel) {
    if (node.radial && !InTravel(*node.radial)) node.radial.reset();
    if (node.up && !InTravel(*node.up)) node.up.reset();
  }
  return node;
}

std::vector<Eigen::Vector3d> TravelPlanner::ArcWaypoints(const Eigen::Vector3d& a_machine,
                                                         const Eigen::Vector3d& b_machine) const {
  const Eigen::Vector3d a = BallFromMachine(a_machine), b = BallFromMachine(b_machine);
  const double pa = std::atan2(a.y(), a.x()), pb = std::atan2(b.y(), b.x());
  double delta = pb - pa;
  while (delta > kPi) delta -= 2.0 * kPi;
  while (delta <= -kPi) delta += 2.0 * kPi;
  std::vector<Eigen::Vector3d> out;
  if (std::abs(delta) < 1e-9) return out;
  const int k = std::max(1, static_cast<int>(std::ceil(std::abs(delta) / options_.arc_step_rad)));
  const double step = delta / k;
  // Vertices on the tangent lines: every chord touches the escape cylinder but never enters it.
  const double radius = escape_radius_ / std::cos(0.5 * step);
  for (int j = 1; j <= k; ++j) {
    const double f = (j - 0.5) / k;
    const double phi = pa + step * (j - 0.5);
    const Eigen::Vector3d s(radius * std::cos(phi), radius * std::sin(phi),
                            a.z() + f * (b.z() - a.z()));
    out.push_back(MachineFromBall(s));
  }
  return out;
}

double TravelPlanner::PathTimeStop(const Eigen::Vector3d& from,
                                   const std::vector<Eigen::Vector3d>& waypoints,
                                   const Eigen::Vector3d& to) const {
  double t = 0.0;
  Eigen::Vector3d at = from;
  for (const Eigen::Vector3d& w : waypoints) {
    t += RapidTime(at, w, options_.machine);
    at = w;
  }
  return t + RapidTime(at, to, options_.machine);
}

bool TravelPlanner::StraightClear(const Node& a, const Node& b) const {
  const double length = (a.ball - b.ball).norm();
  const double gap = options_.travel_clearance;
  if (a.gap < gap - kGapTol || b.gap < gap - kGapTol) return false;
  if (0.5 * (a.gap + b.gap - length) >= gap - kGapTol) return true;
  return SegmentClearRec(a.ball, b.ball, a.gap, b.gap, gap, false, 0);
}

std::optional<TravelPlanner::Route> TravelPlanner::BestRoute(const Node& a, const Node& b) const {
  if (StraightClear(a, b)) {
    return Route{{}, RapidTime(a.machine, b.machine, options_.machine)};
  }
  std::optional<Route> best;
  auto consider = [&](std::vector<Eigen::Vector3d> waypoints) {
    // Drop waypoints equal to their predecessor (or to the ends).
    std::vector<Eigen::Vector3d> w;
    Eigen::Vector3d at = a.machine;
    for (const Eigen::Vector3d& p : waypoints) {
      if ((p - at).norm() < 1e-9) continue;
      w.push_back(p);
      at = p;
    }
    while (!w.empty() && (w.back() - b.machine).norm() < 1e-9) w.pop_back();
    for (const Eigen::Vector3d& p : w) {
      if (!InTravel(p)) return;
    }
    if (!vertical_axis_) {
      // The free-space arguments need an upright sensor: check every leg.
      Eigen::Vector3d from = a.machine;
      for (std::size_t i = 0; i <= w.size(); ++i) {
        const Eigen::Vector3d to = i < w.size() ? w[i] : b.machine;
        if (!SegmentClear(BallFromMachine(from), BallFromMachine(to), options_.travel_clearance)) {
          return;
        }
        from = to;
      }
    }
    const double t = PathTimeStop(a.machine, w, b.machine);
    if (!best || t < best->time) best = Route{std::move(w), t};
  };
  // Around: out to the escape cylinder, around it, in.
  if (a.radial && b.radial) {
    std::vector<Eigen::Vector3d> w{*a.radial};
    const auto arc = ArcWaypoints(*a.radial, *b.radial);
    w.insert(w.end(), arc.begin(), arc.end());
    w.push_back(*b.radial);
    consider(std::move(w));
  }
  // Over the top: each end reaches the plane z = over_z straight up, or out then up.
  auto exits = [&](const Node& n) {
    std::vector<std::vector<Eigen::Vector3d>> e;
    if (n.machine.z() >= over_z_machine_) {
      e.push_back({});
      return e;
    }
    if (n.up) e.push_back({*n.up});
    if (n.radial && vertical_axis_) {
      const Eigen::Vector3d r = *n.radial;
      e.push_back({r, Eigen::Vector3d(r.x(), r.y(), std::max(r.z(), over_z_machine_))});
    }
    return e;
  };
  for (const auto& ea : exits(a)) {
    for (const auto& eb : exits(b)) {
      std::vector<Eigen::Vector3d> w = ea;
      w.insert(w.end(), eb.rbegin(), eb.rend());
      consider(std::move(w));
    }
  }
  return best;
}

std::optional<std::vector<Eigen::Vector3d>> TravelPlanner::Path(
    const Eigen::Vector3d& from_machine, const Eigen::Vector3d& to_machine) const {
  constexpr double kLiftExtra = 0.1;  // mm above the clearance, against rounding
  std::vector<Eigen::Vector3d> lead;
  Eigen::Vector3d from = from_machine;
  // A ball the base plane holds too close, away from the sensor (a printer's, on its bed after
  // homing): straight up first, to travel_clearance above the plane.
  if (vertical_axis_ && options_.base_is_obstacle) {
    const Eigen::Vector3d s = BallFromMachine(from);
    const double base_gap = s.z() - options_.ball_radius;
    const double surface_gap = distance_.Signed(s) - options_.ball_radius;
    if (base_gap < options_.travel_clearance && surface_gap >= 4.0 * options_.travel_clearance) {
      from.z() += options_.travel_clearance - base_gap + kLiftExtra;
      lead.push_back(from);
    }
  }
  if (!InTravel(from)) {
    const Eigen::Vector3d lo = options_.machine.TravelMin().array() + options_.travel_limit_margin;
    const Eigen::Vector3d hi = options_.machine.TravelMax().array() - options_.travel_limit_margin;
    const Eigen::Vector3d inside = from.cwiseMax(lo).cwiseMin(hi);
    const bool in_hard_travel =
        (from.array() >= options_.machine.TravelMin().array() - 1e-9).all() &&
        (from.array() <= options_.machine.TravelMax().array() + 1e-9).all();
    if (in_hard_travel && (lo.array() <= hi.array()).all() &&
        SegmentClear(BallFromMachine(from), BallFromMachine(inside), options_.travel_clearance)) {
      lead.push_back(inside);
      from = inside;
    }
  }
  const Node a = MakeNode(from, true);
  const Node b = MakeNode(to_machine, true);
  auto route = BestRoute(a, b);
  if (!route) return std::nullopt;
  lead.insert(lead.end(), route->waypoints.begin(), route->waypoints.end());
  return lead;
}

// --- Planning ------------------------------------------------------------------------------------

namespace {

struct Candidate {
  int sample_index = 0;
  Eigen::Vector3d point = Eigen::Vector3d::Zero();
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();
  Eigen::Vector3d approach_machine = Eigen::Vector3d::Zero();
  Eigen::Vector3d press_machine = Eigen::Vector3d::Zero();
};

}  // namespace

ProbePointFilter::ProbePointFilter(const RigGeometry& rig, const PlanOptions& options)
    : options_(options),
      profile_(rig.profile),
      cam_from_sensor_(rig.cam_from_sensor),
      travel_(rig, options),
      camera_(rig.camera),
      sensor_bvh_(rig.sensor_mesh),
      contact_dirs_(SphereDirections(96)) {
  if (!rig.fins.Empty()) fins_bvh_.emplace(rig.fins);
  camera_center_ = rig.cam_from_sensor.Inverse().translation;
  const double r = options.ball_radius;
  cos_contact_ = std::cos(std::acos((r - options.press_depth) / r) + options.contact_margin_rad);
}

ProbePointFilter::Result ProbePointFilter::Classify(const Eigen::Vector3d& point,
                                                    const Eigen::Vector3d& normal) const {
  Result res;
  Eigen::Vector3d p = point, n = normal.normalized();
  if (options_.snap_to_profile && profile_ && travel_.Distance().IsRevolution()) {
    const auto c = travel_.Distance().ClosestPoint(p);
    p = c.point;
    n = c.normal;
  }
  res.point = p;
  res.normal = n;
  auto drop = [&](DropReason r) {
    res.reason = r;
    return res;
  };
  // Field of view.
  const Eigen::Vector3d x_cam = cam_from_sensor_ * p;
  const auto uv = camera_.CamToPixel(x_cam);
  if (!uv) return drop(DropReason::kFov);
  const double theta = std::atan2(x_cam.head<2>().norm(), x_cam.z());
  if (theta > camera_.MaxValidTheta() - options_.fov_margin_rad) return drop(DropReason::kFov);
  const double m = options_.image_margin_px;
  if (uv->x() < m - 0.5 || uv->y() < m - 0.5 || uv->x() > camera_.width() - 0.5 - m ||
      uv->y() > camera_.height() - 0.5 - m) {
    return drop(DropReason::kFov);
  }
  // View angle.
  const Eigen::Vector3d to_point = p - camera_center_;
  const double dist = to_point.norm();
  if (!(dist > 0.0)) return drop(DropReason::kFov);
  const Eigen::Vector3d d = to_point / dist;
  if (n.dot(d) < std::cos(options_.max_view_angle_rad)) return drop(DropReason::kViewAngle);
  // Occlusion by the fins, then by the gel itself.
  const Ray ray{camera_center_, d};
  if (fins_bvh_ && fins_bvh_->Occluded(ray, 0.0, dist)) return drop(DropReason::kFin);
  const double tol = options_.occlusion_tolerance_mm + 1e-3 * dist;
  if (dist > tol && sensor_bvh_.Occluded(ray, 0.0, dist - tol)) return drop(DropReason::kGel);
  // Reach.
  const double r = options_.ball_radius;
  const Eigen::Vector3d approach = p + n * (r + options_.clearance);
  const Eigen::Vector3d press = p + n * (r - options_.press_depth);
  const auto ga = travel_.ToolGaps(approach);
  if (ga.Min() < options_.travel_clearance - kGapTol) return drop(DropReason::kReach);
  const auto gp = travel_.ToolGaps(press);
  // At full depth the ball must penetrate only at p (not deeper elsewhere) ...
  if (gp.ball < -options_.press_depth - 0.01) return drop(DropReason::kReach);
  if (options_.base_is_obstacle && press.z() - r < 0.0) return drop(DropReason::kReach);
  if (gp.stylus < options_.press_stylus_clearance - kGapTol) return drop(DropReason::kReach);
  if (!travel_.SegmentClear(approach, press, options_.press_stylus_clearance, true)) {
    return drop(DropReason::kReach);
  }
  // ... and touch nothing else: ball points away from the contact cap are outside.
  for (const Eigen::Vector3d& w : contact_dirs_) {
    if (-w.dot(n) >= cos_contact_) continue;
    if (travel_.ObstacleDistance(press + r * w) < -1e-3) return drop(DropReason::kReach);
  }
  // A way out: radially or straight up.
  res.approach_machine = travel_.MachineFromBall(approach);
  res.press_machine = travel_.MachineFromBall(press);
  TravelPlanner::Node node = travel_.MakeNode(res.approach_machine, false);
  if (!node.radial && !node.up) return drop(DropReason::kReach);
  // Travel limits (a drop keeps every escape: the plan's reach measures how far out they are).
  res.node = node;
  if (!travel_.InTravel(res.approach_machine) || !travel_.InTravel(res.press_machine)) {
    return drop(DropReason::kTravel);
  }
  if (node.radial && !travel_.InTravel(*node.radial)) node.radial.reset();
  if (node.up && !travel_.InTravel(*node.up)) node.up.reset();
  if (!node.radial && !node.up) return drop(DropReason::kTravel);
  res.node = std::move(node);
  return res;
}

namespace {

// Travel times between nodes (index n = the start), cached for the pairs that needed more than
// the quick clearance bound.
class RouteCache {
 public:
  RouteCache(const TravelPlanner& travel, const std::vector<TravelPlanner::Node>& nodes,
             const TravelPlanner::Node& start)
      : travel_(travel), nodes_(nodes), start_(start) {}

  const TravelPlanner::Node& NodeAt(int i) const {
    return i == static_cast<int>(nodes_.size()) ? start_ : nodes_[i];
  }

  double Time(int i, int j) {
    if (i == j) return 0.0;
    const std::uint64_t key = Key(i, j);
    if (auto it = cache_.find(key); it != cache_.end()) return it->second;
    const auto& a = NodeAt(std::min(i, j));
    const auto& b = NodeAt(std::max(i, j));
    double t = 0.0;
    const double length = (a.ball - b.ball).norm();
    const double gap = travel_.Options().travel_clearance;
    if (a.gap >= gap && b.gap >= gap && 0.5 * (a.gap + b.gap - length) >= gap) {
      t = RapidTime(a.machine, b.machine, travel_.Options().machine);
      return t;  // quick, not cached
    }
    const auto route = travel_.BestRoute(a, b);
    t = route ? route->time : 1e9;  // no route: never chosen if avoidable (checked later)
    cache_.emplace(key, t);
    return t;
  }

  double Lower(int i, int j) const {
    return RapidTime(NodeAt(i).machine, NodeAt(j).machine, travel_.Options().machine);
  }

 private:
  static std::uint64_t Key(int i, int j) {
    const auto lo = static_cast<std::uint64_t>(std::min(i, j));
    const auto hi = static_cast<std::uint64_t>(std::max(i, j));
    return (lo << 32) | hi;
  }
  const TravelPlanner& travel_;
  const std::vector<TravelPlanner::Node>& nodes_;
  const TravelPlanner::Node& start_;
  std::unordered_map<std::uint64_t, double> cache_;
};

// Builds the probes in `order` with their travel waypoints. Throws when two consecutive
// positions have no collision-free route.
std::vector<PlannedProbe> BuildProbes(const std::vector<int>& order,
                                      const std::vector<Candidate>& kept,
                                      const std::vector<TravelPlanner::Node>& nodes,
                                      const TravelPlanner::Node& start, const TravelPlanner& travel,
                                      const PlanOptions& options, const ProbePlan& plan,
                                      std::vector<Eigen::Vector3d>* park) {
  // What would change it (a finger beyond the machine's reach: the tool cannot pass over it).
  auto why = [&]() {
    std::string s;
    for (const std::string& line : PlanAdvice(plan.dropped, 0, plan.candidates, &plan.reach)) {
      s += (s.empty() ? ". " : " ") + line;
    }
    return s;
  };
  std::vector<PlannedProbe> probes;
  probes.reserve(order.size());
  const TravelPlanner::Node* prev = &start;
  int prev_index = -1;
  for (std::size_t k = 0; k < order.size(); ++k) {
    const int i = order[k];
    const Candidate& c = kept[i];
    PlannedProbe p;
    p.plan_index = static_cast<int>(k);
    p.sample_index = c.sample_index;
    p.point_sensor = c.point;
    p.normal_sensor = c.normal;
    p.approach_machine = c.approach_machine;
    p.press_machine = c.press_machine;
    p.retract_machine = c.approach_machine;
    p.reference_before =
        k == 0 || (options.reference_every > 0 && k % options.reference_every == 0);
    const auto route = travel.BestRoute(*prev, nodes[i]);
    if (!route) {
      throw std::runtime_error("MakeProbePlan: no collision-free travel from " +
                               (prev_index < 0 ? std::string("the start position")
                                               : "probe " + std::to_string(prev_index)) +
                               " to probe " + std::to_string(k) + " (sample " +
                               std::to_string(c.sample_index) + ")" + why());
    }
    p.travel_machine = route->waypoints;
    probes.push_back(std::move(p));
    prev = &nodes[i];
    prev_index = static_cast<int>(k);
  }
  park->clear();
  if (options.return_to_start && !order.empty()) {
    const auto route = travel.BestRoute(*prev, start);
    if (!route) {
      throw std::runtime_error(
          "MakeProbePlan: no collision-free travel from the last probe back "
          "to the start position" +
          why());
    }
    *park = route->waypoints;
    park->push_back(start.machine);
  }
  return probes;
}

std::string OptionsHash(const RigGeometry& rig, const PlanOptions& o) {
  Hasher h;
  h.Add("gs360.ProbePlan.v1");
  h.AddPod(rig.sensor_mesh.Hash());
  h.AddPod(rig.fins.Hash());
  h.Add(rig.profile ? rig.profile->Describe() : std::string("mesh"));
  const auto& c = rig.camera;
  h.AddPod(c.width).AddPod(c.height);
  for (double v : {c.fx, c.fy, c.cx, c.cy, c.skew, c.k[0], c.k[1], c.k[2], c.k[3], c.max_theta}) {
    h.AddDouble(v);
  }
  for (const Rigid3d* t : {&rig.cam_from_sensor, &rig.machine_from_sensor}) {
    for (int i = 0; i < 4; ++i) h.AddDouble(t->rotation.coeffs()[i]);
    for (int i = 0; i < 3; ++i) h.AddDouble(t->translation[i]);
  }
  for (int i = 0; i < 3; ++i) h.AddDouble(rig.tool_offset[i]);
  h.AddPod(o.probe_count).AddPod(static_cast<int>(o.count_is_kept)).AddPod(o.seed);
  // Only when set, so that the plans stored before the option keep their hash.
  if (o.machine_hours > 0.0) h.AddDouble(o.machine_hours);
  for (double v : {o.candidate_factor,
                   o.ball_radius,
                   o.press_depth,
                   o.clearance,
                   o.stylus_radius,
                   o.stylus_length,
                   o.holder_radius,
                   o.holder_length,
                   o.press_feed_mm_per_min,
                   o.retract_feed_mm_per_min,
                   o.settle_dwell_s,
                   o.capture_time_s,
                   o.status_poll_latency_s,
                   o.host_latency_s,
                   o.reference_dwell_s,
                   o.fov_margin_rad,
                   o.image_margin_px,
                   o.max_view_angle_rad,
                   o.occlusion_tolerance_mm,
                   o.travel_clearance,
                   o.press_stylus_clearance,
                   o.contact_margin_rad,
                   o.travel_limit_margin,
                   o.escape_margin,
                   o.arc_step_rad,
                   o.machine.junction_deviation_mm}) {
    h.AddDouble(v);
  }
  h.AddPod(static_cast<int>(o.snap_to_profile)).AddPod(static_cast<int>(o.base_is_obstacle));
  h.AddPod(o.reference_every).AddPod(static_cast<int>(o.optimise_order)).AddPod(o.neighbours);
  h.AddPod(o.max_improvement_passes).AddPod(static_cast<int>(o.junction_model));
  // Only when set, so that the plans stored before the option keep their hash.
  if (o.checkpoint_probes > 0) h.AddPod(o.checkpoint_probes);
  h.AddPod(static_cast<int>(o.return_to_start)).AddPod(o.machine.planner_blocks);
  for (int i = 0; i < 3; ++i) {
    h.AddDouble(o.start_machine[i]).AddDouble(o.machine.max_rate_mm_per_min[i]);
    h.AddDouble(o.machine.acceleration_mm_per_s2[i]).AddDouble(o.machine.max_travel_mm[i]);
  }
  if (o.machine.travel_min_mm) {  // as checkpoint_probes: older plans keep their hash
    for (int i = 0; i < 3; ++i) h.AddDouble((*o.machine.travel_min_mm)[i]);
  }
  return h.Hex();
}

// The tally of where candidates are kept, its cells sized to hold about six candidates each
// (finer cells would call noise a gap), at least 1 mm tall, at most a quarter of the sensor.
CoverageTally CoverageFor(const RigGeometry& rig, const PlanOptions& options) {
  const double height = std::max(rig.sensor_mesh.Bounds().max().z(), 1e-3);
  CoverageOptions o;
  const double expected = static_cast<double>(options.probe_count) *
                          (options.count_is_kept ? options.candidate_factor : 1);
  o.band_mm = std::clamp(height * o.sectors * 6.0 / std::max(expected, 1.0), 1.0,
                         std::max(1.0, height / 4.0));
  o.min_candidates = 4;
  return CoverageTally(height, o);
}

}  // namespace

namespace {

// What PlanReach is measured from: the machine positions of the candidates the tool can press
// (kept or dropped for travel), and the candidates dropped for reach.
struct ReachTally {
  Eigen::AlignedBox3d machine;
  std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>> reach_dropped;  // point, normal

  void Add(const ProbePointFilter::Result& res) {
    if (res.reason == DropReason::kReach) reach_dropped.emplace_back(res.point, res.normal);
    if (res.reason && *res.reason != DropReason::kTravel) return;
    machine.extend(res.approach_machine);
    machine.extend(res.press_machine);
    if (res.node.radial) {
      machine.extend(*res.node.radial);
    } else if (res.node.up) {
      machine.extend(*res.node.up);
    }
  }
};

// Which of `points` (point, normal) a stylus of `length` mm reaches: not dropped for reach.
std::vector<char> StylusReaches(
    const RigGeometry& rig, const PlanOptions& options, double length,
    const std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>>& points) {
  PlanOptions o = options;
  o.stylus_length = length;
  const ProbePointFilter filter(rig, o);
  std::vector<char> reaches(points.size());
  for (std::size_t i = 0; i < points.size(); ++i) {
    reaches[i] = filter.Classify(points[i].first, points[i].second).reason != DropReason::kReach;
  }
  return reaches;
}

// PlanReach's stylus numbers. A stylus that holds its holder above the sensor's top from any
// ball above the base presses every candidate that a longer stylus can; the lowest of those are
// found going up from the lowest candidate dropped for reach, and the shortest stylus that
// presses them by bisection (a longer stylus only lifts the holder). Each length is a filter of
// its own, and a long stylus makes a point slow to classify (against a mesh, milliseconds): only
// a few points are tried.
void MeasureStylus(const RigGeometry& rig, const PlanOptions& options, const ReachTally& tally,
                   PlanReach* reach) {
  constexpr std::size_t kLowest = 8;      // the band the length is found for
  constexpr std::size_t kMaxTried = 400;  // from the bottom, before giving up
  reach->stylus_length = options.stylus_length;
  const double top = std::max(rig.sensor_mesh.Bounds().max().z(), 0.0);
  const double longest = std::ceil(
      std::max(options.stylus_length + 1.0, top + options.ball_radius + options.clearance +
                                                options.travel_clearance + options.escape_margin));
  auto dropped = tally.reach_dropped;
  std::stable_sort(dropped.begin(), dropped.end(),
                   [](const auto& a, const auto& b) { return a.first.z() < b.first.z(); });
  PlanOptions long_options = options;
  long_options.stylus_length = longest;
  const ProbePointFilter long_filter(rig, long_options);
  std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>> lowest;
  for (std::size_t i = 0; i < dropped.size() && i < kMaxTried; ++i) {
    const auto& p = dropped[i];
    if (!lowest.empty() &&
        (lowest.size() >= kLowest || p.first.z() > lowest.front().first.z() + 1.0)) {
      break;
    }
    if (long_filter.Classify(p.first, p.second).reason != DropReason::kReach) lowest.push_back(p);
  }
  if (lowest.empty()) return;
  double lo = options.stylus_length, hi = longest;  // lo does not press them all, hi does
  while (hi - lo > 1.0) {
    const double mid = std::floor(0.5 * (lo + hi));
    const std::vector<char> r = StylusReaches(rig, options, mid, lowest);
    (std::count(r.begin(), r.end(), 0) == 0 ? hi : lo) = mid;
  }
  reach->stylus_length_needed = hi;
  reach->stylus_lowest_z = lowest.front().first.z();
}

void MeasureReach(const RigGeometry& rig, const PlanOptions& options, const ReachTally& tally,
                  const TravelPlanner& travel, ProbePlan* plan) {
  PlanReach& reach = plan->reach;
  if (!tally.machine.isEmpty()) {
    reach.travel_known = true;
    reach.machine_min = tally.machine.min();
    reach.machine_max = tally.machine.max();
    // The travel between far sides of the sensor and from the start passes over it.
    reach.over_z_machine = travel.OverZMachine();
    reach.machine_max.z() = std::max(reach.machine_max.z(), reach.over_z_machine);
    reach.max_travel_mm = options.machine.max_travel_mm;
    reach.travel_min = options.machine.TravelMin();
    reach.travel_min_set = options.machine.travel_min_mm.has_value();
    reach.travel_margin = options.travel_limit_margin;
    reach.base_in_machine = rig.machine_from_sensor.translation;
  }
  // Only when the advice would say it (it takes a few filters of its own).
  const int kept = plan->candidates - plan->dropped.Total();
  if (10 * plan->dropped[DropReason::kReach] >= plan->candidates && 2 * kept < plan->candidates) {
    MeasureStylus(rig, options, tally, &reach);
  }
}

// The blue-noise candidates through the filters: the kept ones with their travel nodes, and the
// plan's candidate count, drop counts, coverage gaps and reach. Throws std::runtime_error when
// none is kept, with what would change that.
void SampleCandidates(const RigGeometry& rig, const PlanOptions& options,
                      const ProbePointFilter& filter, ProbePlan* plan_out,
                      std::vector<Candidate>* kept_out,
                      std::vector<TravelPlanner::Node>* nodes_out) {
  ProbePlan& plan = *plan_out;
  std::vector<Candidate>& kept = *kept_out;
  std::vector<TravelPlanner::Node>& nodes = *nodes_out;
  CoverageTally coverage = CoverageFor(rig, options);
  ReachTally reach;
  auto add = [&](const SurfaceSample& s, bool count_drops) {
    auto res = filter.Classify(s.point, s.normal);
    if (count_drops) {
      coverage.Add(s.point, res.reason);
      reach.Add(res);
    }
    if (res.reason) {
      if (count_drops) ++plan.dropped[*res.reason];
      return;
    }
    Candidate c;
    c.sample_index = static_cast<int>(kept.size());
    c.point = res.point;
    c.normal = res.normal;
    c.approach_machine = res.approach_machine;
    c.press_machine = res.press_machine;
    kept.push_back(c);
    nodes.push_back(std::move(res.node));
  };
  BlueNoiseOptions bn;
  bn.count = options.probe_count;
  bn.seed = options.seed;
  bn.candidate_factor = options.candidate_factor;
  if (options.count_is_kept) {
    // Sample only where every filter passes; count the rejected draws.
    const auto samples = SampleBlueNoise(rig.sensor_mesh, bn, [&](const SurfaceSample& s) {
      ++plan.candidates;
      const auto res = filter.Classify(s.point, s.normal);
      coverage.Add(s.point, res.reason);
      reach.Add(res);
      if (res.reason) ++plan.dropped[*res.reason];
      return !res.reason.has_value();
    });
    for (const SurfaceSample& s : samples) add(s, false);
  } else {
    const auto samples = SampleBlueNoise(rig.sensor_mesh, bn);
    plan.candidates = static_cast<int>(samples.size());
    for (const SurfaceSample& s : samples) add(s, true);
  }
  plan.coverage_gaps = coverage.Gaps();
  MeasureReach(rig, options, reach, filter.travel(), &plan);
  if (kept.empty()) {
    std::ostringstream os;
    os << "MakeProbePlan: no probe point survives the filters (" << plan.candidates
       << " candidates;";
    for (int r = 0; r < kNumDropReasons; ++r) {
      os << " " << DropReasonName(static_cast<DropReason>(r)) << " " << plan.dropped.counts[r];
    }
    os << ")";
    for (const std::string& line : PlanAdvice(plan)) os << " " << line;
    throw std::runtime_error(os.str());
  }
}

// One tour over every kept probe; the nearest-neighbour tour's estimate goes to the plan's
// report when the local search runs.
std::vector<int> TourOrder(const std::vector<Candidate>& kept, const PlanOptions& options,
                           const TourOptions& tour_options, RouteCache* cache,
                           const std::vector<TravelPlanner::Node>& nodes,
                           const TravelPlanner::Node& start, const TravelPlanner& travel,
                           ProbePlan* plan) {
  const int n = static_cast<int>(kept.size());
  std::vector<Eigen::Vector3d> positions(n);
  for (int i = 0; i < n; ++i) positions[i] = kept[i].approach_machine;
  const auto time = [&](int i, int j) { return cache->Time(i, j); };
  const auto lower = [&](int i, int j) { return cache->Lower(i, j); };
  const TourResult tour = SolveTour(positions, options.start_machine, time, lower, tour_options);
  if (options.optimise_order) {
    TourOptions nn_only = tour_options;
    nn_only.optimise = false;
    const TourResult nn = SolveTour(positions, options.start_machine, time, lower, nn_only);
    std::vector<Eigen::Vector3d> nn_park;
    const auto probes = BuildProbes(nn.order, kept, nodes, start, travel, options, *plan, &nn_park);
    plan->nearest_neighbour_s = EstimatePlan(probes, nn_park, options).Total();
  }
  return tour.order;
}

// options.checkpoint_probes > 0: the kept probes in their farthest-point order, cut into rounds
// of that many, each round toured on its own from where the last one ended (the first from the
// start position).
std::vector<int> RoundsOrder(const std::vector<Candidate>& kept, const PlanOptions& options,
                             const TourOptions& tour_options, RouteCache* cache) {
  const int n = static_cast<int>(kept.size());
  std::vector<Eigen::Vector3d> points(n);
  for (int i = 0; i < n; ++i) points[i] = kept[i].point;
  const std::vector<int> progressive = FarthestPointOrder(points, 0);
  std::vector<int> order;
  order.reserve(static_cast<std::size_t>(n));
  int depot = n;  // RouteCache's index of the start position
  for (int first = 0; first < n; first += options.checkpoint_probes) {
    const int last = std::min(n, first + options.checkpoint_probes);
    const std::vector<int> round(progressive.begin() + first, progressive.begin() + last);
    const int m = static_cast<int>(round.size());
    // Local index m is the round's depot: the last probe toured, or the start.
    const auto global = [&](int i) { return i == m ? depot : round[static_cast<std::size_t>(i)]; };
    std::vector<Eigen::Vector3d> positions(m);
    for (int i = 0; i < m; ++i) positions[i] = kept[round[i]].approach_machine;
    const Eigen::Vector3d from =
        depot == n ? options.start_machine : kept[static_cast<std::size_t>(depot)].approach_machine;
    const TourResult tour = SolveTour(
        positions, from, [&](int i, int j) { return cache->Time(global(i), global(j)); },
        [&](int i, int j) { return cache->Lower(global(i), global(j)); }, tour_options);
    for (const int i : tour.order) order.push_back(round[static_cast<std::size_t>(i)]);
    depot = order.back();
  }
  return order;
}

}  // namespace

namespace {

// The plan for exactly options.probe_count candidates (options.machine_hours ignored).
ProbePlan PlanForCandidates(const RigGeometry& rig, const PlanOptions& options) {
  const auto t0 = std::chrono::steady_clock::now();
  const ProbePointFilter filter(rig, options);
  const TravelPlanner& travel = filter.travel();

  ProbePlan plan;
  plan.start_machine = options.start_machine;
  plan.options_hash = OptionsHash(rig, options);

  std::vector<Candidate> kept;
  std::vector<TravelPlanner::Node> nodes;
  SampleCandidates(rig, options, filter, &plan, &kept, &nodes);

  const TravelPlanner::Node start = travel.MakeNode(options.start_machine, true);
  const int n = static_cast<int>(kept.size());

  // Sampling order (the baseline).
  std::vector<int> sampling(n);
  for (int i = 0; i < n; ++i) sampling[i] = i;
  std::vector<Eigen::Vector3d> park;
  {
    const auto probes = BuildProbes(sampling, kept, nodes, start, travel, options, plan, &park);
    plan.sampling_order_estimate = EstimatePlan(probes, park, options);
  }

  // The tour, or the rounds.
  RouteCache cache(travel, nodes, start);
  TourOptions tour_options;
  tour_options.neighbours = options.neighbours;
  tour_options.max_passes = options.max_improvement_passes;
  tour_options.optimise = options.optimise_order;
  plan.checkpoint_probes = options.checkpoint_probes;
  std::vector<int> order;
  if (options.checkpoint_probes > 0) {
    order = RoundsOrder(kept, options, tour_options, &cache);
  } else {
    order = TourOrder(kept, options, tour_options, &cache, nodes, start, travel, &plan);
  }

  plan.probes = BuildProbes(order, kept, nodes, start, travel, options, plan, &park);
  plan.park_machine = park;
  plan.estimate = EstimatePlan(plan.probes, plan.park_machine, options);
  if (!options.optimise_order || options.checkpoint_probes > 0) {
    plan.nearest_neighbour_s = plan.estimate.Total();
  }
  // Never worse than the sampling order (possible only for tiny plans with junction effects),
  // unless the rounds are asked for: they are worth their time.
  if (options.checkpoint_probes == 0 &&
      plan.estimate.Total() > plan.sampling_order_estimate.Total()) {
    plan.probes = BuildProbes(sampling, kept, nodes, start, travel, options, plan, &park);
    plan.park_machine = park;
    plan.estimate = plan.sampling_order_estimate;
  }
  for (const PlannedProbe& p : plan.probes) {
    plan.waypoints += static_cast<int>(p.travel_machine.size());
    if (!p.travel_machine.empty()) ++plan.detoured_moves;
  }
  CheckTravel(plan, options.machine, 0.0);
  std::vector<Eigen::Vector3d> points, normals;
  for (const PlannedProbe& p : plan.probes) {
    points.push_back(p.point_sensor);
    normals.push_back(p.normal_sensor);
  }
  plan.small_imprints = FindSmallImprints(FisheyeCamera(rig.camera), rig.cam_from_sensor, points,
                                          normals, options.ball_radius, options.press_depth);
  plan.planning_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return plan;
}

// The plan sized to options.machine_hours: the machine time grows about in proportion to the
// candidates drawn (the probes kept are a fixed share of them, the tour's legs shorten slowly),
// so each draw scales the count by budget / estimate, aiming a little short, until the estimate
// lands in [90 %, 100 %] of the budget. Every draw is a whole plan: blue noise over the surface
// at that density, not a cut of a longer tour.
ProbePlan PlanForMachineTime(const RigGeometry& rig, const PlanOptions& options) {
  const auto t0 = std::chrono::steady_clock::now();
  const double budget_s = options.machine_hours * 3600.0;
  const double max_count = 8.0 * options.probe_count;
  PlanOptions o = options;
  o.machine_hours = 0.0;
  ProbePlan plan = PlanForCandidates(rig, o);
  for (int draw = 0; draw < 6; ++draw) {
    const double total = std::max(plan.estimate.Total(), 1.0);
    const bool short_of_it = total < 0.9 * budget_s && o.probe_count < max_count;
    if (!short_of_it && total <= budget_s) break;
    const double count = std::clamp(o.probe_count * 0.97 * budget_s / total, 1.0, max_count);
    const int next = static_cast<int>(std::floor(count));
    if (next == o.probe_count) break;
    o.probe_count = next;
    plan = PlanForCandidates(rig, o);
  }
  // Still over (a plan that barely shrinks per candidate): the candidates that fit, at most.
  while (plan.estimate.Total() > budget_s && o.probe_count > 1) {
    o.probe_count = std::max(1, static_cast<int>(o.probe_count * 0.95));
    plan = PlanForCandidates(rig, o);
  }
  plan.options_hash = OptionsHash(rig, options);
  plan.machine_budget_s = budget_s;
  plan.planning_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return plan;
}

}  // namespace

ProbePlan MakeProbePlan(const RigGeometry& rig, const PlanOptions& options) {
  options.Check();
  rig.Check();
  return options.machine_hours > 0.0 ? PlanForMachineTime(rig, options)
                                     : PlanForCandidates(rig, options);
}

// --- Estimate ------------------------------------------------------------------------------------

PlanEstimate EstimatePlan(const std::vector<PlannedProbe>& probes,
                          const std::vector<Eigen::Vector3d>& park_machine,
                          const PlanOptions& options) {
  enum Kind { kTravelMove, kPressMove, kRetractMove };
  PlanEstimate est;
  const MachineSettings& settings = options.machine;
  const double host =
      std::max(options.capture_time_s, options.status_poll_latency_s) + options.host_latency_s;
  Eigen::Vector3d group_start = options.start_machine;
  Eigen::Vector3d at = options.start_machine;
  std::vector<Move> moves;
  std::vector<Kind> kinds;
  auto add = [&](const Eigen::Vector3d& target, double feed, Kind kind) {
    if ((target - at).norm() == 0.0) return;  // GRBL drops zero-length blocks
    moves.push_back(Move{target, feed});
    kinds.push_back(kind);
    at = target;
  };
  auto flush = [&]() {
    const auto blocks = PlanPath(group_start, moves, settings, options.junction_model);
    for (std::size_t i = 0; i < blocks.size(); ++i) {
      switch (kinds[i]) {
        case kTravelMove:
          est.travel_s += blocks[i].time;
          break;
        case kPressMove:
          est.press_s += blocks[i].time;
          break;
        case kRetractMove:
          est.retract_s += blocks[i].time;
          break;
      }
    }
    moves.clear();
    kinds.clear();
    group_start = at;
  };
  for (std::size_t k = 0; k < probes.size(); ++k) {
    const PlannedProbe& p = probes[k];
    if (k > 0) add(probes[k - 1].retract_machine, options.retract_feed_mm_per_min, kRetractMove);
    for (const Eigen::Vector3d& w : p.travel_machine) add(w, 0.0, kTravelMove);
    add(p.approach_machine, 0.0, kTravelMove);
    if (p.reference_before) {
      flush();
      est.reference_s += options.reference_dwell_s + host;
    }
    add(p.press_machine, options.press_feed_mm_per_min, kPressMove);
    flush();
    est.dwell_s += options.settle_dwell_s;
    est.host_s += host;
  }
  if (!probes.empty()) {
    add(probes.back().retract_machine, options.retract_feed_mm_per_min, kRetractMove);
    for (const Eigen::Vector3d& w : park_machine) add(w, 0.0, kTravelMove);
    flush();
  }
  return est;
}

// --- Travel check --------------------------------------------------------------------------------

void CheckTravel(const ProbePlan& plan, const MachineSettings& settings, double margin) {
  static const char kAxis[3] = {'X', 'Y', 'Z'};
  auto check = [&](const Eigen::Vector3d& m, int plan_index, const std::string& what) {
    for (int a = 0; a < 3; ++a) {
      const double v = Round3(m[a]);
      const double lo = settings.TravelMin()[a] + margin, hi = settings.TravelMax()[a] - margin;
      if (v < lo - 1e-9 || v > hi + 1e-9 || !std::isfinite(v)) {
        std::ostringstream os;
        os.setf(std::ios::fixed);
        os.precision(3);
        os << (plan_index >= 0 ? "probe " + std::to_string(plan_index) : std::string("park path"))
           << " " << what << ": " << kAxis[a] << " = " << v << " mm is outside the travel [" << lo
           << ", " << hi << "] (travel " << settings.max_travel_mm[a] << " from "
           << settings.TravelMin()[a] << ", margin " << margin << ")";
        throw TravelLimitError(os.str(), plan_index, a);
      }
    }
  };
  for (const PlannedProbe& p : plan.probes) {
    for (std::size_t w = 0; w < p.travel_machine.size(); ++w) {
      check(p.travel_machine[w], p.plan_index, "travel waypoint " + std::to_string(w));
    }
    check(p.approach_machine, p.plan_index, "approach");
    check(p.press_machine, p.plan_index, "press");
    check(p.retract_machine, p.plan_index, "retract");
  }
  for (std::size_t w = 0; w + 1 < plan.park_machine.size(); ++w) {
    check(plan.park_machine[w], -1, "waypoint " + std::to_string(w));
  }
}

// --- JSON ----------------------------------------------------------------------------------------

namespace {

nlohmann::json EstimateJson(const PlanEstimate& e) {
  return {{"total_s", e.Total()},
          {"hours", e.Hours()},
          {"travel_s", e.travel_s},
          {"press_s", e.press_s},
          {"retract_s", e.retract_s},
          {"dwell_s", e.dwell_s},
          {"host_s", e.host_s},
          {"reference_s", e.reference_s},
          {"travel_share", e.TravelShare()},
          {"press_share", e.PressShare()}};
}

PlanEstimate EstimateFromJson(const nlohmann::json& j) {
  PlanEstimate e;
  e.travel_s = j.at("travel_s").get<double>();
  e.press_s = j.at("press_s").get<double>();
  e.retract_s = j.at("retract_s").get<double>();
  e.dwell_s = j.at("dwell_s").get<double>();
  e.host_s = j.at("host_s").get<double>();
  e.reference_s = j.at("reference_s").get<double>();
  return e;
}

nlohmann::json Vec(const Eigen::Vector3d& v) {
  return nlohmann::json::array({v.x(), v.y(), v.z()});
}

Eigen::Vector3d VecFrom(const nlohmann::json& j) {
  if (!j.is_array() || j.size() != 3) throw std::invalid_argument("expected [x, y, z]");
  return {j[0].get<double>(), j[1].get<double>(), j[2].get<double>()};
}

}  // namespace

nlohmann::json CoverageGapsJson(const std::vector<CoverageGap>& gaps) {
  nlohmann::json out = nlohmann::json::array();
  for (const CoverageGap& g : gaps) out.push_back(g.ToJson());
  return out;
}

nlohmann::json PlanSummaryJson(const ProbePlan& plan, const PlanOptions& options) {
  nlohmann::json drops = nlohmann::json::object();
  for (int r = 0; r < kNumDropReasons; ++r) {
    drops[std::string(DropReasonName(static_cast<DropReason>(r)))] = plan.dropped.counts[r];
  }
  const auto& m = options.machine;
  nlohmann::json j = {
      {"candidates", plan.candidates},
      {"kept", plan.probes.size()},
      {"dropped", drops},
      {"dropped_total", plan.dropped.Total()},
      {"advice", PlanAdvice(plan)},
      {"coverage_gaps", CoverageGapsJson(plan.coverage_gaps)},
      {"small_imprints",
       {{"probes", plan.small_imprints.probes},
        {"seen", plan.small_imprints.seen},
        {"below_px", kMinImprintPixels},
        {"z_min_mm", plan.small_imprints.z_min_mm},
        {"z_max_mm", plan.small_imprints.z_max_mm},
        {"median_px", plan.small_imprints.median_px}}},
      {"waypoints", plan.waypoints},
      {"detoured_moves", plan.detoured_moves},
      {"estimate", EstimateJson(plan.estimate)},
      {"sampling_order_estimate", EstimateJson(plan.sampling_order_estimate)},
      {"nearest_neighbour_s", plan.nearest_neighbour_s},
      {"tour_gain", plan.TourGain()},
      {"checkpoint_probes", plan.checkpoint_probes},
      {"planning_seconds", plan.planning_seconds},
      {"options_hash", plan.options_hash},
      {"options",
       {{"probe_count", options.probe_count},
        {"count_is_kept", options.count_is_kept},
        {"seed", options.seed},
        {"ball_radius", options.ball_radius},
        {"press_depth", options.press_depth},
        {"clearance", options.clearance},
        {"stylus_radius", options.stylus_radius},
        {"stylus_length", options.stylus_length},
        {"holder_radius", options.holder_radius},
        {"holder_length", options.holder_length},
        {"press_feed_mm_per_min", options.press_feed_mm_per_min},
        {"retract_feed_mm_per_min", options.retract_feed_mm_per_min},
        {"settle_dwell_s", options.settle_dwell_s},
        {"capture_time_s", options.capture_time_s},
        {"status_poll_latency_s", options.status_poll_latency_s},
        {"host_latency_s", options.host_latency_s},
        {"reference_every", options.reference_every},
        {"junction_model", std::string(JunctionModelName(options.junction_model))}}},
      {"machine",
       {{"max_rate_mm_per_min", Vec(m.max_rate_mm_per_min)},
        {"acceleration_mm_per_s2", Vec(m.acceleration_mm_per_s2)},
        {"max_travel_mm", Vec(m.max_travel_mm)},
        {"junction_deviation_mm", m.junction_deviation_mm},
        {"planner_blocks", m.planner_blocks}}},
  };
  if (m.travel_min_mm) j["options"]["machine"]["travel_min_mm"] = Vec(*m.travel_min_mm);
  return j;
}

nlohmann::json PlanToJson(const ProbePlan& plan, const PlanOptions& options) {
  nlohmann::json j = PlanSummaryJson(plan, options);
  j["format"] = "gs360.probe_plan.v1";
  j["start_machine"] = Vec(plan.start_machine);
  nlohmann::json park = nlohmann::json::array();
  for (const auto& w : plan.park_machine) park.push_back(Vec(w));
  j["park_machine"] = park;
  nlohmann::json probes = nlohmann::json::array();
  for (const PlannedProbe& p : plan.probes) {
    nlohmann::json travel = nlohmann::json::array();
    for (const auto& w : p.travel_machine) travel.push_back(Vec(w));
    probes.push_back({{"plan_index", p.plan_index},
                      {"sample_index", p.sample_index},
                      {"point_sensor", Vec(p.point_sensor)},
                      {"normal_sensor", Vec(p.normal_sensor)},
                      {"approach_machine", Vec(p.approach_machine)},
                      {"press_machine", Vec(p.press_machine)},
                      {"retract_machine", Vec(p.retract_machine)},
                      {"travel_machine", travel},
                      {"reference_before", p.reference_before}});
  }
  j["probes"] = probes;
  return j;
}

ProbePlan PlanFromJson(const nlohmann::json& j) {
  try {
    if (j.at("format").get<std::string>() != "gs360.probe_plan.v1") {
      throw std::invalid_argument("unknown format " + j.at("format").dump());
    }
    ProbePlan plan;
    plan.candidates = j.at("candidates").get<int>();
    for (int r = 0; r < kNumDropReasons; ++r) {
      plan.dropped.counts[r] =
          j.at("dropped").at(std::string(DropReasonName(static_cast<DropReason>(r)))).get<int>();
    }
    plan.waypoints = j.at("waypoints").get<int>();
    plan.detoured_moves = j.at("detoured_moves").get<int>();
    plan.estimate = EstimateFromJson(j.at("estimate"));
    plan.sampling_order_estimate = EstimateFromJson(j.at("sampling_order_estimate"));
    plan.nearest_neighbour_s = j.at("nearest_neighbour_s").get<double>();
    plan.checkpoint_probes = j.value("checkpoint_probes", 0);  // absent before the rounds
    plan.planning_seconds = j.at("planning_seconds").get<double>();
    plan.options_hash = j.at("options_hash").get<std::string>();
    plan.start_machine = VecFrom(j.at("start_machine"));
    for (const auto& w : j.at("park_machine")) plan.park_machine.push_back(VecFrom(w));
    for (const auto& jp : j.at("probes")) {
      PlannedProbe p;
      p.plan_index = jp.at("plan_index").get<int>();
      p.sample_index = jp.at("sample_index").get<int>();
      p.point_sensor = VecFrom(jp.at("point_sensor"));
      p.normal_sensor = VecFrom(jp.at("normal_sensor"));
      p.approach_machine = VecFrom(jp.at("approach_machine"));
      p.press_machine = VecFrom(jp.at("press_machine"));
      p.retract_machine = VecFrom(jp.at("retract_machine"));
      for (const auto& w : jp.at("travel_machine")) p.travel_machine.push_back(VecFrom(w));
      p.reference_before = jp.at("reference_before").get<bool>();
      plan.probes.push_back(std::move(p));
    }
    return plan;
  } catch (const nlohmann::json::exception& e) {
    throw std::invalid_argument(std::string("PlanFromJson: malformed plan: ") + e.what());
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(std::string("PlanFromJson: ") + e.what());
  }
}

}  // namespace gs360
