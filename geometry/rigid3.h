#pragma once
// Rigid transforms named by their frames: `b_from_a * x_a` gives x in frame b.
// Units: millimetres for translation, radians for angles.

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace gs360 {

struct Rigid3d {
  Eigen::Quaterniond rotation = Eigen::Quaterniond::Identity();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();

  Rigid3d() = default;
  Rigid3d(const Eigen::Quaterniond& r, const Eigen::Vector3d& t)
      : rotation(r.normalized()), translation(t) {}

  static Rigid3d Identity() { return {}; }
  // Rotation by `angle` (rad) about `axis` (normalised here), then translation `t`.
  static Rigid3d FromAxisAngle(const Eigen::Vector3d& axis, double angle, const Eigen::Vector3d& t);
  // From a 3x4 [R|t] or 4x4 matrix; R is re-orthonormalised.
  static Rigid3d FromMatrix(const Eigen::Matrix<double, 3, 4>& m);

  Eigen::Matrix3d RotationMatrix() const { return rotation.toRotationMatrix(); }
  Eigen::Matrix<double, 3, 4> ToMatrix3x4() const;
  Eigen::Matrix4d ToMatrix4() const;

  Eigen::Vector3d operator*(const Eigen::Vector3d& x) const { return rotation * x + translation; }
  // Rotates a direction (no translation).
  Eigen::Vector3d RotateDirection(const Eigen::Vector3d& d) const { return rotation * d; }
  // (c_from_b * b_from_a) = c_from_a.
  Rigid3d operator*(const Rigid3d& other) const;
  Rigid3d Inverse() const;

  // Rotation angle (rad) of this transform, in [0, pi].
  double AngleRad() const;
};

// Differences between two transforms that should agree: rotation angle (rad) of a_from_b^-1 *
// a_from_b2 and the translation distance (mm).
double RotationDifferenceRad(const Rigid3d& a, const Rigid3d& b);
double TranslationDifferenceMm(const Rigid3d& a, const Rigid3d& b);

}  // namespace gs360
