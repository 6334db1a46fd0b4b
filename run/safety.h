#pragma once
// Safety limits the daemon's operator sets (gs360d.toml [limits]) and the guard that enforces
// them: every G-code line the run engine sends is checked first, and every line of a plan is
// checked when the run is created, so a plan that breaks a limit is refused before anything moves.
//
// What a line may not do (frame: machine, GRBL MPos, mm):
// - move outside the envelope [envelope_min, envelope_max] (any target, any axis);
// - use a feed above max_feed_mm_per_min;
// - put the ball deeper into the gel than MaxDepth(): min(max_press_depth, the rig's gel
//   thickness, the ball's radius), measured as the ball's overlap with the nominal surface at the
//   line's target and along the move;
// - move in anything but machine coordinates (G53) or use a word the guard does not know.
// Lines without motion (G4, G21, G90, $ commands) pass.

#include <Eigen/Core>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include "plan/plan.h"

namespace gs360 {

struct SafetyLimits {
  Eigen::Vector3d envelope_min{-300.0, -180.0, -45.0};
  Eigen::Vector3d envelope_max{0.0, 0.0, 0.0};
  double max_press_depth = 1.2;         // mm into the gel, along its normal
  double max_feed_mm_per_min = 3000.0;  // any F word
  // Throws ConfigError naming the field (limits.*) and value.
  void Check() const;
};

class SafetyGuard {
 public:
  // `travel` gives the rig's surface and the ball's frame; `ball_radius` and `gel_thickness` mm.
  SafetyGuard(const SafetyLimits& limits, std::shared_ptr<const TravelPlanner> travel,
              double ball_radius, double gel_thickness);

  // The deepest press allowed (mm).
  double MaxDepth() const { return max_depth_; }
  // nullopt when `line` may be sent with the tool at `from` (machine frame); else what it breaks,
  // naming the limit and the value ("Z -46.100 is below limits.envelope_min.z = -45").
  std::optional<std::string> CheckLine(std::string_view line, const Eigen::Vector3d& from) const;
  // Every line of the plan (travel, approach, press, retract, park) in run order; the message
  // names the probe (plan index and sensor-frame point) and the limit.
  std::optional<std::string> CheckPlan(const ProbePlan& plan, const PlanOptions& options) const;

 private:
  std::optional<std::string> CheckTarget(const Eigen::Vector3d& from,
                                         const Eigen::Vector3d& to) const;

  SafetyLimits limits_;
  std::shared_ptr<const TravelPlanner> travel_;
  double ball_radius_;
  double max_depth_;
};

}  // namespace gs360
