#include "geometry/rigid3.h"

#include <Eigen/SVD>
#include <algorithm>
#include <cmath>

namespace gs360 {

Rigid3d Rigid3d::FromAxisAngle(const Eigen::Vector3d& axis, double angle,
                               const Eigen::Vector3d& t) {
  const double n = axis.norm();
  if (n == 0.0) return Rigid3d(Eigen::Quaterniond::Identity(), t);
  return Rigid3d(Eigen::Quaterniond(Eigen::AngleAxisd(angle, axis / n)), t);
}

Rigid3d Rigid3d::FromMatrix(const Eigen::Matrix<double, 3, 4>& m) {
  // Project onto SO(3): nearest rotation in the Frobenius sense.
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(m.leftCols<3>(), Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d r = svd.matrixU() * svd.matrixV().transpose();
  if (r.determinant() < 0) {
    Eigen::Matrix3d u = svd.matrixU();
    u.col(2) *= -1.0;
    r = u * svd.matrixV().transpose();
  }
  return Rigid3d(Eigen::Quaterniond(r), m.col(3));
}

Eigen::Matrix<double, 3, 4> Rigid3d::ToMatrix3x4() const {
  Eigen::Matrix<double, 3, 4> m;
  m.leftCols<3>() = RotationMatrix();
  m.col(3) = translation;
  return m;
}

Eigen::Matrix4d Rigid3d::ToMatrix4() const {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  m.topRows<3>() = ToMatrix3x4();
  return m;
}

Rigid3d Rigid3d::operator*(const Rigid3d& other) const {
  return Rigid3d(rotation * other.rotation, rotation * other.translation + translation);
}

Rigid3d Rigid3d::Inverse() const {
  const Eigen::Quaterniond inv = rotation.conjugate();
  return Rigid3d(inv, -(inv * translation));
}

double Rigid3d::AngleRad() const {
  // 2*atan2(|v|, |w|) is accurate near 0 and pi, unlike acos(w).
  return 2.0 * std::atan2(rotation.vec().norm(), std::abs(rotation.w()));
}

double RotationDifferenceRad(const Rigid3d& a, const Rigid3d& b) {
  return (a.Inverse() * b).AngleRad();
}

double TranslationDifferenceMm(const Rigid3d& a, const Rigid3d& b) {
  return (a.translation - b.translation).norm();
}

}  // namespace gs360
