#pragma once
// Checkerboard images through a fisheye camera, for the intrinsics stage (cv::fisheye::calibrate
// on images taken before the sensor is assembled). Render with the TRUE intrinsics
// (SimGroundTruth::TrueIntrinsics) to simulate the real camera.
//
// Board frame (mm): the inner corners lie on the plane z = 0 at (c * square_mm, r * square_mm, 0),
// c = 0..cols-1, r = 0..rows-1 (OpenCV's pattern size is (cols, rows)). Squares tile
// [-square, cols * square] x [-square, rows * square]; the square containing (x, y) is black
// when floor(x / square) + floor(y / square) is even. A white margin of border_squares squares
// surrounds them; beyond it is the background. Both faces of the board show the pattern (the
// generated poses always show its front: the camera looks along the board's +z).
//
// Image: CV_8UC1 grey, pixel (u, v) the average of supersample^2 rays through the pixel (rays
// interpolated bilinearly between the pixel's corner rays), then the lens's relative
// illumination, shot and read noise (seeded), 8-bit quantisation. Pixels outside the valid field
// are black.

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include <opencv2/core.hpp>

#include "geometry/fisheye.h"
#include "geometry/rigid3.h"

namespace gs360 {

struct CheckerboardOptions {
  int cols = 9;                 // inner corners along the board's x
  int rows = 6;                 // inner corners along the board's y
  double square_mm = 5.0;       // square side (mm)
  double border_squares = 1.0;  // white margin around the squares (in squares)
  int supersample = 4;          // rays per pixel along each axis (antialiasing)
  double white_dn = 205.0;
  double black_dn = 30.0;
  double background_dn = 75.0;
  double vignetting_v2 = -0.15;  // relative illumination 1 + v2 s^2 + v4 s^4, s = theta/max_theta
  double vignetting_v4 = -0.20;
  bool noise = true;
  double shot_gain = 0.05;  // DN per electron
  double read_noise = 1.0;  // DN
  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

// Inner corners (board frame), row-major: index r * cols + c.
std::vector<Eigen::Vector3d> CheckerboardCorners(const CheckerboardOptions& options);

// The board seen by a fisheye camera with `intrinsics` at pose cam_from_board. Deterministic for a
// seed. Throws std::invalid_argument for invalid options or intrinsics.
cv::Mat RenderCheckerboard(const CheckerboardOptions& options, const Rigid3d& cam_from_board,
                           const FisheyeIntrinsics& intrinsics, std::uint64_t seed);

struct CheckerboardPoseOptions {
  int count = 20;
  double min_distance_mm = 26.0;  // camera to board centre
  double max_distance_mm = 40.0;
  double max_field_deg = 58.0;  // direction of the board centre off the optical axis, at most
  double max_tilt_deg = 35.0;   // board tilt away from facing the camera, at most
  double max_roll_deg = 30.0;   // rotation of the board in its plane, at most
  double margin_px = 12.0;      // every corner this far inside the image and the valid field
  double min_corner_spacing_px = 7.0;  // neighbouring corners at least this far apart
  void Check() const;
};

// `count` poses cam_from_board spread over the field (board centres stratified from the optical
// axis out to max_field_deg and around in azimuth, so the outer corners reach the rim), each with
// every corner visible (inside the image and the valid field by margin_px) and the board's front
// facing the camera. Deterministic for a seed. Throws std::runtime_error if a pose cannot be
// found (the board is too large for the field at these distances).
std::vector<Rigid3d> CheckerboardPoses(const CheckerboardOptions& board,
                                       const FisheyeIntrinsics& intrinsics,
                                       const CheckerboardPoseOptions& options, std::uint64_t seed);

// A set of calibration shots: CheckerboardPoses(board, intrinsics, poses, seed), each rendered
// with its own noise seed (seed * 1000 + its index). Throws as those two.
std::vector<cv::Mat> RenderCheckerboardSet(const CheckerboardOptions& board,
                                           const FisheyeIntrinsics& intrinsics,
                                           const CheckerboardPoseOptions& poses,
                                           std::uint64_t seed);

// The nominal 160-degree lens (FisheyeIntrinsics::Default160) about as far off as the virtual
// rig's true lens is from it: fx 1.2 % longer, fy 0.3 % shorter than fx, the principal point
// (2.4, -1.8) px away, k1 0.011, k2 -0.0035. What lens calibration tests recover.
FisheyeIntrinsics PerturbedLens160();

}  // namespace gs360
