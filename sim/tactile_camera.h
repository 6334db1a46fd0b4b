#pragma once
// The simulated GelSight360 camera: renders the 8-bit colour image the sensor's camera would
// see, with the calibration ball where the virtual CNC TRULY is at the frame's capture time (a
// frame captured before the motion has finished shows the ball where it was, not where it was
// commanded).
//
// Optical model (what is included):
//   - the TRUE fisheye camera (sim/rig_model.h: perturbed intrinsics and pose); every pixel's ray
//     is cast from the true camera centre: first hit on a fin (grey, with a fixed per-pixel
//     pattern) or on the gel's outer surface (the coating), or nothing (black outside the image
//     circle, a dark housing level inside it);
//   - the gel indentation under the ball (sim/gel_deformation.h: elastic edge, bulge), ray-cast on
//     a locally refined displaced mesh, so an indentation seen obliquely hides what is behind it;
//   - cross-LED lighting with inverse-square fall-off and a semi-specular coating (diffuse plus
//     a Blinn-Phong lobe), fins shadowing the LEDs (sim/lighting.h);
//   - the lens's relative illumination (vignetting) V(theta) = 1 + v2 (theta/theta_max)^2 +
//     v4 (theta/theta_max)^4, an ambient floor, shot noise (variance shot_gain * signal, DN^2),
//     read noise (sigma read_noise DN), 8-bit quantisation with clipping, slow per-channel LED
//     drift (a seeded smooth function of the run time, at most drift_amplitude; it scales the
//     whole image, since all light comes from the LEDs).
// Left out: refraction at the epoxy / gel interfaces, inter-reflections and light scattered
// inside the gel (beyond the ambient floor), self-shadowing of the gel, the ball itself (the
// coating is opaque), defocus / lens blur, spectral crosstalk between the LED colours and the
// Bayer pattern, rolling shutter and motion blur (the ball is taken at one instant), fixed-pattern
// noise of the sensor (only the fins have a fixed pattern), LED bodies as occluders (they are
// inside the fins' thickness), the LEDs' own light reaching the camera directly.
//
// Speed: the static background (rays, hits, shaded no-contact signal and its noise sigma) is
// built once per camera on `threads` threads. A frame writes the whole image from it (drift gain,
// plus noise from a precomputed bank of Gaussian samples read at a seeded per-frame offset: no
// per-pixel random draws; the background's shot noise uses its drift-free level, < 1% off), then
// re-renders only the pixels in the projected bounding box of the displaced patch: each refined
// triangle is tested against the pixels its projection covers with an exact watertight ray test
// (a z-buffer with ray-traced depths), and the visible hits are shaded. The re-rendered pixels'
// drift-free signal is kept: the next frame with the ball at exactly the same place (a dwell:
// several frames of one press) only re-applies drift and noise to them. Its speed:
// bench/bench_sim_camera, figures in docs/benchmarks.md.
//
// Images: cv::Mat CV_8UC3 in OpenCV's BGR channel order (cv::imwrite writes the right colours);
// "red" is channel 2, "blue" channel 0.
//
// Determinism: the same rig, options and sequence of calls give identical images; RenderAtBall
// with the same arguments always gives the same image.
//
// Thread safety: not thread-safe (Render* update the last frame's ground truth and the frame
// counter); use one camera per thread. The rig is shared read-only.

#include <Eigen/Core>
#include <array>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <vector>

#include <opencv2/core.hpp>

#include "geometry/fisheye.h"
#include "sim/gel_deformation.h"
#include "sim/lighting.h"
#include "sim/rig_model.h"

namespace gs360 {

struct SensorModelOptions {
  // Relative illumination of the lens: V = 1 + v2 s^2 + v4 s^4, s = theta / max_theta.
  double vignetting_v2 = -0.15;
  double vignetting_v4 = -0.20;
  bool noise = true;        // shot + read noise (off: noise-free images, still quantised)
  double shot_gain = 0.05;  // DN per electron: shot-noise variance = shot_gain * signal (DN^2)
  double read_noise = 1.0;  // DN, sigma
  // LED drift: per-channel gain 1 + drift_amplitude * sum_k w_k sin(2 pi t / P_k + phase_ck),
  // t the run time (h), P = drift_periods_h, w = (0.6, 0.3, 0.1) (sum 1), phases seeded.
  double drift_amplitude = 0.015;
  std::array<double, 3> drift_periods_h = {7.3, 2.9, 1.1};
  // Exposure (locked, computed once): the 99.5th percentile of the brightest channel of the
  // no-contact gel image is exposure_target DN.
  double exposure_target = 160.0;
  std::array<double, 3> ambient_dn = {7.0, 7.0, 9.0};  // ambient floor (R, G, B), DN
  double fin_grey = 100.0;    // DN of the fins at the image centre (before vignetting)
  double fin_pattern = 0.05;  // relative fixed-pattern variation of the fins
  double housing_dn = 5.0;    // rays in the image circle that meet neither gel nor fin
  std::uint64_t seed = 1;     // noise bank, per-frame noise offsets, fin pattern, drift phases
  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

struct TactileCameraOptions {
  LightingOptions lighting;
  GelDeformationOptions gel;
  SensorModelOptions sensor;
  int threads = 2;  // for the background build (1..64)
  void Check() const;
};

// Tool (machine) position in the machine frame (MPos, mm) at an instant: e.g. the virtual CNC's
// TruePosition(t).
using MachinePositionFn = std::function<Eigen::Vector3d(std::chrono::steady_clock::time_point)>;

struct TactileCameraStats {
  double background_seconds = 0.0;  // building the static background
  double last_frame_seconds = 0.0;  // the last Render* call (wall time), of which:
  double last_image_seconds = 0.0;  //   whole-image noise and quantisation pass
  double last_patch_seconds = 0.0;  //   building the displaced patch
  double last_roi_seconds = 0.0;    //   ray tests, shading and truth of the ROI
  int last_roi_pixels = 0;          // pixels re-rendered in the last frame
  int last_patch_triangles = 0;     // refined patch size in the last frame
  std::uint64_t frames = 0;         // frames rendered so far
};

struct FrameTruth;  // sim/ground_truth.h

class TactileCamera {
 public:
  using Clock = std::chrono::steady_clock;

  // Builds the static background on `threads` threads (its time: bench/bench_sim_camera,
  // docs/benchmarks.md, "Virtual rig"). The run starts now (SetRunStart).
  // Throws std::invalid_argument for invalid options; std::runtime_error if the rig's camera
  // sees no gel at all.
  explicit TactileCamera(std::shared_ptr<const SimRig> rig,
                         const TactileCameraOptions& options = {});
  ~TactileCamera();
  TactileCamera(const TactileCamera&) = delete;
  TactileCamera& operator=(const TactileCamera&) = delete;

  // Where the tool is at any instant (machine frame). Needed by Render().
  void SetMachinePositionSource(MachinePositionFn source);
  // Reference instant for LED drift (run time = frame time - run start).
  void SetRunStart(Clock::time_point start);
  Clock::time_point run_start() const { return run_start_; }

  // The frame captured at `capture_time`: ball centre = machine_from_sensor^-1 (source(t) +
  // tool_offset). Frame index = the number of Render() calls before this one (seeds the noise).
  // Throws std::logic_error when no machine position source is set.
  cv::Mat Render(Clock::time_point capture_time);
  // For tests and tools: the ball centre in the sensor frame (nullopt = no ball), the frame index
  // that seeds the noise, and the run time (s) that sets the LED drift.
  cv::Mat RenderAtBall(const std::optional<Eigen::Vector3d>& ball_center_sensor,
                       std::uint64_t frame_index, double run_time_s = 0.0);
  // No contact: RenderAtBall(nullopt, frame_index, run_time_s).
  cv::Mat RenderReference(std::uint64_t frame_index, double run_time_s = 0.0);

  const SimRig& rig() const { return *rig_; }
  const TactileCameraOptions& options() const { return options_; }
  const Lighting& lighting() const { return *lighting_; }
  const TactileCameraStats& stats() const { return stats_; }
  int width() const { return width_; }
  int height() const { return height_; }
  // Per-channel LED gain at a run time (s), (R, G, B).
  Eigen::Array3d DriftGain(double run_time_s) const;

 private:
  friend class SimGroundTruth;
  struct Background;
  class PatchRender;  // RenderInto's re-rendered region (tactile_camera.cc)
  struct PatchCache;  // the last PatchRender's result, before drift and noise

  enum PixelKind : std::uint8_t { kOutside = 0, kGel = 1, kFin = 2, kNothing = 3 };

  void BuildBackground();
  // Renders into *out (BGR) with the ball at `ball` (sensor frame), with the options' gel model
  // or the rigid imprint; records the truth of the frame.
  void RenderInto(const std::optional<Eigen::Vector3d>& ball, std::uint64_t frame_index,
                  double run_time_s, bool rigid, cv::Mat* out);
  std::uint64_t NoiseOffset(std::uint64_t frame_index) const;
  // RenderInto's patch with the ball at `ball`: rendered into `dst` and kept in patch_cache_;
  // or patch_cache_'s pixels written again with this frame's drift `gain` and noise `z`.
  void RenderPatch(const Eigen::Vector3d& ball, bool rigid, const float gain[3],
                   const std::int16_t* z, std::uint8_t* dst);
  void ReusePatch(const float gain[3], const std::int16_t* z, std::uint8_t* dst);

  std::shared_ptr<const SimRig> rig_;
  TactileCameraOptions options_;
  std::unique_ptr<Lighting> lighting_;
  std::unique_ptr<GelPatchBuilder> patch_builder_;
  std::unique_ptr<GelPatchBuilder> rigid_patch_builder_;
  std::unique_ptr<Background> background_;
  std::unique_ptr<FrameTruth> last_truth_;
  std::unique_ptr<PatchCache> patch_cache_;
  MachinePositionFn position_source_;
  Clock::time_point run_start_;
  std::uint64_t next_frame_index_ = 0;
  TactileCameraStats stats_;
  int width_ = 0;
  int height_ = 0;
  std::array<std::array<double, 3>, 3> drift_phase_{};  // [channel][term]
};

}  // namespace gs360
