#pragma once
// Calibration stage 1, "intrinsics": the fisheye (Kannala-Brandt) model of the camera from
// checkerboard images taken before the sensor is assembled.
//
// Per image: cv::findChessboardCorners on the grey image (adaptive threshold, normalised), then
// cv::cornerSubPix. Then cv::fisheye::calibrate (RECOMPUTE_EXTRINSIC, CHECK_COND, FIX_SKEW, and
// the nominal intrinsics as the initial guess) on the images with a detected board. An image that
// OpenCV's CHECK_COND flags as ill-conditioned is rejected (reason recorded) and the calibration
// repeated without it, as long as min_images remain.
//
// Units: pixels for image quantities ((0, 0) the centre of the top-left pixel, as
// geometry/fisheye.h), mm for the board. The board frame is sim/checkerboard.h's / OpenCV's:
// inner corner (c, r) at (c * square_mm, r * square_mm, 0).
//
// Errors (std::runtime_error with a message naming the problem and the numbers): fewer than
// min_images images with a detected board; the detected corners reach too little of the field
// (radial coverage below min_radial_coverage: the distortion would be extrapolated); OpenCV's
// CHECK_COND failure that cannot be resolved by dropping images; an RMS reprojection error above
// max_rms_px. std::invalid_argument for invalid options, nominal intrinsics, or an image that is
// not CV_8UC1 / CV_8UC3 of the nominal size. An empty image (a file that did not decode) is
// rejected with its reason, not an error. Never a garbage result.

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "geometry/fisheye.h"
#include "geometry/rigid3.h"

namespace gs360 {

struct IntrinsicsOptions {
  int board_cols = 9;       // inner corners along the board's x (OpenCV pattern width)
  int board_rows = 6;       // inner corners along the board's y
  double square_mm = 5.0;   // square side (> 0)
  int min_images = 8;       // images with a detected board needed (>= 3)
  double max_rms_px = 1.0;  // the calibration fails above this RMS reprojection error (> 0)
  // Largest distance of any detected corner from the nominal principal point, as a fraction of
  // the nominal image circle's radius, at least this ((0, 1]).
  double min_radial_coverage = 0.6;
  // cornerSubPix half window (px, >= 1): 4 (9 x 9 px) has the smallest largest ray error over
  // boards rendered sharp and blurred by 1 and 2 px (`gs360 bench stress --only intrinsics`).
  int subpix_window = 4;
  int max_iterations = 200;  // cv::fisheye::calibrate termination (>= 1)
  double epsilon = 1e-12;    // ... and its parameter-change tolerance (> 0)
  // Throws std::invalid_argument naming the field and its value.
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("board_cols", self.board_cols);
    visit("board_rows", self.board_rows);
    visit("square_mm", self.square_mm);
    visit("min_images", self.min_images);
    visit("max_rms_px", self.max_rms_px);
    visit("min_radial_coverage", self.min_radial_coverage);
    visit("subpix_window", self.subpix_window);
    visit("max_iterations", self.max_iterations);
    visit("epsilon", self.epsilon);
  }
  void Check() const;
};

struct IntrinsicsImageReport {
  int index = 0;        // position in the input
  bool used = false;    // in the final calibration
  std::string reason;   // why it was rejected ("" if used)
  int corners = 0;      // detected corners (0 = no board)
  double rms_px = 0.0;  // reprojection RMS of this image under the result (used images only)
};

struct IntrinsicsResult {
  // The calibrated model: K and D from OpenCV, width / height / max_theta from the nominal.
  FisheyeIntrinsics intrinsics;
  double rms_px = 0.0;        // RMS reprojection error over all corners of the used images
  std::vector<int> used;      // input indices in the calibration
  std::vector<int> rejected;  // input indices left out (reasons in `images`)
  std::vector<IntrinsicsImageReport> images;  // one per input image, in input order
  std::vector<Rigid3d> cam_from_board;        // per used image (same order as `used`)
  double radial_coverage = 0.0;               // see IntrinsicsOptions::min_radial_coverage
};

// Why the bytes of a checkerboard image file cannot be trusted, before decoding: too short, or a
// PNG without its closing IEND chunk or a JPEG without its end-of-image marker (a truncated copy:
// OpenCV rejects the one and fills the other's missing rows with grey). nullopt if neither.
std::optional<std::string> ImageFileProblem(std::span<const std::uint8_t> bytes);

// `images`: grey (CV_8UC1) or BGR (CV_8UC3) checkerboard images of nominal.width x nominal.height.
// `nominal`: the lens's nominal model (initial guess; its max_theta is kept in the result). A
// nominal focal length up to 30 % off is only a starting point: when the fit from it fails, it is
// retried from focal lengths around it. Farther off, the std::runtime_error names the fx, fy the
// boards fit at, so that the rig's nominal camera can be corrected.
IntrinsicsResult CalibrateIntrinsics(std::span<const cv::Mat> images,
                                     const FisheyeIntrinsics& nominal,
                                     const IntrinsicsOptions& options = {});

// Largest angle (rad) between the rays of two models over a grid of pixels inside the valid
// field of both (step_px apart): how far apart two intrinsics are where it matters. Pixels
// valid in only one model are skipped. Throws std::invalid_argument for step_px < 1.
double MaxRayAngleDifference(const FisheyeIntrinsics& a, const FisheyeIntrinsics& b,
                             int step_px = 8);

}  // namespace gs360
