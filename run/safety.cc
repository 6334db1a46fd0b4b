#include "run/safety.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <sstream>

#include "base/format.h"
#include "base/json_reader.h"
#include "gcode/probe_program.h"

namespace gs360 {
namespace {

constexpr double kDepthTolerance = 0.02;  // mm: surface snapping and tessellation
constexpr double kSampleStep = 0.25;      // mm between depth checks along a move
constexpr const char* kAxes = "XYZ";

std::string Num(double v, int decimals = 3) {
  return FormatFixed(v, decimals);
}

struct Words {
  bool g53 = false;
  bool motion = false;
  std::optional<double> axis[3];
  std::optional<double> feed;
  std::string unknown;  // first word the guard does not accept
};

Words ParseWords(std::string_view line) {
  Words w;
  std::size_t i = 0;
  while (i < line.size()) {
    const char letter = static_cast<char>(std::toupper(static_cast<unsigned char>(line[i])));
    if (letter == ' ' || letter == '\t') {
      ++i;
      continue;
    }
    std::size_t j = i + 1;
    while (j < line.size() && line[j] != ' ' && line[j] != '\t') ++j;
    const std::string_view number = line.substr(i + 1, j - i - 1);
    double value = 0.0;
    const auto [end, ec] = std::from_chars(number.data(), number.data() + number.size(), value);
    if (ec != std::errc() || end != number.data() + number.size() || !std::isfinite(value)) {
      if (w.unknown.empty()) w.unknown = std::string(line.substr(i, j - i));
      i = j;
      continue;
    }
    switch (letter) {
      case 'G':
        if (value == 53) w.g53 = true;
        if (value == 0 || value == 1) w.motion = true;
        if (value != 0 && value != 1 && value != 4 && value != 21 && value != 53 && value != 90 &&
            w.unknown.empty()) {
          w.unknown = std::string(line.substr(i, j - i));
        }
        break;
      case 'X':
      case 'Y':
      case 'Z':
        w.axis[letter - 'X'] = value;
        break;
      case 'F':
        w.feed = value;
        break;
      case 'P':  // G4's dwell
        break;
      default:
        if (w.unknown.empty()) w.unknown = std::string(line.substr(i, j - i));
    }
    i = j;
  }
  return w;
}

}  // namespace

void SafetyLimits::Check() const {
  for (int i = 0; i < 3; ++i) {
    if (!std::isfinite(envelope_min[i]) || !std::isfinite(envelope_max[i]) ||
        !(envelope_min[i] < envelope_max[i])) {
      const std::string field = std::string("limits.envelope_min");
      throw ConfigError(field + " must be below limits.envelope_max on every axis, got " +
                            std::string(1, kAxes[i]) + " " + Num(envelope_min[i]) +
                            " >= " + Num(envelope_max[i]),
                        field);
    }
  }
  if (!(max_press_depth > 0.0) || !std::isfinite(max_press_depth)) {
    throw ConfigError("limits.max_press_depth must be > 0, got " + Num(max_press_depth),
                      "limits.max_press_depth");
  }
  if (!(max_feed_mm_per_min > 0.0) || !std::isfinite(max_feed_mm_per_min)) {
    throw ConfigError("limits.max_feed_mm_per_min must be > 0, got " + Num(max_feed_mm_per_min, 1),
                      "limits.max_feed_mm_per_min");
  }
}

SafetyGuard::SafetyGuard(const SafetyLimits& limits, std::shared_ptr<const TravelPlanner> travel,
                         double ball_radius, double gel_thickness)
    : limits_(limits),
      travel_(std::move(travel)),
      ball_radius_(ball_radius),
      max_depth_(std::min({limits.max_press_depth, gel_thickness, ball_radius})) {
  limits_.Check();
}

std::optional<std::string> SafetyGuard::CheckTarget(const Eigen::Vector3d& from,
                                                    const Eigen::Vector3d& to) const {
  for (int i = 0; i < 3; ++i) {
    if (to[i] < limits_.envelope_min[i] - 1e-9) {
      return std::string(1, kAxes[i]) + " " + Num(to[i]) + " is below limits.envelope_min." +
             static_cast<char>('x' + i) + " = " + Num(limits_.envelope_min[i]);
    }
    if (to[i] > limits_.envelope_max[i] + 1e-9) {
      return std::string(1, kAxes[i]) + " " + Num(to[i]) + " is above limits.envelope_max." +
             static_cast<char>('x' + i) + " = " + Num(limits_.envelope_max[i]);
    }
  }
  // The ball's deepest overlap with the gel along the move (its target included).
  const double length = (to - from).norm();
  const int steps = std::max(1, static_cast<int>(std::ceil(length / kSampleStep)));
  double deepest = -1e9;
  Eigen::Vector3d deepest_at = to;
  for (int k = 1; k <= steps; ++k) {
    const Eigen::Vector3d at = from + (to - from) * (static_cast<double>(k) / steps);
    const double depth = ball_radius_ - travel_->Distance().Signed(travel_->BallFromMachine(at));
    if (depth > deepest) {
      deepest = depth;
      deepest_at = at;
    }
  }
  if (deepest > max_depth_ + kDepthTolerance) {
    return "the ball would go " + Num(deepest) + " mm into the gel at " + Num(deepest_at.x()) +
           ", " + Num(deepest_at.y()) + ", " + Num(deepest_at.z()) + " (deepest allowed " +
           Num(max_depth_) +
           " mm: limits.max_press_depth, rig.gel_thickness and the ball's radius)";
  }
  return std::nullopt;
}

std::optional<std::string> SafetyGuard::CheckLine(std::string_view line,
                                                  const Eigen::Vector3d& from) const {
  if (line.empty() || line[0] == '$') return std::nullopt;
  const Words w = ParseWords(line);
  if (!w.unknown.empty()) return "'" + std::string(w.unknown) + "' is not a word the guard allows";
  if (w.feed && *w.feed > limits_.max_feed_mm_per_min + 1e-9) {
    return "feed F" + Num(*w.feed, 1) +
           " is above limits.max_feed_mm_per_min = " + Num(limits_.max_feed_mm_per_min, 1);
  }
  const bool has_axis = w.axis[0] || w.axis[1] || w.axis[2];
  if (!has_axis) return std::nullopt;
  if (!w.g53) return "motion outside machine coordinates (no G53)";
  Eigen::Vector3d to = from;
  for (int i = 0; i < 3; ++i) {
    if (w.axis[i]) to[i] = *w.axis[i];
  }
  return CheckTarget(from, to);
}

std::optional<std::string> SafetyGuard::CheckPlan(const ProbePlan& plan,
                                                  const PlanOptions& options) const {
  Eigen::Vector3d at = plan.start_machine;
  const auto check_lines =
      [&](const std::vector<std::string>& lines) -> std::optional<std::string> {
    for (const std::string& line : lines) {
      if (auto bad = CheckLine(line, at)) return "'" + line + "': " + *bad;
      const Words w = ParseWords(line);
      for (int i = 0; i < 3; ++i) {
        if (w.axis[i]) at[i] = *w.axis[i];
      }
    }
    return std::nullopt;
  };
  for (const PlannedProbe& probe : plan.probes) {
    const ProbeProgram program = MakeProbeProgram(probe, options);
    for (const auto* lines : {&program.reference, &program.press, &program.retract}) {
      if (auto bad = check_lines(*lines)) {
        const Eigen::Vector3d& p = probe.point_sensor;
        return "probe " + std::to_string(probe.plan_index) + " (sensor point " + Num(p.x(), 2) +
               ", " + Num(p.y(), 2) + ", " + Num(p.z(), 2) + "): " + *bad;
      }
    }
  }
  if (auto bad = check_lines(ParkLines(plan))) return "the park move: " + *bad;
  return std::nullopt;
}

}  // namespace gs360
