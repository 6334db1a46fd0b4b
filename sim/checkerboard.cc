#include "sim/checkerboard.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <numbers>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <string>

#include "base/field_error.h"
#include "sim/camera_random.h"

namespace gs360 {
namespace {

constexpr double kDegToRad = std::numbers::pi / 180.0;

void RequireDn(const std::string& field, double v) {
  if (!(v >= 0.0 && v <= 255.0)) ThrowFieldError(field, v, "must be in [0, 255]");
}

}  // namespace

void CheckerboardOptions::Check() const {
  if (cols < 2 || cols > 100)
    ThrowFieldError("CheckerboardOptions.cols", cols, "must be in [2, 100]");
  if (rows < 2 || rows > 100)
    ThrowFieldError("CheckerboardOptions.rows", rows, "must be in [2, 100]");
  if (!std::isfinite(square_mm) || !(square_mm > 0.0)) {
    ThrowFieldError("CheckerboardOptions.square_mm", square_mm, "must be finite and > 0");
  }
  if (!std::isfinite(border_squares) || border_squares < 0.0) {
    ThrowFieldError("CheckerboardOptions.border_squares", border_squares,
                    "must be finite and >= 0");
  }
  if (supersample < 1 || supersample > 16) {
    ThrowFieldError("CheckerboardOptions.supersample", supersample, "must be in [1, 16]");
  }
  RequireDn("CheckerboardOptions.white_dn", white_dn);
  RequireDn("CheckerboardOptions.black_dn", black_dn);
  RequireDn("CheckerboardOptions.background_dn", background_dn);
  if (!std::isfinite(vignetting_v2) || !std::isfinite(vignetting_v4)) {
    ThrowFieldError("CheckerboardOptions.vignetting_v2 + v4", vignetting_v2 + vignetting_v4,
                    "must be finite");
  }
  if (!std::isfinite(shot_gain) || shot_gain < 0.0) {
    ThrowFieldError("CheckerboardOptions.shot_gain", shot_gain, "must be finite and >= 0");
  }
  if (!std::isfinite(read_noise) || read_noise < 0.0) {
    ThrowFieldError("CheckerboardOptions.read_noise", read_noise, "must be finite and >= 0");
  }
}

void CheckerboardPoseOptions::Check() const {
  if (count < 1 || count > 10000)
    ThrowFieldError("CheckerboardPoseOptions.count", count, "must be in [1, 10000]");
  if (!(min_distance_mm > 0.0)) {
    ThrowFieldError("CheckerboardPoseOptions.min_distance_mm", min_distance_mm, "must be > 0");
  }
  if (!(max_distance_mm >= min_distance_mm) || !std::isfinite(max_distance_mm)) {
    ThrowFieldError("CheckerboardPoseOptions.max_distance_mm", max_distance_mm,
                    "must be finite and >= min_distance_mm");
  }
  if (!(max_field_deg >= 0.0 && max_field_deg < 90.0)) {
    ThrowFieldError("CheckerboardPoseOptions.max_field_deg", max_field_deg, "must be in [0, 90)");
  }
  if (!(max_tilt_deg >= 0.0 && max_tilt_deg < 80.0)) {
    ThrowFieldError("CheckerboardPoseOptions.max_tilt_deg", max_tilt_deg, "must be in [0, 80)");
  }
  if (!(max_roll_deg >= 0.0 && max_roll_deg <= 180.0)) {
    ThrowFieldError("CheckerboardPoseOptions.max_roll_deg", max_roll_deg, "must be in [0, 180]");
  }
  if (!(margin_px >= 0.0) || !std::isfinite(margin_px)) {
    ThrowFieldError("CheckerboardPoseOptions.margin_px", margin_px, "must be finite and >= 0");
  }
  if (!(min_corner_spacing_px >= 0.0) || !std::isfinite(min_corner_spacing_px)) {
    ThrowFieldError("CheckerboardPoseOptions.min_corner_spacing_px", min_corner_spacing_px,
                    "must be finite and >= 0");
  }
}

std::vector<Eigen::Vector3d> CheckerboardCorners(const CheckerboardOptions& options) {
  options.Check();
  std::vector<Eigen::Vector3d> corners;
  corners.reserve(static_cast<std::size_t>(options.cols) * options.rows);
  for (int r = 0; r < options.rows; ++r) {
    for (int c = 0; c < options.cols; ++c) {
      corners.emplace_back(c * options.square_mm, r * options.square_mm, 0.0);
    }
  }
  return corners;
}

cv::Mat RenderCheckerboard(const CheckerboardOptions& options, const Rigid3d& cam_from_board,
                           const FisheyeIntrinsics& intrinsics, std::uint64_t seed) {
  options.Check();
  const FisheyeCamera camera(intrinsics);
  const int w = intrinsics.width, h = intrinsics.height;
  const Rigid3d board_from_cam = cam_from_board.Inverse();
  const Eigen::Matrix3d rotation = board_from_cam.RotationMatrix();
  const Eigen::Vector3d origin = board_from_cam.translation;  // camera centre in the board frame
  const double s = options.square_mm;
  const double lo_x = -s * (1.0 + options.border_squares);
  const double hi_x = s * (options.cols + options.border_squares);
  const double lo_y = -s * (1.0 + options.border_squares);
  const double hi_y = s * (options.rows + options.border_squares);

  // Grey level seen along a board-frame direction d from the camera centre.
  auto shade = [&](const Eigen::Vector3d& d) {
    if (std::abs(d.z()) < 1e-12) return options.background_dn;
    const double t = -origin.z() / d.z();
    if (t <= 0.0) return options.background_dn;
    const double x = origin.x() + t * d.x(), y = origin.y() + t * d.y();
    if (x < lo_x || x > hi_x || y < lo_y || y > hi_y) return options.background_dn;
    if (x < -s || x >= s * options.cols || y < -s || y >= s * options.rows) return options.white_dn;
    const long a = static_cast<long>(std::floor(x / s)), b = static_cast<long>(std::floor(y / s));
    return ((a + b) % 2 == 0) ? options.black_dn : options.white_dn;
  };

  // Rays (board frame) at the pixel corners (u - 0.5, v - 0.5).
  const int cw = w + 1;
  std::vector<Eigen::Vector3d> corner_dir(static_cast<std::size_t>(cw) * (h + 1));
  std::vector<std::uint8_t> corner_ok(corner_dir.size(), 0);
  for (int v = 0; v <= h; ++v) {
    for (int u = 0; u <= w; ++u) {
      const auto ray = camera.PixelToRay(Eigen::Vector2d(u - 0.5, v - 0.5));
      if (ray) {
        corner_dir[v * cw + u] = rotation * *ray;
        corner_ok[v * cw + u] = 1;
      }
    }
  }

  SimRandom rng(MixSeed(seed, 0x636865636bull));  // "check"
  const int n = options.supersample;
  cv::Mat image(h, w, CV_8U);
  for (int v = 0; v < h; ++v) {
    for (int u = 0; u < w; ++u) {
      const Eigen::Vector2d uv(u, v);
      const auto centre_ray = camera.PixelToRay(uv);
      if (!centre_ray) {
        image.at<std::uint8_t>(v, u) = 0;
        continue;
      }
      const std::size_t c00 = static_cast<std::size_t>(v) * cw + u;
      const std::size_t c10 = c00 + 1, c01 = c00 + cw, c11 = c01 + 1;
      double sum = 0.0;
      if (corner_ok[c00] && corner_ok[c10] && corner_ok[c01] && corner_ok[c11]) {
        for (int sy = 0; sy < n; ++sy) {
          const double fy = (sy + 0.5) / n;
          for (int sx = 0; sx < n; ++sx) {
            const double fx = (sx + 0.5) / n;
            const Eigen::Vector3d d =
                (1.0 - fy) * ((1.0 - fx) * corner_dir[c00] + fx * corner_dir[c10]) +
                fy * ((1.0 - fx) * corner_dir[c01] + fx * corner_dir[c11]);
            sum += shade(d);
          }
        }
        sum /= n * n;
      } else {
        sum = shade(rotation * *centre_ray);
      }
      const double theta = std::atan2(centre_ray->head<2>().norm(), centre_ray->z());
      const double q = (theta / intrinsics.max_theta) * (theta / intrinsics.max_theta);
      double value =
          sum * std::max(0.02, 1.0 + options.vignetting_v2 * q + options.vignetting_v4 * q * q);
      if (options.noise) {
        value += std::sqrt(options.read_noise * options.read_noise +
                           options.shot_gain * std::max(0.0, value)) *
                 rng.Normal();
      }
      image.at<std::uint8_t>(v, u) =
          static_cast<std::uint8_t>(std::clamp(std::lround(value), 0L, 255L));
    }
  }
  return image;
}

std::vector<Rigid3d> CheckerboardPoses(const CheckerboardOptions& board,
                                       const FisheyeIntrinsics& intrinsics,
                                       const CheckerboardPoseOptions& options, std::uint64_t seed) {
  board.Check();
  options.Check();
  const FisheyeCamera camera(intrinsics);
  const std::vector<Eigen::Vector3d> corners = CheckerboardCorners(board);
  const Eigen::Vector3d centre((board.cols - 1) * 0.5 * board.square_mm,
                               (board.rows - 1) * 0.5 * board.square_mm, 0.0);
  const double golden = std::numbers::pi * (3.0 - std::sqrt(5.0));
  SimRandom rng(MixSeed(seed, 0x706f736573ull));  // "poses"
  std::vector<Rigid3d> poses;
  constexpr int kAttempts = 400;
  for (int k = 0; k < options.count; ++k) {
    bool found = false;
    for (int attempt = 0; attempt < kAttempts && !found; ++attempt) {
      // Stratified over the image disc (area-uniform in field angle), shrinking toward the axis
      // when a pose keeps failing.
      const double shrink = 1.0 - 0.7 * attempt / kAttempts;
      const double frac = options.count == 1 ? 0.0 : (k + rng.Uniform(0.2, 0.8)) / options.count;
      const double field = options.max_field_deg * kDegToRad * std::sqrt(frac) * shrink;
      const double azimuth = golden * k + rng.Uniform(-0.3, 0.3);
      const double distance = rng.Uniform(options.min_distance_mm, options.max_distance_mm);
      const Eigen::Vector3d look(std::sin(field) * std::cos(azimuth),
                                 std::sin(field) * std::sin(azimuth), std::cos(field));
      // Board +z along the line of sight (front faces the camera), then tilt and roll.
      const Eigen::Quaterniond facing =
          Eigen::Quaterniond::FromTwoVectors(Eigen::Vector3d::UnitZ(), look);
      const double tilt = options.max_tilt_deg * kDegToRad * std::sqrt(rng.Uniform());
      const double tilt_dir = rng.Uniform(0.0, 2.0 * std::numbers::pi);
      const Eigen::Vector3d tilt_axis(std::cos(tilt_dir), std::sin(tilt_dir), 0.0);
      const double roll = rng.Uniform(-1.0, 1.0) * options.max_roll_deg * kDegToRad;
      const Eigen::Quaterniond rotation =
          facing * Eigen::Quaterniond(Eigen::AngleAxisd(tilt, tilt_axis)) *
          Eigen::Quaterniond(Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitZ()));
      const Rigid3d cam_from_board(rotation, distance * look - rotation * centre);
      // Every corner well inside the image and the field; corners far enough apart.
      std::vector<Eigen::Vector2d> pixels;
      bool ok = true;
      for (const Eigen::Vector3d& x : corners) {
        const Eigen::Vector3d xc = cam_from_board * x;
        const auto uv = camera.CamToPixel(xc);
        const double theta = std::atan2(xc.head<2>().norm(), xc.z());
        const double theta_margin = options.margin_px / std::max(intrinsics.fx, intrinsics.fy);
        if (!uv || theta > camera.MaxValidTheta() - theta_margin || uv->x() < options.margin_px ||
            uv->y() < options.margin_px || uv->x() > intrinsics.width - 1 - options.margin_px ||
            uv->y() > intrinsics.height - 1 - options.margin_px) {
          ok = false;
          break;
        }
        pixels.push_back(*uv);
      }
      for (int r = 0; ok && r < board.rows; ++r) {
        for (int c = 0; ok && c < board.cols; ++c) {
          const Eigen::Vector2d& p = pixels[r * board.cols + c];
          if (c + 1 < board.cols &&
              (pixels[r * board.cols + c + 1] - p).norm() < options.min_corner_spacing_px)
            ok = false;
          if (r + 1 < board.rows &&
              (pixels[(r + 1) * board.cols + c] - p).norm() < options.min_corner_spacing_px)
            ok = false;
        }
      }
      if (ok) {
        poses.push_back(cam_from_board);
        found = true;
      }
    }
    if (!found) {
      throw std::runtime_error(
          "CheckerboardPoses: no valid pose for board " + std::to_string(k) + " (" +
          std::to_string(board.cols) + "x" + std::to_string(board.rows) + " corners of " +
          std::to_string(board.square_mm) + " mm at " + std::to_string(options.min_distance_mm) +
          "-" + std::to_string(options.max_distance_mm) + " mm)");
    }
  }
  return poses;
}

std::vector<cv::Mat> RenderCheckerboardSet(const CheckerboardOptions& board,
                                           const FisheyeIntrinsics& intrinsics,
                                           const CheckerboardPoseOptions& poses,
                                           std::uint64_t seed) {
  std::vector<cv::Mat> images;
  std::uint64_t k = 0;
  for (const Rigid3d& pose : CheckerboardPoses(board, intrinsics, poses, seed)) {
    images.push_back(RenderCheckerboard(board, pose, intrinsics, seed * 1000 + k++));
  }
  return images;
}

FisheyeIntrinsics PerturbedLens160() {
  FisheyeIntrinsics in = FisheyeIntrinsics::Default160();
  in.fx *= 1.012;
  in.fy = in.fx * 0.997;
  in.cx += 2.4;
  in.cy -= 1.8;
  in.k = {0.011, -0.0035, 0.0, 0.0};
  return in;
}

}  // namespace gs360
