#include "sim/lighting.h"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <sstream>
#include <stdexcept>
#include <string>

#include "base/field_error.h"

namespace gs360 {
namespace {

[[noreturn]] void ThrowField(const std::string& field, double value, const std::string& why) {
  ThrowFieldError("LightingOptions." + field, value, why);
}

void RequireNonNegative(const std::string& field, double value) {
  if (!std::isfinite(value) || value < 0.0) ThrowField(field, value, "must be finite and >= 0");
}

// x^n for a small non-negative integer n (repeated squaring; pow() is several times slower).
inline double PowInt(double x, int n) {
  double result = 1.0;
  while (n > 0) {
    if (n & 1) result *= x;
    x *= x;
    n >>= 1;
  }
  return result;
}

constexpr int kFinTableSize = 1024;

}  // namespace

void LightingOptions::Check() const {
  if (fin_led_heights.empty()) {
    throw std::invalid_argument("LightingOptions.fin_led_heights is empty (need >= 1 height)");
  }
  for (std::size_t i = 0; i < fin_led_heights.size(); ++i) {
    const double h = fin_led_heights[i];
    if (!(h > 0.0 && h < 1.0)) {
      ThrowField("fin_led_heights[" + std::to_string(i) + "]", h, "must be in (0, 1)");
    }
  }
  if (!(fin_led_radial > 0.0 && fin_led_radial < 1.0)) {
    ThrowField("fin_led_radial", fin_led_radial, "must be in (0, 1)");
  }
  if (blue_ring_count < 1 || blue_ring_count > 256) {
    ThrowField("blue_ring_count", blue_ring_count, "must be in [1, 256]");
  }
  if (!(blue_ring_radius > 0.0 && blue_ring_radius < 1.0)) {
    ThrowField("blue_ring_radius", blue_ring_radius, "must be in (0, 1)");
  }
  if (!std::isfinite(blue_ring_z)) ThrowField("blue_ring_z", blue_ring_z, "must be finite");
  RequireNonNegative("red_intensity", red_intensity);
  RequireNonNegative("green_intensity", green_intensity);
  RequireNonNegative("blue_intensity", blue_intensity);
  if (emission_exponent < 0 || emission_exponent > 64) {
    ThrowField("emission_exponent", emission_exponent, "must be in [0, 64]");
  }
  if (blue_emission_exponent < 0 || blue_emission_exponent > 64) {
    ThrowField("blue_emission_exponent", blue_emission_exponent, "must be in [0, 64]");
  }
  RequireNonNegative("attenuation", attenuation);
  if (!std::isfinite(led_size) || !(led_size > 0.0)) {
    ThrowField("led_size", led_size, "must be finite and > 0");
  }
  RequireNonNegative("albedo", albedo);
  RequireNonNegative("specular", specular);
  if (shininess < 1 || shininess > 1024) ThrowField("shininess", shininess, "must be in [1, 1024]");
}

Lighting::Lighting(const LightingOptions& options, const RevolutionProfile& profile,
                   const FinOptions& fins)
    : options_(options) {
  options_.Check();
  fins.Check();
  // Fin outline table (FinHalfWidthAt solves for the offset curve each call: too slow per ray).
  // A sensor without fins keeps its LEDs where the boards would stand; nothing casts shadows.
  fins_cast_shadows_ = fins.enabled;
  FinOptions outline = fins;
  outline.enabled = true;
  const double height = profile.Height();
  const double z_top = std::min(height, fins.top_z);
  fin_z0_ = fins.bottom_z;
  fin_dz_ = std::max(1e-9, (z_top - fin_z0_) / (kFinTableSize - 1));
  fin_half_width_.resize(kFinTableSize);
  for (int i = 0; i < kFinTableSize; ++i) {
    fin_half_width_[i] = FinHalfWidthAt(outline, profile, fin_z0_ + i * fin_dz_);
  }
  fin_half_width_.push_back(0.0);  // guard for interpolation at the top

  const double half_thickness = 0.5 * fins.thickness;
  for (const double fraction : options_.fin_led_heights) {
    const double z = fraction * height;
    const double radial = options_.fin_led_radial * FinHalfWidth(z);
    if (radial <= 0.0) {
      ThrowField("fin_led_heights", fraction,
                 "puts fin LEDs at z = " + std::to_string(z) + " mm, outside the fins");
    }
    for (const double side : {1.0, -1.0}) {    // which half of the board (along the board)
      for (const double face : {1.0, -1.0}) {  // which face of the board
        Led red;
        red.position = Eigen::Vector3d(side * radial, face * half_thickness, z);
        red.axis = Eigen::Vector3d(0.0, face, 0.0);
        red.channel = 0;
        red.intensity = options_.red_intensity;
        red.exponent = options_.emission_exponent;
        leds_.push_back(red);
        Led green;
        green.position = Eigen::Vector3d(face * half_thickness, side * radial, z);
        green.axis = Eigen::Vector3d(face, 0.0, 0.0);
        green.channel = 1;
        green.intensity = options_.green_intensity;
        green.exponent = options_.emission_exponent;
        leds_.push_back(green);
      }
    }
  }
  const double ring_radius = options_.blue_ring_radius * profile.BaseRadius();
  for (int k = 0; k < options_.blue_ring_count; ++k) {
    const double phi = (k + 0.5) * 2.0 * std::numbers::pi / options_.blue_ring_count;
    Led blue;
    blue.position = Eigen::Vector3d(ring_radius * std::cos(phi), ring_radius * std::sin(phi),
                                    options_.blue_ring_z);
    blue.axis = Eigen::Vector3d::UnitZ();
    blue.channel = 2;
    blue.intensity = options_.blue_intensity;
    blue.exponent = options_.blue_emission_exponent;
    leds_.push_back(blue);
  }
}

double Lighting::FinHalfWidth(double z) const {
  const double s = (z - fin_z0_) / fin_dz_;
  if (!(s >= 0.0) || s > kFinTableSize - 1) return 0.0;
  const int i = static_cast<int>(s);
  const double f = s - i;
  return (1.0 - f) * fin_half_width_[i] + f * fin_half_width_[i + 1];
}

bool Lighting::FinBlocks(const Eigen::Vector3d& a, const Eigen::Vector3d& b) const {
  // Each fin is a slab around a plane through the axis (x = 0: yz fin, y = 0: xz fin); its
  // thickness is negligible for the crossing test, its outline is |along| <= half-width(z).
  if (!fins_cast_shadows_) return false;
  for (int plane_axis = 0; plane_axis < 2; ++plane_axis) {
    const double da = a[plane_axis], db = b[plane_axis];
    if (da * db >= 0.0) continue;  // both on one side (or on the plane: the LED's own board)
    const double s = da / (da - db);
    const Eigen::Vector3d q = a + s * (b - a);
    const double along = std::abs(q[1 - plane_axis]);
    if (along <= FinHalfWidth(q.z())) return true;
  }
  return false;
}

Eigen::Array3d Lighting::Shade(const Eigen::Vector3d& point, const Eigen::Vector3d& outward_normal,
                               const Eigen::Vector3d& to_camera) const {
  const Eigen::Vector3d n = -outward_normal;
  const double size2 = options_.led_size * options_.led_size;
  Eigen::Array3d radiance = Eigen::Array3d::Zero();
  for (const Led& led : leds_) {
    Eigen::Vector3d l = led.position - point;
    const double d2 = l.squaredNorm();
    const double d = std::sqrt(d2);
    if (!(d > 0.0)) continue;
    l /= d;
    const double n_dot_l = n.dot(l);
    if (n_dot_l <= 0.0) continue;
    const double cos_emit = -l.dot(led.axis);
    if (cos_emit <= 0.0) continue;
    if (options_.fin_shadows && FinBlocks(led.position, point)) continue;
    const double irradiance = led.intensity * PowInt(cos_emit, led.exponent) *
                              std::exp(-options_.attenuation * d) / (d2 + size2);
    const Eigen::Vector3d h = (l + to_camera).normalized();
    const double n_dot_h = std::max(0.0, n.dot(h));
    radiance[led.channel] += irradiance * (options_.albedo * n_dot_l +
                                           options_.specular * PowInt(n_dot_h, options_.shininess));
  }
  return radiance;
}

}  // namespace gs360
