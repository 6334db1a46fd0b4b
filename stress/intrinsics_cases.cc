// Lens intrinsics at their edges: nominal guesses 20 % off, and the corner refinement window
// measured against a synthetic board's known truth.

#include <algorithm>
#include <cmath>
#include <numbers>
#include <stdexcept>
#include <string>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "calib/intrinsics.h"
#include "sim/checkerboard.h"
#include "stress/stress_cases.h"

namespace gs360::stress {
namespace {

constexpr double kRadToDeg = 180.0 / std::numbers::pi;

// `count` boards through `truth`, blurred by a Gaussian of `blur_px` (a real lens's spot; 0 none).
std::vector<cv::Mat> Boards(const FisheyeIntrinsics& truth, int count, std::uint64_t seed,
                            double blur_px) {
  CheckerboardPoseOptions poses;
  poses.count = count;
  std::vector<cv::Mat> images = RenderCheckerboardSet(CheckerboardOptions{}, truth, poses, seed);
  if (blur_px > 0.0) {
    for (cv::Mat& image : images) cv::GaussianBlur(image, image, cv::Size(), blur_px);
  }
  return images;
}

StressCase NominalOff(double factor) {
  const std::string name =
      Format("nominal focal length %s 20 %%, 20 boards", factor > 1.0 ? "over" : "under");
  return {"intrinsics", name, "fx, fy, cx, cy within 0.5 px of the truth",
          [factor](const StressContext& c, std::string* observed) {
            const FisheyeIntrinsics truth = PerturbedLens160();
            FisheyeIntrinsics nominal = FisheyeIntrinsics::Default160();
            nominal.fx *= factor;
            nominal.fy *= factor;
            const IntrinsicsResult r = CalibrateIntrinsics(Boards(truth, 20, c.seed, 0.0), nominal);
            const FisheyeIntrinsics& got = r.intrinsics;
            const double worst =
                std::max({std::abs(got.fx - truth.fx), std::abs(got.fy - truth.fy),
                          std::abs(got.cx - truth.cx), std::abs(got.cy - truth.cy)});
            *observed = Format(
                "fx %.2f (truth %.2f), fy %.2f, cx %.2f, cy %.2f: %.3f px at worst; "
                "rms %.3f px, %zu of 20 boards used",
                got.fx, truth.fx, got.fy, got.cx, got.cy, worst, r.rms_px, r.used.size());
            return worst <= 0.5;
          }};
}

// cv::cornerSubPix's half window, measured: each window's largest ray-angle error over the field
// against the truth, on boards sharp and blurred by 1 and 2 px (a real lens's spot). The default
// is the window whose worst error over the three is smallest.
StressCase CornerWindow() {
  return {"intrinsics", "corner refinement window 2-8 on boards blurred 0, 1 and 2 px",
          "the default window has the smallest worst-case ray error",
          [](const StressContext& c, std::string* observed) {
            const FisheyeIntrinsics truth = PerturbedLens160();
            const std::vector<int> windows = {2, 3, 4, 5, 8};
            std::vector<double> worst(windows.size(), 0.0);
            for (double blur : {0.0, 1.0, 2.0}) {
              const std::vector<cv::Mat> images = Boards(truth, 20, c.seed, blur);
              *observed += Format("%sblur %.0f px:", observed->empty() ? "" : "; ", blur);
              for (std::size_t k = 0; k < windows.size(); ++k) {
                IntrinsicsOptions options;
                options.subpix_window = windows[k];
                double err = 90.0;  // a failed calibration counts as the worst
                try {
                  const IntrinsicsResult r =
                      CalibrateIntrinsics(images, FisheyeIntrinsics::Default160(), options);
                  err = MaxRayAngleDifference(r.intrinsics, truth, 4) * kRadToDeg;
                  *observed += Format(" %d: %.3f deg", windows[k], err);
                } catch (const std::runtime_error&) {
                  *observed += Format(" %d: fails", windows[k]);
                }
                worst[k] = std::max(worst[k], err);
              }
            }
            const std::size_t best = static_cast<std::size_t>(
                std::min_element(worst.begin(), worst.end()) - worst.begin());
            *observed += Format("; smallest worst case: window %d", windows[best]);
            return windows[best] == IntrinsicsOptions{}.subpix_window;
          }};
}

}  // namespace

std::vector<StressCase> IntrinsicsCases() {
  return {NominalOff(1.2), NominalOff(0.8), CornerWindow()};
}

}  // namespace gs360::stress
