#include "calib/intrinsics.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <string>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

#include "base/field_error.h"
#include "geometry/fisheye_cv.h"

namespace gs360 {
namespace {

// The detected boards do not reach far enough out (CheckCoverage).
class CoverageError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

}  // namespace

namespace {

template <typename T>
[[noreturn]] void ThrowField(const char* field, T value, const char* what) {
  ThrowFieldError(std::string("IntrinsicsOptions.") + field, static_cast<double>(value), what);
}

std::string Fixed(double v, int digits = 3) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.*f", digits, v);
  return buf;
}

// Index of the image OpenCV's CHECK_COND complained about, or -1.
int IllConditionedIndex(const std::string& message) {
  const std::string key = "Ill-conditioned matrix for input array ";
  const auto at = message.find(key);
  if (at == std::string::npos) return -1;
  int index = -1;
  if (std::sscanf(message.c_str() + at + key.size(), "%d", &index) != 1) return -1;
  return index;
}

}  // namespace

std::optional<std::string> ImageFileProblem(std::span<const std::uint8_t> bytes) {
  if (bytes.size() < 16) {
    return "too short to be an image (" + std::to_string(bytes.size()) + " bytes)";
  }
  const auto tail_has = [&](std::span<const std::uint8_t> marker, std::size_t tail) {
    const auto from = bytes.end() - static_cast<std::ptrdiff_t>(std::min(tail, bytes.size()));
    return std::search(from, bytes.end(), marker.begin(), marker.end()) != bytes.end();
  };
  static constexpr std::uint8_t kPng[8] = {0x89, 'P', 'N', 'G', 0x0D, 0x0A, 0x1A, 0x0A};
  static constexpr std::uint8_t kIend[4] = {'I', 'E', 'N', 'D'};
  static constexpr std::uint8_t kJpegEoi[2] = {0xFF, 0xD9};
  if (std::equal(std::begin(kPng), std::end(kPng), bytes.begin())) {
    // The last chunk: length 0, "IEND", its CRC.
    if (!tail_has(kIend, 12)) return std::string("truncated PNG (no IEND chunk at its end)");
  } else if (bytes[0] == 0xFF && bytes[1] == 0xD8) {
    // The end-of-image marker, allowing a few bytes of padding after it.
    if (!tail_has(kJpegEoi, 16)) return std::string("truncated JPEG (no end-of-image marker)");
  }
  return std::nullopt;
}

void IntrinsicsOptions::Check() const {
  if (board_cols < 2) ThrowField("board_cols", board_cols, "must be >= 2");
  if (board_rows < 2) ThrowField("board_rows", board_rows, "must be >= 2");
  if (!(square_mm > 0.0) || !std::isfinite(square_mm)) {
    ThrowField("square_mm", square_mm, "must be finite and > 0");
  }
  if (min_images < 3) ThrowField("min_images", min_images, "must be >= 3");
  if (!(max_rms_px > 0.0)) ThrowField("max_rms_px", max_rms_px, "must be > 0");
  if (!(min_radial_coverage > 0.0 && min_radial_coverage <= 1.0)) {
    ThrowField("min_radial_coverage", min_radial_coverage, "must be in (0, 1]");
  }
  if (subpix_window < 1) ThrowField("subpix_window", subpix_window, "must be >= 1");
  if (max_iterations < 1) ThrowField("max_iterations", max_iterations, "must be >= 1");
  if (!(epsilon > 0.0)) ThrowField("epsilon", epsilon, "must be > 0");
}

namespace {

using Corners = std::vector<cv::Point2d>;

// The board's inner corners (mm, board frame), row by row.
std::vector<cv::Point3d> BoardCorners(const IntrinsicsOptions& options) {
  std::vector<cv::Point3d> board;
  for (int r = 0; r < options.board_rows; ++r) {
    for (int c = 0; c < options.board_cols; ++c) {
      board.emplace_back(c * options.square_mm, r * options.square_mm, 0.0);
    }
  }
  return board;
}

// Finds the board's corners in every image (*detected, per image; result->images' reports).
// Returns the images where the whole board was found.
std::vector<int> DetectBoards(std::span<const cv::Mat> images, const FisheyeIntrinsics& nominal,
                              const IntrinsicsOptions& options, std::size_t corner_count,
                              IntrinsicsResult* result, std::vector<Corners>* detected) {
  const cv::Size pattern(options.board_cols, options.board_rows);
  const cv::Size image_size(nominal.width, nominal.height);
  result->images.resize(images.size());
  std::vector<int> candidates;
  for (std::size_t i = 0; i < images.size(); ++i) {
    IntrinsicsImageReport& report = result->images[i];
    report.index = static_cast<int>(i);
    const cv::Mat& image = images[i];
    if (image.empty()) {
      report.reason = "not a decodable image";
      continue;
    }
    if (image.size() != image_size || (image.type() != CV_8UC1 && image.type() != CV_8UC3)) {
      throw std::invalid_argument("CalibrateIntrinsics: image " + std::to_string(i) + " is " +
                                  std::to_string(image.cols) + "x" + std::to_string(image.rows) +
                                  " type " + std::to_string(image.type()) + ", expected " +
                                  std::to_string(nominal.width) + "x" +
                                  std::to_string(nominal.height) + " CV_8UC1 or CV_8UC3");
    }
    cv::Mat grey;
    if (image.channels() == 3) {
      cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
    } else {
      grey = image;
    }
    std::vector<cv::Point2f> corners;
    const bool found = cv::findChessboardCorners(
        grey, pattern, corners, cv::CALIB_CB_ADAPTIVE_THRESH | cv::CALIB_CB_NORMALIZE_IMAGE);
    if (!found || corners.size() != corner_count) {
      report.reason = "no checkerboard detected";
      continue;
    }
    cv::cornerSubPix(grey, corners, cv::Size(options.subpix_window, options.subpix_window),
                     cv::Size(-1, -1),
                     cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 50, 1e-4));
    report.corners = static_cast<int>(corners.size());
    for (const cv::Point2f& p : corners) (*detected)[i].emplace_back(p.x, p.y);
    candidates.push_back(static_cast<int>(i));
  }
  return candidates;
}

// Coverage: the distortion is only determined where corners were seen. Sets
// result->radial_coverage; throws std::runtime_error below min_radial_coverage.
void CheckCoverage(const FisheyeIntrinsics& nominal, const std::vector<int>& candidates,
                   const std::vector<Corners>& detected, const IntrinsicsOptions& options,
                   IntrinsicsResult* result) {
  const FisheyeCamera nominal_camera(nominal);
  const double circle_radius = std::min(nominal.fx, nominal.fy) *
                               nominal_camera.ThetaToThetaD(nominal_camera.MaxValidTheta());
  double max_radius = 0.0;
  for (int i : candidates) {
    for (const cv::Point2d& p : detected[i]) {
      max_radius = std::max(max_radius, std::hypot(p.x - nominal.cx, p.y - nominal.cy));
    }
  }
  result->radial_coverage = max_radius / circle_radius;
  if (result->radial_coverage < options.min_radial_coverage) {
    throw CoverageError("CalibrateIntrinsics: the detected boards reach " + Fixed(max_radius, 1) +
                        " px from the principal point, " +
                        Fixed(100.0 * result->radial_coverage, 1) +
                        "% of the image circle's radius (" + Fixed(circle_radius, 1) +
                        " px); need " + Fixed(100.0 * options.min_radial_coverage, 1) +
                        "%: take images with the board near the rim of the field");
  }
}

struct FisheyeFit {
  cv::Matx33d K;
  cv::Vec4d D;
  std::vector<cv::Vec3d> rvecs, tvecs;  // per used image
  std::vector<int> used;                // input indices
};

// cv::fisheye::calibrate over the candidates from the nominal model; an image OpenCV finds
// ill-conditioned (CALIB_CHECK_COND) is left out, its reason recorded, and the rest calibrated
// again.
FisheyeFit FitFisheye(const std::vector<int>& candidates, const std::vector<Corners>& detected,
                      const std::vector<cv::Point3d>& board, const FisheyeIntrinsics& nominal,
                      const IntrinsicsOptions& options, IntrinsicsResult* result) {
  const cv::Size image_size(nominal.width, nominal.height);
  const int flags = cv::fisheye::CALIB_RECOMPUTE_EXTRINSIC | cv::fisheye::CALIB_CHECK_COND |
                    cv::fisheye::CALIB_FIX_SKEW | cv::fisheye::CALIB_USE_INTRINSIC_GUESS;
  const cv::TermCriteria criteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS,
                                  options.max_iterations, options.epsilon);
  FisheyeFit fit;
  fit.used = candidates;
  for (;;) {
    if (static_cast<int>(fit.used.size()) < options.min_images) {
      throw std::runtime_error(
          "CalibrateIntrinsics: after rejecting ill-conditioned images (OpenCV CALIB_CHECK_COND) "
          "only " +
          std::to_string(fit.used.size()) + " images remain, need at least " +
          std::to_string(options.min_images) + ": vary the board's distance and tilt more");
    }
    std::vector<std::vector<cv::Point3d>> object_points(fit.used.size(), board);
    std::vector<Corners> image_points;
    for (int i : fit.used) image_points.push_back(detected[i]);
    fit.K = ToCvK(nominal);
    fit.K(0, 1) = 0.0;
    fit.D = ToCvD(nominal);
    fit.rvecs.clear();
    fit.tvecs.clear();
    try {
      cv::fisheye::calibrate(object_points, image_points, image_size, fit.K, fit.D, fit.rvecs,
                             fit.tvecs, flags, criteria);
      return fit;
    } catch (const cv::Exception& e) {
      const int bad = IllConditionedIndex(e.what());
      if (bad < 0 || bad >= static_cast<int>(fit.used.size())) {
        // OpenCV's message is an assertion in its own code ("fabs(norm_u1) > 0"): say what it
        // means instead, and keep it for the log only.
        throw std::runtime_error(
            "CalibrateIntrinsics: cv::fisheye::calibrate found no solution from the nominal lens "
            "(fx " +
            Fixed(nominal.fx, 1) + ", fy " + Fixed(nominal.fy, 1) +
            " px): its initial estimate of a board's pose failed (OpenCV: " + e.err + ")");
      }
      result->images[fit.used[bad]].reason = "ill-conditioned (OpenCV CALIB_CHECK_COND)";
      fit.used.erase(fit.used.begin() + bad);
    }
  }
}

// Per-image and overall reprojection errors under the fit (`skew`: the result's); marks the used
// images and records their board poses.
void AddReprojectionErrors(const FisheyeFit& fit, const std::vector<cv::Point3d>& board,
                           const std::vector<Corners>& detected, double skew,
                           IntrinsicsResult* result) {
  double sum_sq = 0.0;
  std::size_t count = 0;
  for (std::size_t j = 0; j < fit.used.size(); ++j) {
    Corners projected;
    cv::fisheye::projectPoints(board, projected, fit.rvecs[j], fit.tvecs[j], fit.K, fit.D, skew);
    double image_sq = 0.0;
    const auto& seen = detected[fit.used[j]];
    for (std::size_t k = 0; k < board.size(); ++k) {
      const cv::Point2d e = projected[k] - seen[k];
      image_sq += e.dot(e);
    }
    IntrinsicsImageReport& report = result->images[fit.used[j]];
    report.used = true;
    report.rms_px = std::sqrt(image_sq / static_cast<double>(board.size()));
    sum_sq += image_sq;
    count += board.size();
    cv::Matx33d R;
    cv::Rodrigues(fit.rvecs[j], R);
    Eigen::Matrix<double, 3, 4> m;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) m(r, c) = R(r, c);
      m(r, 3) = fit.tvecs[j][r];
    }
    result->cam_from_board.push_back(Rigid3d::FromMatrix(m));
  }
  result->rms_px = std::sqrt(sum_sq / static_cast<double>(count));
}

}  // namespace

namespace {

// Coverage, fit and checks from `nominal` on the detected boards; `result` holds the detection.
IntrinsicsResult Solve(const std::vector<int>& candidates, const std::vector<Corners>& detected,
                       const std::vector<cv::Point3d>& board, const FisheyeIntrinsics& nominal,
                       const IntrinsicsOptions& options, IntrinsicsResult result) {
  CheckCoverage(nominal, candidates, detected, options, &result);
  const FisheyeFit fit = FitFisheye(candidates, detected, board, nominal, options, &result);
  FisheyeIntrinsics intrinsics;
  try {
    intrinsics = FromCv(fit.K, fit.D, nominal.width, nominal.height, nominal.max_theta);
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error(std::string("CalibrateIntrinsics: unusable result: ") + e.what());
  }
  AddReprojectionErrors(fit, board, detected, intrinsics.skew, &result);
  result.used = fit.used;
  for (std::size_t i = 0; i < result.images.size(); ++i) {
    if (!result.images[i].used) result.rejected.push_back(static_cast<int>(i));
  }
  if (!(result.rms_px <= options.max_rms_px)) {
    throw std::runtime_error("CalibrateIntrinsics: RMS reprojection error " + Fixed(result.rms_px) +
                             " px over " + std::to_string(fit.used.size()) +
                             " images exceeds max_rms_px = " + Fixed(options.max_rms_px));
  }
  result.intrinsics = intrinsics;
  return result;
}

}  // namespace

IntrinsicsResult CalibrateIntrinsics(std::span<const cv::Mat> images,
                                     const FisheyeIntrinsics& nominal,
                                     const IntrinsicsOptions& options) {
  options.Check();
  nominal.Check();
  const std::vector<cv::Point3d> board = BoardCorners(options);
  IntrinsicsResult detection;
  std::vector<Corners> detected(images.size());
  const std::vector<int> candidates =
      DetectBoards(images, nominal, options, board.size(), &detection, &detected);
  if (static_cast<int>(candidates.size()) < options.min_images) {
    throw std::runtime_error("CalibrateIntrinsics: a " + std::to_string(options.board_cols) + "x" +
                             std::to_string(options.board_rows) + " checkerboard was detected in " +
                             std::to_string(candidates.size()) + " of " +
                             std::to_string(images.size()) + " images, need at least " +
                             std::to_string(options.min_images));
  }
  try {
    return Solve(candidates, detected, board, nominal, options, detection);
  } catch (const std::runtime_error& e) {
    // A nominal focal length far from the lens's misleads the coverage check and OpenCV's
    // initialisation, and their messages then blame the images. If the boards fit from another
    // focal length: within kGuessTolerance of the nominal, the nominal was only a rough guess and
    // the fit is the answer (unless coverage failed: boards only at the centre fit from a shorter
    // guess too, and their coverage message is the true one); farther, that is the problem to
    // report (not a result to use: the nominal lens also seeds the plan and the pose).
    constexpr double kGuessTolerance = 0.3;
    const bool coverage_failed = dynamic_cast<const CoverageError*>(&e) != nullptr;
    for (const double scale : {0.8, 1.25, 0.25, 0.35, 0.5, 0.7, 1.4, 2.0, 2.8, 4.0}) {
      FisheyeIntrinsics guess = nominal;
      guess.fx *= scale;
      guess.fy *= scale;
      std::optional<IntrinsicsResult> r;
      try {
        r = Solve(candidates, detected, board, guess, options, detection);
      } catch (const std::exception&) {
        continue;
      }
      // A fit near the nominal says the nominal was not the problem (boards only at the centre
      // fit from a shorter guess too, and their coverage message is the true one).
      const double off = std::abs(r->intrinsics.fx / nominal.fx - 1.0);
      if (!coverage_failed && off <= kGuessTolerance) return *r;
      if (off < 0.25) continue;
      throw std::runtime_error(
          std::string(e.what()) + ". But the nominal lens looks far from the real one: from " +
          Fixed(scale, 2) + " times its focal length the boards fit with an RMS of " +
          Fixed(r->rms_px) + " px at fx " + Fixed(r->intrinsics.fx, 1) + ", fy " +
          Fixed(r->intrinsics.fy, 1) + " px, where the nominal says fx " + Fixed(nominal.fx, 1) +
          ", fy " + Fixed(nominal.fy, 1) +
          ". Set the rig's nominal camera (fx, fy) near those and calibrate again");
    }
    throw;
  }
}

double MaxRayAngleDifference(const FisheyeIntrinsics& a, const FisheyeIntrinsics& b, int step_px) {
  if (step_px < 1) {
    throw std::invalid_argument("MaxRayAngleDifference: step_px must be >= 1, got " +
                                std::to_string(step_px));
  }
  const FisheyeCamera ca(a), cb(b);
  double worst = 0.0;
  for (int v = 0; v < a.height; v += step_px) {
    for (int u = 0; u < a.width; u += step_px) {
      const Eigen::Vector2d uv(u, v);
      const auto ra = ca.PixelToRay(uv);
      const auto rb = cb.PixelToRay(uv);
      if (!ra || !rb) continue;
      worst = std::max(worst, std::atan2(ra->cross(*rb).norm(), ra->dot(*rb)));
    }
  }
  return worst;
}

}  // namespace gs360
