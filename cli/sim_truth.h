#pragma once
// The virtual rig's physical truth for the calibration's validation stage: the simulator's own
// deformed gel (elastic edge and bulge, sim/gel_deformation.h) under each probe, and the true
// camera pose. Used by `demo`, `calibrate --sim-truth-seed` and tests only: production code sees
// it only through calib/validate.h's ValidationTruth interface.

#include <memory>

#include "calib/validate.h"
#include "sim/gel_deformation.h"
#include "sim/rig_model.h"

namespace gs360::cli {

class SimValidationTruth : public ValidationTruth {
 public:
  // `gel`: the deformation model the tactile camera renders with.
  SimValidationTruth(std::shared_ptr<const SimRig> rig, const GelDeformationOptions& gel);
  std::string Describe() const override;
  std::optional<Rigid3d> TrueCamFromSensor() const override;
  std::unique_ptr<ProbeSurfaceTruth> ForProbe(const Eigen::Vector3d& ball_center_sensor,
                                              double ball_radius) const override;

 private:
  std::shared_ptr<const SimRig> rig_;
  GelDeformationOptions gel_;
  std::unique_ptr<GelPatchBuilder> builder_;
};

// Closest point on triangle (a, b, c) to p, with its barycentrics (1 - s - t, s, t).
Eigen::Vector3d ClosestPointOnTriangle(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                                       const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                                       double* s, double* t);

}  // namespace gs360::cli
