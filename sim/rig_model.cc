#include "sim/rig_model.h"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <sstream>
#include <stdexcept>

#include "base/field_error.h"
#include "rig/rig_shape.h"
#include "sim/camera_random.h"

namespace gs360 {
namespace {

constexpr double kDegToRad = std::numbers::pi / 180.0;

void RequireFiniteNonNegative(const std::string& field, double value) {
  if (!std::isfinite(value) || value < 0.0)
    ThrowFieldError(field, value, "must be finite and >= 0");
}

// Unit vector uniformly distributed on the sphere.
Eigen::Vector3d RandomUnitVector(SimRandom& rng) {
  const double z = rng.Uniform(-1.0, 1.0);
  const double phi = rng.Uniform(0.0, 2.0 * std::numbers::pi);
  const double s = std::sqrt(std::max(0.0, 1.0 - z * z));
  return {s * std::cos(phi), s * std::sin(phi), z};
}

}  // namespace

void TruePerturbationOptions::Check() const {
  RequireFiniteNonNegative("TruePerturbationOptions.translation_mm", translation_mm);
  RequireFiniteNonNegative("TruePerturbationOptions.rotation_deg", rotation_deg);
  if (rotation_deg >= 90.0) {
    ThrowFieldError("TruePerturbationOptions.rotation_deg", rotation_deg, "must be < 90");
  }
  RequireFiniteNonNegative("TruePerturbationOptions.focal_relative", focal_relative);
  if (focal_relative >= 0.2) {
    ThrowFieldError("TruePerturbationOptions.focal_relative", focal_relative, "must be < 0.2");
  }
  RequireFiniteNonNegative("TruePerturbationOptions.aspect_relative", aspect_relative);
  if (aspect_relative >= 0.2) {
    ThrowFieldError("TruePerturbationOptions.aspect_relative", aspect_relative, "must be < 0.2");
  }
  RequireFiniteNonNegative("TruePerturbationOptions.principal_point_px", principal_point_px);
  RequireFiniteNonNegative("TruePerturbationOptions.k1", k1);
  RequireFiniteNonNegative("TruePerturbationOptions.k2", k2);
}

TruePerturbationOptions TruePerturbationOptions::None() {
  TruePerturbationOptions p;
  p.translation_mm = 0.0;
  p.rotation_deg = 0.0;
  p.focal_relative = 0.0;
  p.aspect_relative = 0.0;
  p.principal_point_px = 0.0;
  p.k1 = 0.0;
  p.k2 = 0.0;
  return p;
}

void SimRigOptions::Check() const {
  rig.Check();
  mesh_load.Check();
  perturbation.Check();
}

SimRig::SimRig(const SimRigOptions& options) : options_(options) {
  options_.Check();
  RigShape shape = BuildRigShape(options_.rig, options_.mesh_load);
  profile_ = std::move(shape.profile);
  gel_bvh_ = std::make_unique<Bvh>(std::move(shape.gel));
  fin_bvh_ = std::make_unique<Bvh>(std::move(shape.fins));
  fin_options_ = shape.fin_options;

  // True camera: the nominal one perturbed by fixed magnitudes in seeded directions.
  SimRandom rng(MixSeed(options_.seed, 0x7472756563616dull));  // "truecam"
  const TruePerturbationOptions& p = options_.perturbation;
  const Rigid3d nominal = nominal_cam_from_sensor();
  const Rigid3d sensor_from_cam_nominal = nominal.Inverse();
  const Eigen::Vector3d centre_offset = p.translation_mm * RandomUnitVector(rng);
  const Eigen::Vector3d rotation_axis = RandomUnitVector(rng);
  // sensor_from_cam_true = (rotate the camera about its own centre) then move the centre.
  Rigid3d sensor_from_cam_true = sensor_from_cam_nominal;
  sensor_from_cam_true.rotation =
      (sensor_from_cam_nominal.rotation *
       Eigen::Quaterniond(Eigen::AngleAxisd(p.rotation_deg * kDegToRad, rotation_axis)))
          .normalized();
  sensor_from_cam_true.translation += centre_offset;
  true_cam_from_sensor_ = sensor_from_cam_true.Inverse();

  true_intrinsics_ = options_.rig.camera;
  const double focal_scale = 1.0 + rng.Sign() * p.focal_relative;
  const double aspect_scale = 1.0 + rng.Sign() * p.aspect_relative;
  true_intrinsics_.fx *= focal_scale;
  true_intrinsics_.fy *= focal_scale * aspect_scale;
  const double pp_angle = rng.Uniform(0.0, 2.0 * std::numbers::pi);
  true_intrinsics_.cx += p.principal_point_px * std::cos(pp_angle);
  true_intrinsics_.cy += p.principal_point_px * std::sin(pp_angle);
  true_intrinsics_.k[0] += rng.Sign() * p.k1;
  true_intrinsics_.k[1] += rng.Sign() * p.k2;
  true_intrinsics_.Check();
  // The lens must stay a bijection over the whole nominal field.
  const FisheyeCamera true_camera(true_intrinsics_);
  if (true_camera.MaxValidTheta() < true_intrinsics_.max_theta - 1e-9) {
    throw std::invalid_argument(
        "TruePerturbationOptions: k1/k2 fold the true lens inside its field (theta_d stops "
        "increasing at " +
        std::to_string(true_camera.MaxValidTheta() / kDegToRad) + " deg)");
  }
}

std::string SimRig::Describe() const {
  if (!options_.rig.mesh_path.empty()) return "mesh " + options_.rig.mesh_path;
  return std::string(SensorShapeName(options_.rig.shape.shape));
}

Eigen::Vector3d SimRig::BallCenterSensor(const Eigen::Vector3d& machine_position) const {
  return machine_from_sensor().Inverse() * (machine_position + tool_offset());
}

Eigen::Vector3d SimRig::MachinePositionForBall(const Eigen::Vector3d& ball_center_sensor) const {
  return machine_from_sensor() * ball_center_sensor - tool_offset();
}

}  // namespace gs360
