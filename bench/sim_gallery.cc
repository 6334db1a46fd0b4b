// What the simulated GelSight360 camera sees: writes a no-contact reference frame, three presses
// (side wall, near the tip, next to a fin) and their difference images, and one checkerboard
// image, as PNG. Usage: sim_gallery [output_dir]   (default: docs/images)
//
// Difference images: 128 + 3 * (press - reference) per channel, so that grey means no change.
// Zoom images: the press and its difference around the impression, enlarged 4x side by side.

#include <cstdio>
#include <exception>
#include <filesystem>
#include <memory>
#include <numbers>
#include <string>

#include <CLI/CLI.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "sim/checkerboard.h"
#include "sim/ground_truth.h"
#include "sim/rig_model.h"
#include "sim/tactile_camera.h"

namespace {

using gs360::SimGroundTruth;

// Ball centre pressing `depth` mm into the surface at profile parameter t, azimuth phi.
Eigen::Vector3d BallAt(const gs360::SimRig& rig, double t, double phi_deg, double depth) {
  const double phi = phi_deg * std::numbers::pi / 180.0;
  return rig.profile().SurfacePoint(t, phi) +
         (rig.ball_radius() - depth) * rig.profile().SurfaceNormal(t, phi);
}

cv::Mat Difference(const cv::Mat& press, const cv::Mat& reference) {
  cv::Mat a, b;
  press.convertTo(a, CV_16SC3);
  reference.convertTo(b, CV_16SC3);
  cv::Mat d = (a - b) * 3 + cv::Scalar::all(128);
  cv::Mat out;
  d.convertTo(out, CV_8UC3);
  return out;
}

// The press and its difference image around `roi` (padded), 4x, side by side.
cv::Mat Zoom(const cv::Mat& press, const cv::Mat& difference, const cv::Rect& roi) {
  const int pad = 16;
  const cv::Rect box =
      cv::Rect(roi.x - pad, roi.y - pad, roi.width + 2 * pad, roi.height + 2 * pad) &
      cv::Rect(0, 0, press.cols, press.rows);
  cv::Mat a, b, out;
  cv::resize(press(box), a, cv::Size(), 4.0, 4.0, cv::INTER_NEAREST);
  cv::resize(difference(box), b, cv::Size(), 4.0, 4.0, cv::INTER_NEAREST);
  cv::hconcat(a, b, out);
  return out;
}

void Write(const std::filesystem::path& path, const cv::Mat& image) {
  if (!cv::imwrite(path.string(), image)) {
    throw std::runtime_error("cannot write " + path.string());
  }
  std::printf("wrote %s\n", path.string().c_str());
}

}  // namespace

int main(int argc, char** argv) {
  std::string out_dir = "docs/images";
  CLI::App app(
      "sim_gallery: writes what the simulated GelSight360 camera sees (reference, presses, "
      "difference and zoom images, a checkerboard) as PNG");
  app.option_defaults()->always_capture_default();
  app.add_option("output_dir", out_dir, "directory for the PNG images (created if missing)");
  CLI11_PARSE(app, argc, argv);
  try {
    const std::filesystem::path out = out_dir;
    std::filesystem::create_directories(out);
    const gs360::SimRigOptions options;  // the default rig (sim/rig_model.h)
    auto rig = std::make_shared<gs360::SimRig>(options);
    gs360::TactileCamera camera(rig);
    std::printf("rig: %s, background %.2f s\n", rig->Describe().c_str(),
                camera.stats().background_seconds);

    const cv::Mat reference = camera.RenderReference(0);
    Write(out / "sim_reference.png", reference);
    struct Press {
      const char* name;
      double t, phi_deg, depth;
    };
    // Side wall between the fins; near the tip, off the fin cross; right next to the xz fin,
    // so that the fin cuts the impression (the paper's Fig. 8A).
    const Press presses[] = {
        {"side", 0.30, 45.0, 1.0}, {"tip", 0.80, 45.0, 1.0}, {"fin", 0.22, 4.0, 1.0}};
    for (const Press& p : presses) {
      const Eigen::Vector3d ball = BallAt(*rig, p.t, p.phi_deg, p.depth);
      const cv::Mat image = camera.RenderAtBall(ball, 0);
      const gs360::FrameTruth& truth = SimGroundTruth::LastFrame(camera);
      std::printf(
          "press %-5s ball (%.2f, %.2f, %.2f) mm, depth %.2f mm, ROI %dx%d at (%d, %d), "
          "%d contact px, %.2f ms\n",
          p.name, ball.x(), ball.y(), ball.z(), truth.max_depth_mm, truth.roi.width,
          truth.roi.height, truth.roi.x, truth.roi.y,
          truth.contact_mask.empty() ? 0 : cv::countNonZero(truth.contact_mask),
          camera.stats().last_frame_seconds * 1e3);
      const cv::Mat difference = Difference(image, reference);
      Write(out / (std::string("sim_press_") + p.name + ".png"), image);
      Write(out / (std::string("sim_diff_") + p.name + ".png"), difference);
      Write(out / (std::string("sim_zoom_") + p.name + ".png"), Zoom(image, difference, truth.roi));
    }

    gs360::CheckerboardOptions board;
    const auto& intrinsics = SimGroundTruth::TrueIntrinsics(*rig);
    const auto poses = gs360::CheckerboardPoses(board, intrinsics, {}, 7);
    Write(out / "sim_checkerboard.png",
          gs360::RenderCheckerboard(board, poses[poses.size() * 3 / 4], intrinsics, 7));
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "sim_gallery: %s\n", e.what());
    return 1;
  }
}
