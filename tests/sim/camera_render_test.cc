// The simulated tactile camera's images: where impressions appear, how each colour responds to the
// surface slope, fin occlusion, determinism, capture-time coupling with the machine position,
// noise and drift statistics, the geometric truth, every shape.
#include <catch2/catch.hpp>

#include <Eigen/Dense>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <memory>
#include <vector>

#include <opencv2/core.hpp>

#include "camera_test_util.h"
#include "geometry/mesh.h"
#include "geometry/shapes.h"
#include "sim/ground_truth.h"
#include "sim/rig_model.h"
#include "sim/tactile_camera.h"

using namespace gs360;
using namespace gs360::camera_test;

namespace {

std::shared_ptr<const SimRig> DefaultRig() {
  static const SimRigOptions options;
  static const std::shared_ptr<const SimRig> rig = std::make_shared<const SimRig>(options);
  return rig;
}

TactileCamera& NoisyCamera() {
  static TactileCamera camera(DefaultRig());
  return camera;
}

TactileCameraOptions NoiseFree() {
  TactileCameraOptions options;
  options.sensor.noise = false;
  return options;
}

TactileCamera& CleanCamera() {
  static TactileCamera camera(DefaultRig(), NoiseFree());
  return camera;
}

Eigen::Vector3d Vec(const cv::Vec3d& v) {
  return {v[0], v[1], v[2]};
}

// Least-squares fit of each channel's change (press - reference, noise-free) at the deformed
// pixels against the tilt of the inward normal along the azimuthal (toward increasing phi) and
// the upward (toward the tip) tangent directions at the contact point:
//   dC = a + b_az * (tilt . e_az) + b_up * (tilt . e_up).
struct SlopeFit {
  Eigen::Vector3d b_az = Eigen::Vector3d::Zero();  // R, G, B
  Eigen::Vector3d b_up = Eigen::Vector3d::Zero();
  int pixels = 0;
};

SlopeFit FitSlopeResponse(TactileCamera& camera, const Eigen::Vector3d& ball) {
  const cv::Mat reference = camera.RenderReference(0);
  const cv::Mat press = camera.RenderAtBall(ball, 0);
  const FrameTruth& truth = SimGroundTruth::LastFrame(camera);
  const cv::Mat normals0 = SimGroundTruth::BackgroundNormals(camera);
  const Eigen::Vector3d n0c = truth.contact_normal_sensor;
  const double phi = std::atan2(n0c.y(), n0c.x());
  const Eigen::Vector3d e_az(-std::sin(phi), std::cos(phi), 0.0);
  const Eigen::Vector3d e_up = n0c.cross(e_az).normalized();
  std::vector<Eigen::Vector3d> rows;
  std::vector<Eigen::Vector3d> changes;
  for (int ry = 0; ry < truth.roi.height; ++ry) {
    for (int rx = 0; rx < truth.roi.width; ++rx) {
      if (truth.deformed_mask.at<std::uint8_t>(ry, rx) == 0) continue;
      const int x = truth.roi.x + rx, y = truth.roi.y + ry;
      const Eigen::Vector3d n_def = Vec(truth.normals.at<cv::Vec3d>(ry, rx));
      const Eigen::Vector3d n0 = Vec(normals0.at<cv::Vec3d>(y, x));
      if (!n_def.allFinite() || !n0.allFinite()) continue;
      const Eigen::Vector3d tilt = n0 - n_def;  // change of the inward normal
      rows.emplace_back(1.0, tilt.dot(e_az), tilt.dot(e_up));
      const cv::Vec3b p = press.at<cv::Vec3b>(y, x), r = reference.at<cv::Vec3b>(y, x);
      changes.emplace_back(double(p[2]) - r[2], double(p[1]) - r[1], double(p[0]) - r[0]);
    }
  }
  SlopeFit fit;
  fit.pixels = static_cast<int>(rows.size());
  if (rows.size() < 10) return fit;
  Eigen::MatrixXd A(rows.size(), 3), B(rows.size(), 3);
  for (std::size_t i = 0; i < rows.size(); ++i) {
    A.row(i) = rows[i].transpose();
    B.row(i) = changes[i].transpose();
  }
  const Eigen::MatrixXd coef = A.colPivHouseholderQr().solve(B);  // 3 x 3: [a; b_az; b_up]
  fit.b_az = coef.row(1).transpose();
  fit.b_up = coef.row(2).transpose();
  return fit;
}

}  // namespace

TEST_CASE("tactile camera: the impression is where the true camera projects the contact point",
          "[sim][camera]") {
  TactileCamera& camera = NoisyCamera();
  const SimRig& rig = *DefaultRig();
  const cv::Mat reference = camera.RenderReference(5);
  struct Press {
    double t, phi;
  };
  for (const Press p :
       {Press{0.30, 45.0}, Press{0.50, 135.0}, Press{0.15, 225.0}, Press{0.70, 300.0}}) {
    CAPTURE(p.t, p.phi);
    const cv::Mat press = camera.RenderAtBall(BallAt(rig, p.t, p.phi, 1.0), 5);
    const FrameTruth& truth = SimGroundTruth::LastFrame(camera);
    // The truth's contact point is the surface point the ball was aimed at.
    CHECK((truth.contact_point_sensor - rig.profile().SurfacePoint(p.t, Deg(p.phi))).norm() < 0.03);
    CHECK(truth.max_depth_mm == Approx(1.0).margin(0.01));
    const auto expected = SimGroundTruth::ProjectTrue(rig, truth.contact_point_sensor);
    REQUIRE(expected);
    const auto blob = DifferenceBlob(press, reference, 10);
    REQUIRE(blob);
    CHECK(blob->pixels > 80);
    CAPTURE(blob->u, blob->v, expected->x(), expected->y());
    CHECK((Eigen::Vector2d(blob->u, blob->v) - *expected).norm() < 2.0);
  }
}

TEST_CASE("tactile camera: the nominal camera misplaces impressions (true pose differs)",
          "[sim][camera]") {
  // What the pipeline starts from is off by the perturbation: the same surface point lands
  // several pixels away through the nominal camera, so pose estimation has work to do.
  const SimRig& rig = *DefaultRig();
  const FisheyeCamera nominal(rig.nominal_intrinsics());
  double worst = 0.0;
  for (const double phi : {0.0, 90.0, 180.0, 270.0}) {
    const Eigen::Vector3d x = rig.profile().SurfacePoint(0.3, Deg(phi));
    const auto truth = SimGroundTruth::ProjectTrue(rig, x);
    const auto guess = nominal.CamToPixel(rig.nominal_cam_from_sensor() * x);
    REQUIRE(truth);
    REQUIRE(guess);
    worst = std::max(worst, (*truth - *guess).norm());
  }
  CHECK(worst > 3.0);
  CHECK(worst < 40.0);
}

TEST_CASE("tactile camera: each colour responds to the slope toward its own LEDs",
          "[sim][camera]") {
  TactileCamera& camera = CleanCamera();
  const SimRig& rig = *DefaultRig();
  // Red LEDs sit on the xz board (phi = 0 and 180 deg), green on the yz board (90, 270), blue on
  // the base ring: the side of the bump that faces a board gets more of its colour, and the side
  // facing down gets more blue. Sign of d(colour)/d(tilt toward increasing phi):
  struct Case {
    double phi;
    double red_sign;    // +1: the xz board lies toward increasing phi
    double green_sign;  // +1: the yz board lies toward increasing phi
  };
  for (const Case c : {Case{60.0, -1.0, +1.0}, Case{120.0, +1.0, -1.0}, Case{300.0, +1.0, -1.0},
                       Case{240.0, -1.0, +1.0}}) {
    CAPTURE(c.phi);
    const SlopeFit fit = FitSlopeResponse(camera, BallAt(rig, 0.32, c.phi, 1.0));
    REQUIRE(fit.pixels > 200);
    CAPTURE(fit.b_az.transpose(), fit.b_up.transpose());
    // Tilts are up to ~0.5 (30 deg): a coefficient of 20 DN per unit tilt is a 10 DN change.
    CHECK(c.red_sign * fit.b_az[0] > 20.0);
    CHECK(c.green_sign * fit.b_az[1] > 20.0);
    CHECK(fit.b_up[2] < -20.0);  // tilting down (toward the blue ring) brightens blue
  }
}

TEST_CASE("tactile camera: the fins hide ~10% of the image circle, grey, unchanged by a press",
          "[sim][camera]") {
  TactileCamera& camera = NoisyCamera();
  const SimRig& rig = *DefaultRig();
  const cv::Mat fins = SimGroundTruth::FinMask(camera);
  const cv::Mat circle = SimGroundTruth::ImageCircleMask(camera);
  const double fraction = double(cv::countNonZero(fins)) / cv::countNonZero(circle);
  CHECK(fraction > 0.06);
  CHECK(fraction < 0.15);

  const cv::Mat reference = camera.RenderReference(3);
  // Grey: equal channels up to noise, mid-level.
  const cv::Scalar mean = cv::mean(reference, fins);
  CHECK(mean[0] > 40.0);
  CHECK(mean[0] < 140.0);
  CHECK(std::abs(mean[0] - mean[1]) < 4.0);  // the LED drift tints it by up to ~2%
  CHECK(std::abs(mean[1] - mean[2]) < 4.0);

  // A press right behind the xz fin (phi = 2 deg): the fin crosses the impression, whose two
  // halves show on both sides of it; the fin pixels do not change at all (same noise draw).
  const cv::Mat press = camera.RenderAtBall(BallAt(rig, 0.22, 2.0, 1.0), 3);
  const FrameTruth& truth = SimGroundTruth::LastFrame(camera);
  const auto centre = SimGroundTruth::ProjectTrue(rig, truth.contact_point_sensor);
  REQUIRE(centre);
  CHECK(fins.at<std::uint8_t>(cvRound(centre->y()), cvRound(centre->x())) == 255);
  const cv::Mat deformed = SimGroundTruth::DeformedMask(camera);
  int above = 0, below = 0;
  for (int y = 0; y < deformed.rows; ++y) {
    for (int x = 0; x < deformed.cols; ++x) {
      if (deformed.at<std::uint8_t>(y, x) == 0) continue;
      if (y < centre->y() - 3) ++above;
      if (y > centre->y() + 3) ++below;
    }
  }
  CHECK(above > 30);
  CHECK(below > 30);
  cv::Mat changed = AbsDiffSum(press, reference) > 0;
  CHECK(cv::countNonZero(changed) > 300);
  cv::Mat changed_fins;
  cv::bitwise_and(changed, fins, changed_fins);
  CHECK(cv::countNonZero(changed_fins) == 0);
}

TEST_CASE("tactile camera: the same seed and calls give identical images, another seed differs",
          "[sim][camera]") {
  const std::shared_ptr<const SimRig> rig = DefaultRig();
  TactileCamera a(rig), b(rig);
  const Eigen::Vector3d ball = BallAt(*rig, 0.4, 30.0, 0.8);
  const Eigen::Vector3d machine = rig->MachinePositionForBall(ball);
  const auto start = std::chrono::steady_clock::now();
  for (TactileCamera* camera : {&a, &b}) {
    camera->SetRunStart(start);
    camera->SetMachinePositionSource(
        [machine](std::chrono::steady_clock::time_point) { return machine; });
  }
  for (int k = 0; k < 3; ++k) {
    const auto t = start + std::chrono::milliseconds(100 * k);
    const cv::Mat ia = a.Render(t), ib = b.Render(t);
    CHECK(cv::countNonZero(AbsDiffSum(ia, ib)) == 0);
  }
  const cv::Mat once = a.RenderAtBall(ball, 7, 60.0);
  const cv::Mat again = a.RenderAtBall(ball, 7, 60.0);
  CHECK(cv::countNonZero(AbsDiffSum(once, again)) == 0);
  // Another frame index: other noise everywhere.
  const cv::Mat other_frame = a.RenderAtBall(ball, 8, 60.0);
  CHECK(cv::countNonZero(AbsDiffSum(once, other_frame)) > 100000);

  TactileCameraOptions other_seed;
  other_seed.sensor.seed = 2;
  TactileCamera c(rig, other_seed);
  CHECK(cv::countNonZero(AbsDiffSum(once, c.RenderAtBall(ball, 7, 60.0))) > 100000);

  // The background is the same whatever the number of threads that built it.
  TactileCameraOptions one_thread;
  one_thread.threads = 1;
  TactileCamera single(rig, one_thread);
  CHECK(cv::countNonZero(AbsDiffSum(single.RenderAtBall(ball, 7, 60.0), once)) == 0);

  // Another rig seed: another true camera, so the scene itself moves in the image.
  SimRigOptions rig_options;
  rig_options.seed = 2;
  TactileCamera d(std::make_shared<const SimRig>(rig_options), NoiseFree());
  TactileCamera e(rig, NoiseFree());
  CHECK(cv::countNonZero(AbsDiffSum(d.RenderReference(0), e.RenderReference(0)) > 30) > 1000);
}

TEST_CASE("tactile camera: a dwell's frames reuse the patch and equal a fresh render",
          "[sim][camera]") {
  const std::shared_ptr<const SimRig> rig = DefaultRig();
  const Eigen::Vector3d ball = BallAt(*rig, 0.4, 30.0, 0.8);
  const Eigen::Vector3d elsewhere = BallAt(*rig, 0.5, 120.0, 0.6);
  TactileCamera dwell(rig), fresh(rig);
  // The same ball frame after frame (other noise, another drift), then elsewhere and back: each
  // frame is what a camera that renders it first gives, pixel for pixel, truth included.
  const std::vector<std::pair<Eigen::Vector3d, std::uint64_t>> frames = {
      {ball, 3}, {ball, 4}, {ball, 5}, {elsewhere, 6}, {ball, 7}};
  for (const auto& [at, index] : frames) {
    const double run_time = 1800.0 * static_cast<double>(index);
    const cv::Mat reused = dwell.RenderAtBall(at, index, run_time);
    const FrameTruth truth = SimGroundTruth::LastFrame(dwell);
    TactileCamera first(rig);
    const cv::Mat rendered = first.RenderAtBall(at, index, run_time);
    const FrameTruth& expected = SimGroundTruth::LastFrame(first);
    CHECK(cv::countNonZero(AbsDiffSum(reused, rendered)) == 0);
    CHECK(truth.roi == expected.roi);
    CHECK(truth.max_depth_mm == expected.max_depth_mm);
    CHECK(truth.drift_gain.isApprox(expected.drift_gain, 0.0));
    CHECK(cv::countNonZero(truth.contact_mask != expected.contact_mask) == 0);
    cv::Mat rho_diff;
    cv::absdiff(truth.rho, expected.rho, rho_diff);
    rho_diff.convertTo(rho_diff, CV_32F);
    cv::patchNaNs(rho_diff, 0.0);
    CHECK(cv::countNonZero(rho_diff) == 0);
  }
  // Drift moved between the dwell's frames, so reuse did re-apply it.
  CHECK(cv::countNonZero(AbsDiffSum(dwell.RenderAtBall(ball, 5, 0.0),
                                    dwell.RenderAtBall(ball, 5, 3600.0))) > 1000);
}

TEST_CASE("tactile camera: a frame shows the ball where the machine is at the capture time",
          "[sim][camera]") {
  const std::shared_ptr<const SimRig> rig = DefaultRig();
  TactileCamera camera(rig);
  const double t = 0.3, phi = 45.0;
  const Eigen::Vector3d normal = rig->profile().SurfaceNormal(t, Deg(phi));
  const Eigen::Vector3d pressed = BallAt(*rig, t, phi, 1.0);
  const Eigen::Vector3d away = pressed + 1.6 * normal;  // 0.6 mm clear of the surface
  const Eigen::Vector3d m0 = rig->MachinePositionForBall(away);
  const Eigen::Vector3d m1 = rig->MachinePositionForBall(pressed);
  const auto start = std::chrono::steady_clock::now();
  // The tool moves in a straight line from `away` to `pressed` during the first second.
  auto position = [&](std::chrono::steady_clock::time_point when) {
    const double s = std::clamp(std::chrono::duration<double>(when - start).count(), 0.0, 1.0);
    return Eigen::Vector3d(m0 + s * (m1 - m0));
  };
  camera.SetRunStart(start);
  camera.SetMachinePositionSource(position);

  const cv::Mat early = camera.Render(start);  // frame 0: before contact
  const FrameTruth t0 = SimGroundTruth::LastFrame(camera);
  CHECK(t0.max_depth_mm == 0.0);
  CHECK(t0.roi.empty());
  CHECK((t0.ball_center_sensor - away).norm() < 1e-9);
  REQUIRE(t0.machine_position);
  CHECK((*t0.machine_position - m0).norm() < 1e-9);
  CHECK(cv::countNonZero(AbsDiffSum(early, camera.RenderReference(0))) == 0);

  const cv::Mat halfway = camera.Render(start + std::chrono::milliseconds(500));  // frame 1
  const FrameTruth t1 = SimGroundTruth::LastFrame(camera);
  CHECK(t1.max_depth_mm == Approx(0.2).margin(0.01));
  const cv::Mat done = camera.Render(start + std::chrono::milliseconds(1500));  // frame 2
  const FrameTruth t2 = SimGroundTruth::LastFrame(camera);
  CHECK(t2.max_depth_mm == Approx(1.0).margin(0.01));
  CHECK((t2.ball_center_machine - (m1 + rig->tool_offset())).norm() < 1e-9);
  // Same frame, same noise: Render(t) is RenderAtBall(ball(t)) with the frame counter's index.
  CHECK(cv::countNonZero(AbsDiffSum(done, camera.RenderAtBall(pressed, 2, 1.5))) == 0);

  const auto blob_half = DifferenceBlob(halfway, camera.RenderReference(1, 0.5), 10);
  const auto blob_done = DifferenceBlob(done, camera.RenderReference(2, 1.5), 10);
  REQUIRE(blob_half);
  REQUIRE(blob_done);
  CHECK(blob_done->pixels > 2 * blob_half->pixels);
  const auto expected = SimGroundTruth::ProjectTrue(*rig, t2.contact_point_sensor);
  REQUIRE(expected);
  CHECK((Eigen::Vector2d(blob_done->u, blob_done->v) - *expected).norm() < 2.0);
}

TEST_CASE("tactile camera: shot and read noise follow the model", "[sim][camera]") {
  TactileCamera& camera = NoisyCamera();
  const SensorModelOptions& sensor = camera.options().sensor;
  const cv::Mat a = camera.RenderReference(10), b = camera.RenderReference(11);
  const cv::Mat signal = SimGroundTruth::BackgroundSignal(camera);  // R, G, B
  const cv::Mat gel = SimGroundTruth::ImageCircleMask(camera) & ~SimGroundTruth::FinMask(camera);
  const Eigen::Array3d gain = camera.DriftGain(0.0);
  double normalised = 0.0, mean = 0.0;
  long count = 0;
  for (int y = 0; y < a.rows; ++y) {
    for (int x = 0; x < a.cols; ++x) {
      if (gel.at<std::uint8_t>(y, x) == 0) continue;
      const cv::Vec3f s = signal.at<cv::Vec3f>(y, x);
      for (int c = 0; c < 3; ++c) {
        const double level = s[c] * gain[c];
        if (level < 15.0 || level > 200.0) continue;  // keep clear of clipping
        const double var =
            2.0 * (sensor.read_noise * sensor.read_noise + sensor.shot_gain * level) +
            2.0 / 12.0;  // two frames, plus quantisation
        const double d = double(a.at<cv::Vec3b>(y, x)[2 - c]) - b.at<cv::Vec3b>(y, x)[2 - c];
        normalised += d * d / var;
        mean += d;
        ++count;
      }
    }
  }
  REQUIRE(count > 100000);
  CHECK(normalised / count == Approx(1.0).margin(0.05));
  CHECK(std::abs(mean / count) < 0.05);

  // Noise off: every frame is the same.
  TactileCamera& clean = CleanCamera();
  CHECK(cv::countNonZero(AbsDiffSum(clean.RenderReference(10), clean.RenderReference(11))) == 0);
}

TEST_CASE("tactile camera: LED drift is slow, per channel and a few percent", "[sim][camera]") {
  TactileCamera& camera = CleanCamera();
  const Eigen::Array3d g0 = camera.DriftGain(0.0);
  double largest_change = 0.0;
  for (double hours = 0.0; hours <= 12.0; hours += 0.25) {
    const Eigen::Array3d g = camera.DriftGain(hours * 3600.0);
    CHECK((g - 1.0).abs().maxCoeff() < 0.02);
    largest_change = std::max(largest_change, (g - g0).abs().maxCoeff());
    // Slow: under 0.05% per minute.
    CHECK((camera.DriftGain(hours * 3600.0 + 60.0) - g).abs().maxCoeff() < 5e-4);
  }
  CHECK(largest_change > 0.01);
  // Channels drift independently.
  const Eigen::Array3d g3 = camera.DriftGain(3.0 * 3600.0);
  CHECK(std::abs((g3[0] - g0[0]) - (g3[2] - g0[2])) > 1e-3);

  // The image follows the gains.
  const cv::Mat start = camera.RenderReference(0, 0.0),
                later = camera.RenderReference(0, 3.0 * 3600.0);
  const cv::Mat gel = SimGroundTruth::ImageCircleMask(camera) & ~SimGroundTruth::FinMask(camera);
  const cv::Scalar m0 = cv::mean(start, gel), m1 = cv::mean(later, gel);
  for (int c = 0; c < 3; ++c) {
    CAPTURE(c);
    CHECK(m1[2 - c] / m0[2 - c] == Approx(g3[c] / g0[c]).epsilon(0.003));
  }
}

TEST_CASE("tactile camera: contact pixels see the ball's surface, and a bump hides the wall",
          "[sim][camera]") {
  TactileCamera& camera = CleanCamera();
  const SimRig& rig = *DefaultRig();
  const FisheyeCamera true_camera = SimGroundTruth::TrueCamera(rig);
  const Rigid3d sensor_from_cam = SimGroundTruth::TrueCamFromSensor(rig).Inverse();
  const Eigen::Vector3d ball = BallAt(rig, 0.3, 45.0, 1.0);
  camera.RenderAtBall(ball, 0);
  const FrameTruth truth = SimGroundTruth::LastFrame(camera);
  REQUIRE(cv::countNonZero(truth.contact_mask) > 200);
  int checked = 0;
  for (int ry = 0; ry < truth.roi.height; ++ry) {
    for (int rx = 0; rx < truth.roi.width; ++rx) {
      if (truth.contact_mask.at<std::uint8_t>(ry, rx) == 0) continue;
      const auto ray = true_camera.PixelToRay(Eigen::Vector2d(truth.roi.x + rx, truth.roi.y + ry));
      REQUIRE(ray);
      const Eigen::Vector3d o = sensor_from_cam.translation;
      const Eigen::Vector3d d = sensor_from_cam.RotateDirection(*ray);
      // Entry of the ray into the ball: what the calibration pipeline's render computes.
      const double b = d.dot(o - ball);
      const double disc =
          b * b - ((o - ball).squaredNorm() - rig.ball_radius() * rig.ball_radius());
      REQUIRE(disc >= 0.0);
      const double entry = -b - std::sqrt(disc);
      // Within 10 um (the soft edge leaves the gel a few um off the ball at the contact rim).
      CHECK(truth.rho.at<double>(ry, rx) == Approx(entry).margin(0.01));
      const Eigen::Vector3d n = Vec(truth.normals.at<cv::Vec3d>(ry, rx));
      const Eigen::Vector3d p = Vec(truth.points.at<cv::Vec3d>(ry, rx));
      CHECK(n.dot((ball - p).normalized()) > std::cos(Deg(3.0)));
      ++checked;
    }
  }
  CHECK(checked > 200);
  // The elastic edge: the deformed region is larger than the contact region.
  CHECK(cv::countNonZero(truth.deformed_mask) > cv::countNonZero(truth.contact_mask) * 1.1);

  // Low on the wall the camera sees the indentation at a grazing angle: the bump moves toward
  // the camera and hides wall that the reference frame showed farther away.
  camera.RenderAtBall(BallAt(rig, 0.06, 45.0, 1.0), 0);
  const FrameTruth low = SimGroundTruth::LastFrame(camera);
  const cv::Mat rho0 = SimGroundTruth::BackgroundRho(camera);
  int hidden = 0;
  for (int ry = 0; ry < low.roi.height; ++ry) {
    for (int rx = 0; rx < low.roi.width; ++rx) {
      const double rho = low.rho.at<double>(ry, rx);
      const double before = rho0.at<double>(low.roi.y + ry, low.roi.x + rx);
      if (std::isfinite(rho) && std::isfinite(before) && before - rho > 0.5) ++hidden;
    }
  }
  CHECK(hidden > 20);
}

TEST_CASE("tactile camera: a 1 mm press does not saturate", "[sim][camera]") {
  TactileCamera& camera = NoisyCamera();
  const SimRig& rig = *DefaultRig();
  long saturated = 0, total = 0;
  for (int k = 0; k < 12; ++k) {
    const double t = 0.08 + 0.07 * k, phi = 17.0 + 31.0 * k;
    const cv::Mat press = camera.RenderAtBall(BallAt(rig, t, phi, 1.0), k);
    const FrameTruth& truth = SimGroundTruth::LastFrame(camera);
    if (truth.roi.empty()) continue;
    const cv::Mat roi = press(truth.roi);
    total += roi.total() * 3;
    saturated += cv::countNonZero(roi.reshape(1) == 255);
  }
  REQUIRE(total > 10000);
  CHECK(double(saturated) / total < 0.005);
}

TEST_CASE("tactile camera: every built-in shape and a loaded mesh render", "[sim][camera]") {
  double cone_fraction = 0.0;
  for (const char* name : {"cylinder", "cone", "spline"}) {
    CAPTURE(name);
    SimRigOptions options;
    options.rig.shape.shape = ParseSensorShape(name);
    const auto rig = std::make_shared<const SimRig>(options);
    TactileCamera camera(rig);
    const cv::Mat fins = SimGroundTruth::FinMask(camera);
    const cv::Mat circle = SimGroundTruth::ImageCircleMask(camera);
    const double fraction = double(cv::countNonZero(fins)) / cv::countNonZero(circle);
    if (std::string(name) == "cone") cone_fraction = fraction;
    CHECK(fraction > 0.04);
    CHECK(fraction < 0.2);
    // Nearly every ray in the image circle meets the gel or a fin.
    CHECK(cv::countNonZero(SimGroundTruth::BackgroundRho(camera) ==
                           SimGroundTruth::BackgroundRho(camera)) +
              cv::countNonZero(fins) >
          0.97 * cv::countNonZero(circle));
    const cv::Mat reference = camera.RenderReference(1);
    const cv::Mat press = camera.RenderAtBall(BallAt(*rig, 0.35, 45.0, 1.0), 1);
    const auto blob = DifferenceBlob(press, reference, 10);
    REQUIRE(blob);
    const auto expected =
        SimGroundTruth::ProjectTrue(*rig, SimGroundTruth::LastFrame(camera).contact_point_sensor);
    REQUIRE(expected);
    CHECK((Eigen::Vector2d(blob->u, blob->v) - *expected).norm() < 2.5);
  }

  // The cone as a mesh file: fins from the fitted profile, same picture as the built-in cone.
  SensorShapeOptions cone;
  cone.shape = SensorShape::kCone;
  const std::filesystem::path path =
      std::filesystem::path(GS360_BINARY_DIR) / "sim_camera_test_cone.stl";
  WriteMesh(path, MakeSensorMesh(cone));
  SimRigOptions options;
  options.rig.mesh_path = path.string();
  const auto rig = std::make_shared<const SimRig>(options);
  TactileCamera camera(rig);
  const double fraction = double(cv::countNonZero(SimGroundTruth::FinMask(camera))) /
                          cv::countNonZero(SimGroundTruth::ImageCircleMask(camera));
  CHECK(fraction == Approx(cone_fraction).margin(0.02));
  const cv::Mat reference = camera.RenderReference(1);
  const Eigen::Vector3d ball = MakeConeProfile(cone.cone)->SurfacePoint(0.35, Deg(45.0)) +
                               MakeConeProfile(cone.cone)->SurfaceNormal(0.35, Deg(45.0));
  const cv::Mat press = camera.RenderAtBall(ball, 1);
  const FrameTruth& truth = SimGroundTruth::LastFrame(camera);
  CHECK(truth.max_depth_mm == Approx(1.0).margin(0.02));
  const auto blob = DifferenceBlob(press, reference, 10);
  REQUIRE(blob);
  CHECK(blob->pixels > 50);
  std::filesystem::remove(path);
}

TEST_CASE("tactile camera: the rigid render is the pipeline's sharp imprint", "[sim][camera]") {
  TactileCamera& camera = CleanCamera();
  const SimRig& rig = *DefaultRig();
  const Eigen::Vector3d ball = BallAt(rig, 0.3, 135.0, 0.8);
  const cv::Mat soft = camera.RenderAtBall(ball, 0);
  const FrameTruth soft_truth = SimGroundTruth::LastFrame(camera);
  const cv::Mat rigid = SimGroundTruth::RenderRigidAtBall(camera, ball, 0);
  const FrameTruth rigid_truth = SimGroundTruth::LastFrame(camera);
  CHECK_FALSE(soft_truth.rigid);
  CHECK(rigid_truth.rigid);
  // Rigid: the gel moves only where the ball is, so every deformed pixel is a contact pixel.
  const int rigid_contact = cv::countNonZero(rigid_truth.contact_mask);
  const int rigid_deformed = cv::countNonZero(rigid_truth.deformed_mask);
  CHECK(rigid_contact > 200);
  CHECK(rigid_deformed == Approx(rigid_contact).epsilon(0.05));
  CHECK(cv::countNonZero(soft_truth.deformed_mask) > 1.05 * rigid_deformed);  // slightly larger
  CHECK(rigid_truth.max_depth_mm == Approx(soft_truth.max_depth_mm).margin(1e-9));
  // The two images differ around the imprint's edge.
  CHECK(cv::countNonZero(AbsDiffSum(soft, rigid) > 10) > 50);
}
