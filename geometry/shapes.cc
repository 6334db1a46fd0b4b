#include "geometry/shapes.h"

#include "geometry/bvh.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <sstream>
#include <stdexcept>

#include "base/field_error.h"

namespace gs360 {
namespace {

constexpr double kPi = std::numbers::pi;
constexpr int kTableIntervals = 8192;

void RequirePositive(const char* field, double v) {
  if (!(v > 0.0) || !std::isfinite(v)) ThrowFieldError(field, v, "must be finite and > 0");
}

std::string Num(double v) {
  std::ostringstream os;
  os << v;
  return os.str();
}

// ---------------------------------------------------------------------------------------------
// Concrete profiles. Each is parameterised roughly by arc length so that a uniform t table is
// accurate.

class CylinderCapProfile final : public RevolutionProfile {
 public:
  explicit CylinderCapProfile(const CylinderCapOptions& o)
      : radius_(o.radius),
        straight_(o.height - o.radius),
        length_(straight_ + 0.5 * kPi * o.radius) {
    Tabulate();
  }
  Eigen::Vector2d Point(double t) const override {
    const double s = std::clamp(t, 0.0, 1.0) * length_;
    if (s <= straight_) return {radius_, s};
    if (t >= 1.0) return {0.0, straight_ + radius_};
    const double a = (s - straight_) / radius_;
    return {radius_ * std::cos(a), straight_ + radius_ * std::sin(a)};
  }
  Eigen::Vector2d Normal(double t) const override {
    const double s = std::clamp(t, 0.0, 1.0) * length_;
    if (s <= straight_) return {1.0, 0.0};
    if (t >= 1.0) return {0.0, 1.0};
    const double a = (s - straight_) / radius_;
    return {std::cos(a), std::sin(a)};
  }
  std::string Describe() const override {
    return "cylinder-cap radius=" + Num(radius_) + " height=" + Num(straight_ + radius_);
  }

 private:
  double radius_, straight_, length_;
};

class ConeProfile final : public RevolutionProfile {
 public:
  explicit ConeProfile(const ConeOptions& o)
      : base_radius_(o.base_radius), height_(o.height), tip_radius_(o.tip_radius) {
    const Eigen::Vector2d base(base_radius_, 0.0);
    center_ = Eigen::Vector2d(0.0, height_ - tip_radius_);
    const Eigen::Vector2d to_base = base - center_;
    const double d = to_base.norm();
    // Tangent point: rotate the direction to the base rim by acos(rho / d) toward +z.
    const double a = std::atan2(to_base.y(), to_base.x()) + std::acos(tip_radius_ / d);
    tangent_angle_ = a;
    tangent_point_ = center_ + tip_radius_ * Eigen::Vector2d(std::cos(a), std::sin(a));
    side_length_ = (tangent_point_ - base).norm();
    length_ = side_length_ + tip_radius_ * (0.5 * kPi - tangent_angle_);
    Tabulate();
  }
  Eigen::Vector2d Point(double t) const override {
    t = std::clamp(t, 0.0, 1.0);
    const double s = t * length_;
    if (s <= side_length_) {
      const double u = s / side_length_;
      return Eigen::Vector2d(base_radius_, 0.0) * (1.0 - u) + tangent_point_ * u;
    }
    if (t >= 1.0) return {0.0, height_};
    const double a = tangent_angle_ + (s - side_length_) / tip_radius_;
    return center_ + tip_radius_ * Eigen::Vector2d(std::cos(a), std::sin(a));
  }
  Eigen::Vector2d Normal(double t) const override {
    t = std::clamp(t, 0.0, 1.0);
    const double s = t * length_;
    const double a =
        s <= side_length_ ? tangent_angle_ : tangent_angle_ + (s - side_length_) / tip_radius_;
    if (t >= 1.0) return {0.0, 1.0};
    return {std::cos(a), std::sin(a)};
  }
  std::string Describe() const override {
    return "cone base_radius=" + Num(base_radius_) + " height=" + Num(height_) +
           " tip_radius=" + Num(tip_radius_);
  }

 private:
  double base_radius_, height_, tip_radius_;
  Eigen::Vector2d center_, tangent_point_;
  double tangent_angle_ = 0.0, side_length_ = 0.0, length_ = 0.0;
};

// r(z)^2 as a monotone piecewise cubic (PCHIP); the last interval is written as a polynomial in
// w = height - z so that r near the tip is computed without cancellation.
class SplineProfile final : public RevolutionProfile {
 public:
  explicit SplineProfile(const SplineOptions& o) {
    const auto& cp = o.control_points;
    const int n = static_cast<int>(cp.size());
    z_.resize(n);
    f_.resize(n);
    for (int i = 0; i < n; ++i) {
      z_[i] = cp[i].x();
      f_[i] = cp[i].y() * cp[i].y();
    }
    height_ = z_.back();
    std::vector<double> h(n - 1), delta(n - 1);
    for (int i = 0; i + 1 < n; ++i) {
      h[i] = z_[i + 1] - z_[i];
      delta[i] = (f_[i + 1] - f_[i]) / h[i];
    }
    m_.assign(n, 0.0);
    for (int k = 1; k + 1 < n; ++k) {
      if (delta[k - 1] * delta[k] <= 0.0) {
        m_[k] = 0.0;
      } else {
        const double w1 = 2.0 * h[k] + h[k - 1];
        const double w2 = h[k] + 2.0 * h[k - 1];
        m_[k] = (w1 + w2) / (w1 / delta[k - 1] + w2 / delta[k]);
      }
    }
    if (n == 2) {
      m_[0] = delta[0];
    } else {
      // Shape-preserving three-point end slope (as scipy's PchipInterpolator).
      double m0 = ((2.0 * h[0] + h[1]) * delta[0] - h[0] * delta[1]) / (h[0] + h[1]);
      if (m0 * delta[0] <= 0.0) {
        m0 = 0.0;
      } else if (delta[0] * delta[1] <= 0.0 && std::abs(m0) > 3.0 * std::abs(delta[0])) {
        m0 = 3.0 * delta[0];
      }
      m_[0] = m0;
    }
    // Tip: the secant slope of the last interval (negative), which gives the tip a horizontal
    // tangent with curvature radius -m/2.
    m_[n - 1] = delta[n - 2];
    // Last interval in w = H - z: g(w) = a1 w + a2 w^2 + a3 w^3.
    const double hl = h[n - 2];
    const double big_f = f_[n - 2];
    a1_ = -m_[n - 1];
    const double A = big_f - a1_ * hl;
    const double B = -m_[n - 2] - a1_;
    a3_ = (B - 2.0 * A / hl) / (hl * hl);
    a2_ = (A - a3_ * hl * hl * hl) / (hl * hl);
    points_ = cp;
    Tabulate();
  }

  Eigen::Vector2d Point(double t) const override {
    t = std::clamp(t, 0.0, 1.0);
    const double u = 1.0 - t;
    const double w = height_ * u * u;
    const double z = height_ - w;
    if (z >= z_[z_.size() - 2]) {
      const double q = a1_ + w * (a2_ + w * a3_);
      return {std::sqrt(height_) * u * std::sqrt(std::max(q, 0.0)), z};
    }
    double f, df;
    Evaluate(z, &f, &df);
    return {std::sqrt(std::max(f, 0.0)), z};
  }

  Eigen::Vector2d Normal(double t) const override {
    t = std::clamp(t, 0.0, 1.0);
    const double u = 1.0 - t;
    const double w = height_ * u * u;
    const double z = height_ - w;
    const double dz_dt = 2.0 * height_ * u;
    double dr_dt;
    if (z >= z_[z_.size() - 2]) {
      const double q = std::max(a1_ + w * (a2_ + w * a3_), 1e-300);
      const double dq_dw = a2_ + 2.0 * w * a3_;
      const double dw_dt = -2.0 * height_ * u;
      dr_dt = std::sqrt(height_) * (-std::sqrt(q) + u * dq_dw * dw_dt / (2.0 * std::sqrt(q)));
    } else {
      double f, df;
      Evaluate(z, &f, &df);
      dr_dt = df * dz_dt / (2.0 * std::sqrt(std::max(f, 1e-300)));
    }
    const Eigen::Vector2d n(dz_dt, -dr_dt);
    return n.normalized();
  }

  std::string Describe() const override {
    std::ostringstream os;
    os << "spline points=";
    for (std::size_t i = 0; i < points_.size(); ++i) {
      os << (i ? ";" : "") << points_[i].x() << "," << points_[i].y();
    }
    return os.str();
  }

 private:
  // f = r^2 and df/dz at z in [0, z_{n-2}] (standard cubic Hermite).
  void Evaluate(double z, double* f, double* df) const {
    const int n = static_cast<int>(z_.size());
    int i = static_cast<int>(std::upper_bound(z_.begin(), z_.end(), z) - z_.begin()) - 1;
    i = std::clamp(i, 0, n - 2);
    const double h = z_[i + 1] - z_[i];
    const double s = (z - z_[i]) / h;
    const double s2 = s * s, s3 = s2 * s;
    const double h00 = 2 * s3 - 3 * s2 + 1, h10 = s3 - 2 * s2 + s, h01 = -2 * s3 + 3 * s2,
                 h11 = s3 - s2;
    *f = h00 * f_[i] + h10 * h * m_[i] + h01 * f_[i + 1] + h11 * h * m_[i + 1];
    const double d00 = (6 * s2 - 6 * s) / h, d10 = 3 * s2 - 4 * s + 1, d01 = (-6 * s2 + 6 * s) / h,
                 d11 = 3 * s2 - 2 * s;
    *df = d00 * f_[i] + d10 * m_[i] + d01 * f_[i + 1] + d11 * m_[i + 1];
  }

  std::vector<double> z_, f_, m_;
  std::vector<Eigen::Vector2d> points_;
  double height_ = 0.0;
  double a1_ = 0.0, a2_ = 0.0, a3_ = 0.0;
};

// Inner-wall outline of a fin: the profile offset inward by `inset`, clipped to
// [bottom_z, top_z], as points (w, z) with z increasing. `apex` is true when it ends on the axis.
struct FinOutline {
  std::vector<Eigen::Vector2d> points;
  bool apex = false;
};

Eigen::Vector2d Offset(const RevolutionProfile& p, double t, double inset) {
  return p.Point(t) - inset * p.Normal(t);
}

// t in [lo, hi] with Offset(t).z == z (Offset z increasing on the interval).
double SolveOffsetZ(const RevolutionProfile& p, double inset, double z, double lo, double hi) {
  for (int it = 0; it < 100; ++it) {
    const double mid = 0.5 * (lo + hi);
    if (Offset(p, mid, inset).y() < z) {
      lo = mid;
    } else {
      hi = mid;
    }
  }
  return 0.5 * (lo + hi);
}

// Walks the inner-wall outline up from the base: the parameter where it reaches top_z (1 when it
// reaches the tip first), or where it folds (stops rising along z, or meets the axis before the
// tip): *fold_z is then the height of the fold, else +inf. Above top_z the outline is cut off,
// so its shape there does not matter.
double OutlineEnd(const FinOptions& o, const RevolutionProfile& p, double* fold_z) {
  const int n = kTableIntervals;
  *fold_z = std::numeric_limits<double>::infinity();
  Eigen::Vector2d prev = Offset(p, 0.0, o.inset);
  for (int i = 1; i <= n; ++i) {
    const double t = static_cast<double>(i) / n;
    if (prev.y() >= o.top_z) return t;
    const Eigen::Vector2d q = Offset(p, t, o.inset);
    if (!(q.y() > prev.y()) || (i < n && !(q.x() > 0.0))) {
      *fold_z = q.y();
      return t;
    }
    prev = q;
  }
  return 1.0;
}

FinOutline ComputeFinOutline(const FinOptions& o, const RevolutionProfile& p) {
  o.Check();
  // The offset must stay a graph over z and off the axis (else the inset is too large).
  double fold_z = 0.0;
  const double t_end = OutlineEnd(o, p, &fold_z);
  if (std::isfinite(fold_z)) {
    throw std::invalid_argument("FinOptions.inset = " + Num(o.inset) + " is too large for " +
                                p.Describe() +
                                ": the inner-wall outline folds over near z = " + Num(fold_z) +
                                " mm (a lower [rig.fins] top_z cuts the fins below it)");
  }
  const double z0 = Offset(p, 0.0, o.inset).y();
  const double z1 = Offset(p, t_end, o.inset).y();
  const double lo_z = std::max(o.bottom_z, z0);
  const double hi_z = std::min(o.top_z, z1);
  if (!(hi_z > lo_z)) {
    throw std::invalid_argument("FinOptions: bottom_z = " + Num(o.bottom_z) + " and top_z = " +
                                Num(o.top_z) + " leave no fin inside " + p.Describe() +
                                " (inner wall spans z " + Num(z0) + ".." + Num(z1) + ")");
  }
  const double t_lo = o.bottom_z > z0 ? SolveOffsetZ(p, o.inset, lo_z, 0.0, t_end) : 0.0;
  const double t_hi = o.top_z < z1 ? SolveOffsetZ(p, o.inset, hi_z, 0.0, t_end) : t_end;
  // Even spacing along the outline's own arc length.
  const int n = kTableIntervals;
  std::vector<double> ts(n + 1), acc(n + 1, 0.0);
  for (int i = 0; i <= n; ++i) ts[i] = t_lo + (t_hi - t_lo) * i / n;
  for (int i = 1; i <= n; ++i)
    acc[i] = acc[i - 1] + (Offset(p, ts[i], o.inset) - Offset(p, ts[i - 1], o.inset)).norm();
  FinOutline out;
  out.apex = t_hi >= 1.0;
  for (int k = 0; k <= o.samples; ++k) {
    double t;
    if (k == 0) {
      t = t_lo;
    } else if (k == o.samples) {
      t = t_hi;
    } else {
      const double s = acc.back() * k / o.samples;
      const int j = static_cast<int>(std::lower_bound(acc.begin(), acc.end(), s) - acc.begin());
      const int j0 = std::clamp(j - 1, 0, n - 1);
      const double f = (s - acc[j0]) / std::max(acc[j0 + 1] - acc[j0], 1e-300);
      t = ts[j0] + std::clamp(f, 0.0, 1.0) * (ts[j0 + 1] - ts[j0]);
    }
    Eigen::Vector2d q = Offset(p, t, o.inset);
    if (k == 0) q.y() = lo_z;
    if (k == o.samples && !out.apex) q.y() = hi_z;
    if (k == o.samples && out.apex) q.x() = 0.0;
    out.points.push_back(q);
  }
  return out;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// RevolutionProfile

void RevolutionProfile::Tabulate() {
  const int n = kTableIntervals;
  table_t_.resize(n + 1);
  arc_length_.assign(n + 1, 0.0);
  Eigen::Vector2d prev = Point(0.0);
  table_t_[0] = 0.0;
  for (int i = 1; i <= n; ++i) {
    const double t = static_cast<double>(i) / n;
    table_t_[i] = t;
    const Eigen::Vector2d q = Point(t);
    // Chord plus the midpoint correction (Simpson-like): two half chords are closer to the arc.
    const Eigen::Vector2d mid = Point(t - 0.5 / n);
    const double two_half = (mid - prev).norm() + (q - mid).norm();
    const double chord = (q - prev).norm();
    arc_length_[i] = arc_length_[i - 1] + (4.0 * two_half - chord) / 3.0;
    prev = q;
  }
}

double RevolutionProfile::ParameterAtArcLength(double s) const {
  if (s <= 0.0) return 0.0;
  if (s >= arc_length_.back()) return 1.0;
  const int j = static_cast<int>(std::upper_bound(arc_length_.begin(), arc_length_.end(), s) -
                                 arc_length_.begin());
  const int i = std::clamp(j - 1, 0, static_cast<int>(arc_length_.size()) - 2);
  const double f = (s - arc_length_[i]) / (arc_length_[i + 1] - arc_length_[i]);
  return table_t_[i] + f * (table_t_[i + 1] - table_t_[i]);
}

double RevolutionProfile::ParameterAtZ(double z) const {
  double lo = 0.0, hi = 1.0;
  if (z <= Point(0.0).y()) return 0.0;
  if (z >= Point(1.0).y()) return 1.0;
  for (int it = 0; it < 100 && hi - lo > 1e-17; ++it) {
    const double mid = 0.5 * (lo + hi);
    if (Point(mid).y() < z) {
      lo = mid;
    } else {
      hi = mid;
    }
  }
  return 0.5 * (lo + hi);
}

double RevolutionProfile::RadiusAt(double z) const {
  if (z <= 0.0) return BaseRadius();
  if (z >= Height()) return 0.0;
  return Point(ParameterAtZ(z)).x();
}

double RevolutionProfile::SurfaceArea() const {
  // Pappus per sub-interval with Simpson's rule on 2 pi r ds.
  const int n = kTableIntervals;
  double area = 0.0;
  for (int i = 0; i < n; ++i) {
    const double t0 = static_cast<double>(i) / n, t1 = static_cast<double>(i + 1) / n;
    const double ds = arc_length_[i + 1] - arc_length_[i];
    const double r0 = Point(t0).x(), rm = Point(0.5 * (t0 + t1)).x(), r1 = Point(t1).x();
    area += 2.0 * kPi * ds * (r0 + 4.0 * rm + r1) / 6.0;
  }
  return area;
}

Eigen::Vector3d RevolutionProfile::SurfacePoint(double t, double phi) const {
  const Eigen::Vector2d p = Point(t);
  return {p.x() * std::cos(phi), p.x() * std::sin(phi), p.y()};
}

Eigen::Vector3d RevolutionProfile::SurfaceNormal(double t, double phi) const {
  const Eigen::Vector2d n = Normal(t);
  return {n.x() * std::cos(phi), n.x() * std::sin(phi), n.y()};
}

RevolutionProfile::Closest RevolutionProfile::ClosestPoint(const Eigen::Vector3d& p) const {
  const double rho = std::hypot(p.x(), p.y());
  const double phi = rho > 0.0 ? std::atan2(p.y(), p.x()) : 0.0;
  const Eigen::Vector2d q(rho, p.z());
  // Coarse scan on a 1024-interval grid, then refinement around the best.
  const int n = 1024;
  int best = 0;
  double best_d2 = std::numeric_limits<double>::infinity();
  for (int i = 0; i <= n; ++i) {
    const double d2 = (Point(static_cast<double>(i) / n) - q).squaredNorm();
    if (d2 < best_d2) {
      best_d2 = d2;
      best = i;
    }
  }
  // Refine on h(t) = (q - P(t)) . tangent(t), which is zero at the foot of the perpendicular:
  // positive before it, negative after. Bisection to full precision (the distance itself is
  // too flat at its minimum to locate t better than ~1e-8).
  auto h = [&](double t) {
    const Eigen::Vector2d nt = Normal(t);
    return (q - Point(t)).dot(Eigen::Vector2d(-nt.y(), nt.x()));
  };
  double lo = std::max(0.0, (best - 1.0) / n), hi = std::min(1.0, (best + 1.0) / n);
  double t = static_cast<double>(best) / n;
  const double h_lo = h(lo), h_hi = h(hi);
  if (h_lo > 0.0 && h_hi < 0.0) {
    for (int it = 0; it < 200; ++it) {
      const double mid = 0.5 * (lo + hi);
      if (mid <= lo || mid >= hi) break;
      (h(mid) > 0.0 ? lo : hi) = mid;
    }
    t = 0.5 * (lo + hi);
  } else if (h_lo <= 0.0 && lo == 0.0) {
    t = 0.0;  // beyond the base rim
  } else if (h_hi >= 0.0 && hi == 1.0) {
    t = 1.0;
  }
  for (double cand : {0.0, 1.0}) {
    if ((Point(cand) - q).squaredNorm() < (Point(t) - q).squaredNorm()) t = cand;
  }
  Closest c;
  c.t = t;
  c.phi = phi;
  c.point = SurfacePoint(t, phi);
  c.normal = SurfaceNormal(t, phi);
  const Eigen::Vector2d diff = q - Point(t);
  const double dist = diff.norm();
  c.signed_distance = diff.dot(Normal(t)) >= 0.0 ? dist : -dist;
  return c;
}

// ---------------------------------------------------------------------------------------------
// Options

void CylinderCapOptions::Check() const {
  RequirePositive("CylinderCapOptions.radius", radius);
  RequirePositive("CylinderCapOptions.height", height);
  if (height < radius) {
    ThrowFieldError("CylinderCapOptions.height", height,
                    "must be >= radius (" + Num(radius) + ") so the hemispherical cap fits");
  }
}

void ConeOptions::Check() const {
  RequirePositive("ConeOptions.base_radius", base_radius);
  RequirePositive("ConeOptions.height", height);
  RequirePositive("ConeOptions.tip_radius", tip_radius);
  if (tip_radius >= base_radius) {
    ThrowFieldError("ConeOptions.tip_radius", tip_radius,
                    "must be < base_radius (" + Num(base_radius) + ") for the cone to narrow");
  }
  if (tip_radius >= height) {
    ThrowFieldError("ConeOptions.tip_radius", tip_radius, "must be < height (" + Num(height) + ")");
  }
}

void SplineOptions::Check() const {
  const int n = static_cast<int>(control_points.size());
  if (n < 2) ThrowFieldError("SplineOptions.control_points.size()", n, "must be >= 2");
  for (int i = 0; i < n; ++i) {
    const std::string name = "SplineOptions.control_points[" + std::to_string(i) + "]";
    const double z = control_points[i].x(), r = control_points[i].y();
    if (!std::isfinite(z) || !std::isfinite(r)) ThrowFieldError(name + ".z/r", z, "must be finite");
    if (i == 0 && z != 0.0) ThrowFieldError(name + ".z", z, "must be 0 (the base plane)");
    if (i > 0 && !(z > control_points[i - 1].x())) {
      ThrowFieldError(name + ".z", z,
                      "must be > the previous z (" + Num(control_points[i - 1].x()) + ")");
    }
    if (i + 1 < n && !(r > 0.0))
      ThrowFieldError(name + ".r", r, "must be > 0 (only the tip is on the axis)");
    if (i + 1 == n && r != 0.0)
      ThrowFieldError(name + ".r", r, "must be 0 (the tip is on the axis)");
  }
}

void TessellationOptions::Check() const {
  if (segments < 3 || segments > 1000000) {
    ThrowFieldError("TessellationOptions.segments", segments, "must be in [3, 1000000]");
  }
  if (rings < 0 || rings > 1000000) {
    ThrowFieldError("TessellationOptions.rings", rings, "must be in [0, 1000000] (0 = automatic)");
  }
}

TessellationOptions TessellationOptions::ForTriangleCount(const RevolutionProfile& profile,
                                                          int triangles) {
  if (triangles < 3) ThrowFieldError("ForTriangleCount triangles", triangles, "must be >= 3");
  const double length = profile.ArcLength();
  const double r0 = profile.BaseRadius();
  TessellationOptions t;
  t.segments = std::max(3, static_cast<int>(std::lround(std::sqrt(triangles * kPi * r0 / length))));
  t.rings = std::max(
      1, static_cast<int>(std::lround((static_cast<double>(triangles) / t.segments + 1.0) / 2.0)));
  return t;
}

void FinOptions::Check() const {
  RequirePositive("FinOptions.thickness", thickness);
  if (!(inset >= 0.0) || !std::isfinite(inset))
    ThrowFieldError("FinOptions.inset", inset, "must be finite and >= 0");
  if (!std::isfinite(bottom_z)) ThrowFieldError("FinOptions.bottom_z", bottom_z, "must be finite");
  if (std::isnan(top_z)) ThrowFieldError("FinOptions.top_z", top_z, "must not be NaN");
  if (!(top_z > bottom_z))
    ThrowFieldError("FinOptions.top_z", top_z, "must be > bottom_z (" + Num(bottom_z) + ")");
  if (samples < 2 || samples > 1000000)
    ThrowFieldError("FinOptions.samples", samples, "must be in [2, 1000000]");
}

void SensorShapeOptions::Check() const {
  switch (shape) {
    case SensorShape::kCylinderCap:
      cylinder.Check();
      break;
    case SensorShape::kCone:
      cone.Check();
      break;
    case SensorShape::kSpline:
      spline.Check();
      break;
  }
  tessellation.Check();
}

// ---------------------------------------------------------------------------------------------
// Factories

std::shared_ptr<const RevolutionProfile> MakeCylinderCapProfile(const CylinderCapOptions& options) {
  options.Check();
  return std::make_shared<CylinderCapProfile>(options);
}

std::shared_ptr<const RevolutionProfile> MakeConeProfile(const ConeOptions& options) {
  options.Check();
  return std::make_shared<ConeProfile>(options);
}

std::shared_ptr<const RevolutionProfile> MakeSplineProfile(const SplineOptions& options) {
  options.Check();
  return std::make_shared<SplineProfile>(options);
}

TriangleMesh MakeRevolutionMesh(const RevolutionProfile& profile,
                                const TessellationOptions& tessellation) {
  tessellation.Check();
  const int segs = tessellation.segments;
  int rings = tessellation.rings;
  if (rings == 0) {
    const double spacing = 2.0 * kPi * profile.BaseRadius() / segs;
    const double automatic = profile.ArcLength() / spacing;
    // Far more than the cap below: checked before it is rounded into an int.
    rings = automatic > 1e9 ? 1000000000 : std::max(1, static_cast<int>(std::lround(automatic)));
  }
  // Before anything is allocated: a thin, tall profile with rings = 0 asks for a great many.
  if (static_cast<double>(segs) * rings > kMaxRevolutionVertices) {
    ThrowFieldError("TessellationOptions.segments", static_cast<double>(segs) * rings,
                    "x rings (the mesh's vertices) must be at most " +
                        std::to_string(static_cast<long long>(kMaxRevolutionVertices)) +
                        " (fewer segments, or set rings)");
  }
  TriangleMesh mesh;
  mesh.vertices.reserve(static_cast<std::size_t>(segs) * rings + 1);
  mesh.normals.reserve(mesh.vertices.capacity());
  std::vector<double> cos_phi(segs), sin_phi(segs);
  for (int j = 0; j < segs; ++j) {
    const double phi = 2.0 * kPi * j / segs;
    cos_phi[j] = std::cos(phi);
    sin_phi[j] = std::sin(phi);
  }
  const double length = profile.ArcLength();
  for (int i = 0; i < rings; ++i) {
    const double t = i == 0 ? 0.0 : profile.ParameterAtArcLength(length * i / rings);
    const Eigen::Vector2d p = profile.Point(t);
    const Eigen::Vector2d n = profile.Normal(t);
    for (int j = 0; j < segs; ++j) {
      mesh.vertices.emplace_back(p.x() * cos_phi[j], p.x() * sin_phi[j], i == 0 ? 0.0 : p.y());
      mesh.normals.emplace_back(n.x() * cos_phi[j], n.x() * sin_phi[j], n.y());
    }
  }
  const int tip = static_cast<int>(mesh.vertices.size());
  mesh.vertices.emplace_back(0.0, 0.0, profile.Height());
  mesh.normals.emplace_back(0.0, 0.0, 1.0);
  mesh.triangles.reserve(static_cast<std::size_t>(segs) * (2 * rings - 1));
  for (int i = 0; i + 1 < rings; ++i) {
    for (int j = 0; j < segs; ++j) {
      const int jn = (j + 1) % segs;
      const int a = i * segs + j, b = i * segs + jn, c = (i + 1) * segs + jn,
                d = (i + 1) * segs + j;
      mesh.triangles.emplace_back(a, b, c);
      mesh.triangles.emplace_back(a, c, d);
    }
  }
  for (int j = 0; j < segs; ++j) {
    const int i = rings - 1;
    mesh.triangles.emplace_back(i * segs + j, i * segs + (j + 1) % segs, tip);
  }
  return mesh;
}

SensorShape ParseSensorShape(std::string_view name) {
  std::string s(name);
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return std::tolower(c); });
  if (s == "cylinder" || s == "cylinder-cap" || s == "cylinder_cap")
    return SensorShape::kCylinderCap;
  if (s == "cone") return SensorShape::kCone;
  if (s == "spline") return SensorShape::kSpline;
  throw std::invalid_argument("unknown sensor shape '" + std::string(name) +
                              "' (expected cylinder, cone or spline)");
}

std::string_view SensorShapeName(SensorShape shape) {
  switch (shape) {
    case SensorShape::kCylinderCap:
      return "cylinder";
    case SensorShape::kCone:
      return "cone";
    case SensorShape::kSpline:
      return "spline";
  }
  return "unknown";
}

std::shared_ptr<const RevolutionProfile> MakeProfile(const SensorShapeOptions& options) {
  options.Check();
  switch (options.shape) {
    case SensorShape::kCylinderCap:
      return MakeCylinderCapProfile(options.cylinder);
    case SensorShape::kCone:
      return MakeConeProfile(options.cone);
    case SensorShape::kSpline:
      return MakeSplineProfile(options.spline);
  }
  throw std::invalid_argument("SensorShapeOptions.shape has an invalid value " +
                              std::to_string(static_cast<int>(options.shape)));
}

TriangleMesh MakeSensorMesh(const SensorShapeOptions& options) {
  return MakeRevolutionMesh(*MakeProfile(options), options.tessellation);
}

// ---------------------------------------------------------------------------------------------
// Fins

TriangleMesh MakeFin(const FinOptions& options, const RevolutionProfile& profile, FinPlane plane) {
  if (!options.enabled) return {};
  const FinOutline outline = ComputeFinOutline(options, profile);
  const int m = static_cast<int>(outline.points.size()) - 1;  // top index
  // Polygon CCW in (a, z): right chain up, then left chain down (the apex is shared).
  std::vector<Eigen::Vector2d> poly;
  std::vector<int> right(m + 1), left(m + 1);
  for (int k = 0; k <= m; ++k) {
    right[k] = static_cast<int>(poly.size());
    poly.emplace_back(outline.points[k].x(), outline.points[k].y());
  }
  for (int k = m; k >= 0; --k) {
    if (k == m && outline.apex) {
      left[k] = right[k];
      continue;
    }
    left[k] = static_cast<int>(poly.size());
    poly.emplace_back(-outline.points[k].x(), outline.points[k].y());
  }
  const int np = static_cast<int>(poly.size());
  const double h = 0.5 * options.thickness;
  TriangleMesh mesh;
  // Local frame (a, b, z) = (x, y, z) for the xz fin; vertices [0, np) at b = -h, [np, 2np) at +h.
  for (int side = 0; side < 2; ++side) {
    const double b = side == 0 ? -h : h;
    for (const auto& q : poly) mesh.vertices.emplace_back(q.x(), b, q.y());
  }
  // Caps: CCW in (a, z) faces -b.
  for (int k = 0; k < m; ++k) {
    const int r0 = right[k], r1 = right[k + 1], l0 = left[k], l1 = left[k + 1];
    std::vector<Eigen::Vector3i> tris;
    if (r1 != l1) tris.emplace_back(r0, r1, l1);
    tris.emplace_back(r0, l1, l0);
    for (const auto& f : tris) {
      mesh.triangles.emplace_back(f[0], f[1], f[2]);                 // b = -h, faces -b
      mesh.triangles.emplace_back(f[0] + np, f[2] + np, f[1] + np);  // b = +h, faces +b
    }
  }
  // Side walls along every polygon edge (outward = right of the CCW edge direction).
  for (int i = 0; i < np; ++i) {
    const int j = (i + 1) % np;
    mesh.triangles.emplace_back(i, j + np, j);
    mesh.triangles.emplace_back(i, i + np, j + np);
  }
  if (plane == FinPlane::kYZ) {
    // Rotate +90 deg about z: (x, y, z) -> (-y, x, z), exact in floating point.
    for (auto& v : mesh.vertices) v = Eigen::Vector3d(-v.y(), v.x(), v.z());
  }
  mesh.ComputeVertexNormals();
  return mesh;
}

TriangleMesh MakeFins(const FinOptions& options, const RevolutionProfile& profile) {
  TriangleMesh fins = MakeFin(options, profile, FinPlane::kXZ);
  fins.Append(MakeFin(options, profile, FinPlane::kYZ));
  return fins;
}

double FinFoldZ(const FinOptions& options, const RevolutionProfile& profile) {
  options.Check();
  FinOptions whole = options;
  whole.top_z = std::numeric_limits<double>::infinity();
  double fold_z = 0.0;
  OutlineEnd(whole, profile, &fold_z);
  return fold_z;
}

double FinHalfWidthAt(const FinOptions& options, const RevolutionProfile& profile, double z) {
  options.Check();
  if (!options.enabled) return 0.0;
  // Same clipping as ComputeFinOutline, without tabulating the whole outline (~100 profile
  // evaluations per call). The fold check is MakeFin's.
  const double z0 = Offset(profile, 0.0, options.inset).y();
  double t_end = 1.0;
  if (options.top_z < profile.Height()) {
    // Cut below the tip: bisect only below the cut, where the outline is a graph over z.
    double fold_z = 0.0;
    t_end = OutlineEnd(options, profile, &fold_z);
  }
  const double z1 = Offset(profile, t_end, options.inset).y();
  const double lo_z = std::max(options.bottom_z, z0);
  const double hi_z = std::min(options.top_z, z1);
  if (!(z >= lo_z && z <= hi_z)) return 0.0;
  const double t = SolveOffsetZ(profile, options.inset, z, 0.0, t_end);
  return std::max(0.0, Offset(profile, t, options.inset).x());
}

SplineOptions FitInscribedProfile(const Bvh& mesh, int samples) {
  if (samples < 3) ThrowFieldError("FitInscribedProfile samples", samples, "must be >= 3");
  Ray up;
  up.origin = Eigen::Vector3d(0.0, 0.0, 1e-6);
  up.direction = Eigen::Vector3d::UnitZ();
  const auto top = mesh.Intersect(up);
  if (!top) {
    throw std::invalid_argument(
        "FitInscribedProfile: the sensor axis (x = y = 0, z > 0) does not meet the mesh; the mesh "
        "must be a finger around the +z axis in the sensor frame");
  }
  const double height = top->t + up.origin.z();
  constexpr int kAzimuths = 16;
  SplineOptions spline;
  spline.control_points.clear();
  for (int i = 0; i < samples; ++i) {
    // Denser toward the tip, where the radius changes fastest: z = h (1 - (1 - s)^2).
    const double s = static_cast<double>(i) / samples;
    const double z = std::max(height * (1.0 - (1.0 - s) * (1.0 - s)), 1e-3);
    double radius = std::numeric_limits<double>::infinity();
    for (int a = 0; a < kAzimuths; ++a) {
      const double phi = (a + 0.5) * 2.0 * std::numbers::pi / kAzimuths;
      Ray ray;
      ray.origin = Eigen::Vector3d(0.0, 0.0, z);
      ray.direction = Eigen::Vector3d(std::cos(phi), std::sin(phi), 0.0);
      const auto hit = mesh.Intersect(ray);
      if (!hit) {
        throw std::invalid_argument(
            "FitInscribedProfile: no wall around the axis at z = " + std::to_string(z) +
            " mm (azimuth " + std::to_string(phi * 180.0 / std::numbers::pi) + " deg)");
      }
      radius = std::min(radius, hit->t);
    }
    // The base ring itself is the mesh's open boundary: sample just above it, store at z = 0.
    spline.control_points.emplace_back(i == 0 ? 0.0 : z, radius);
  }
  spline.control_points.emplace_back(height, 0.0);
  spline.Check();
  return spline;
}

}  // namespace gs360
