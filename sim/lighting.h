#pragma once
// Cross-LED illumination of the GelSight360 (paper, "Sensor Illumination Strategy") and the
// coating's reflectance, for the simulated tactile camera.
//
// LEDs (sensor frame, mm): point lights with a Lambertian emission lobe max(0, cos)^m about
// their axis.
//   red   on both faces of the xz board (y = +-thickness/2, shining +-y), one column on each side
//         of the axis (x = +-fin_led_radial * fin half-width) at each of fin_led_heights;
//   green the same on the yz board (x = +-thickness/2, shining +-x);
//   blue  a ring of blue_ring_count LEDs at z = blue_ring_z, radius blue_ring_radius * base
//         radius, shining +z with a narrow lobe (blue_emission_exponent), placed between the fins.
// Irradiance from an LED at distance d: intensity * lobe * exp(-attenuation * d) /
// (d^2 + led_size^2) (inverse square, softened over the LED's size, with absorption in the
// epoxy and elastomer), so the tip, far from the fin LEDs, is lit mostly by the blue ring as in
// the paper. Each channel sees only its own LEDs (no spectral crosstalk).
//
// Coating (semi-specular): radiance = sum over LEDs of E * (albedo * max(0, n.l) +
// specular * max(0, n.h)^shininess) for n.l > 0, with h the half vector between the light and
// the view direction (Blinn-Phong). Shadows: the fins block the straight path from an LED to a
// point (analytic slab test); the gel does not shadow itself and there is no refraction at the
// epoxy/gel interfaces or inter-reflection. The ambient floor is added by the camera after
// exposure (TactileCameraOptions).
//
// Thread safety: immutable after construction; Shade() may be called from any thread.

#include <Eigen/Core>
#include <array>
#include <vector>

#include "geometry/shapes.h"

namespace gs360 {

struct LightingOptions {
  // Fin LEDs: heights as fractions of the sensor height, radial position as a fraction of the
  // fin half-width at that height.
  std::vector<double> fin_led_heights = {0.12, 0.32};
  double fin_led_radial = 0.55;
  int blue_ring_count = 12;
  double blue_ring_radius = 0.35;  // fraction of the base radius
  double blue_ring_z = -1.0;  // mm (on the base board, below the gel, out of the camera's view)
  // Relative LED intensities per colour (resistor values in the real sensor).
  double red_intensity = 1.0;
  double green_intensity = 1.0;
  double blue_intensity = 10.0;
  int emission_exponent = 1;  // m of the LED lobe (1 = Lambertian emitter)
  int blue_emission_exponent = 16;
  double attenuation = 0.02;  // 1/mm, absorption along the light path
  double led_size = 0.6;      // mm, softens 1/d^2 near an LED
  double albedo = 0.75;       // diffuse part of the coating
  double specular = 0.2;      // Blinn-Phong lobe weight of the coating
  int shininess = 16;         // Blinn-Phong exponent
  bool fin_shadows = true;    // fins block LED light

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

struct Led {
  Eigen::Vector3d position = Eigen::Vector3d::Zero();  // sensor frame, mm
  Eigen::Vector3d axis = Eigen::Vector3d::UnitZ();     // unit, direction of peak emission
  int channel = 0;                                     // 0 red, 1 green, 2 blue
  double intensity = 1.0;
  int exponent = 1;
};

class Lighting {
 public:
  // Lays out the LEDs on `profile` with `fins` (the same fins the camera sees). Throws
  // std::invalid_argument for invalid options.
  Lighting(const LightingOptions& options, const RevolutionProfile& profile,
           const FinOptions& fins);

  // Linear radiance (R, G, B; arbitrary units, scaled by the camera's exposure) leaving the
  // coating at `point` (sensor frame) toward the camera. `outward_normal` is the gel's outward
  // unit normal there (the coating is seen and lit from the inside, i.e. along -outward_normal);
  // `to_camera` the unit direction from the point to the camera centre.
  Eigen::Array3d Shade(const Eigen::Vector3d& point, const Eigen::Vector3d& outward_normal,
                       const Eigen::Vector3d& to_camera) const;

  // True when a fin blocks the segment from `a` to `b` (both sensor frame); never without fins
  // (FinOptions::enabled false: the LEDs stay where the boards would stand).
  bool FinBlocks(const Eigen::Vector3d& a, const Eigen::Vector3d& b) const;

  const std::vector<Led>& leds() const { return leds_; }
  const LightingOptions& options() const { return options_; }

 private:
  double FinHalfWidth(double z) const;  // tabulated FinHalfWidthAt; 0 outside the fin

  LightingOptions options_;
  std::vector<Led> leds_;
  double fin_z0_ = 0.0;  // first table height
  double fin_dz_ = 1.0;  // table step
  std::vector<double> fin_half_width_;
  bool fins_cast_shadows_ = true;
};

}  // namespace gs360
