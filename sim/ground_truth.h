#pragma once
// GROUND TRUTH of the simulated rig -- for tests, the demo and benchmarks ONLY.
//
// Production code (capture, calib, recon, daemon, cli's run path) never includes this header: it
// is given the nominal camera (SimRig::nominal_*()) and the images, as with a real sensor. This
// header exposes what a real rig would hide: the true fisheye intrinsics and camera pose, the
// true ball position of each rendered frame, the true contact and deformation masks, the true
// distance along each pixel's ray to the deformed surface, the true deformed points and normals,
// and a render of the same frame with the rigid imprint the calibration pipeline assumes.
//
// Frames and units as in sim/rig_model.h (sensor frame, mm). Full-image maps are
// camera.width() x camera.height(); ROI maps are FrameTruth::roi.size() and cover the pixels the
// frame re-rendered (outside the ROI the frame shows the undeformed background).

#include <Eigen/Core>
#include <chrono>
#include <cstdint>
#include <optional>

#include <opencv2/core.hpp>

#include "geometry/fisheye.h"
#include "geometry/rigid3.h"
#include "sim/gel_deformation.h"
#include "sim/rig_model.h"
#include "sim/tactile_camera.h"

namespace gs360 {

// Truth of one rendered frame.
struct FrameTruth {
  std::uint64_t frame_index = 0;
  double run_time_s = 0.0;                             // sets the LED drift
  Eigen::Array3d drift_gain = Eigen::Array3d::Ones();  // (R, G, B) LED gains of this frame
  // Render(t) only: the capture time and the tool's true machine position at that time.
  std::optional<std::chrono::steady_clock::time_point> capture_time;
  std::optional<Eigen::Vector3d> machine_position;
  bool has_ball = false;
  Eigen::Vector3d ball_center_sensor = Eigen::Vector3d::Zero();
  Eigen::Vector3d ball_center_machine = Eigen::Vector3d::Zero();
  bool rigid = false;  // rendered with GelDeformationOptions::Rigid()
  // Largest rigid penetration of the ball into the undeformed gel (mm; 0 = no contact), and the
  // undeformed surface point closest to the ball centre with its outward normal (the "contact
  // point").
  double max_depth_mm = 0.0;
  double max_indentation_mm = 0.0;  // largest displacement delta (mm)
  Eigen::Vector3d contact_point_sensor = Eigen::Vector3d::Zero();
  Eigen::Vector3d contact_normal_sensor = Eigen::Vector3d::Zero();
  int patch_triangles = 0;

  // Re-rendered pixels (empty when the ball deforms nothing). ROI-sized maps:
  cv::Rect roi;
  cv::Mat contact_mask;   // CV_8U, 255 where the visible gel touches the ball (penetration >= w)
  cv::Mat deformed_mask;  // CV_8U, 255 where the visible gel moved inward (delta > 1e-4 mm)
  cv::Mat rho;            // CV_64F, mm along the pixel's unit ray from the true camera centre to
                          // the visible (deformed) gel; NaN where a fin or nothing is seen
  cv::Mat indentation;  // CV_64F, delta (mm, + inward; bulge < 0) at the visible point; NaN as rho
  cv::Mat points;       // CV_64FC3, visible gel point (sensor frame); NaN as rho
  cv::Mat normals;      // CV_64FC3, outward unit normal of the deformed gel there; NaN as rho
};

class SimGroundTruth {
 public:
  // The camera the simulator renders with.
  static const FisheyeIntrinsics& TrueIntrinsics(const SimRig& rig) { return rig.true_intrinsics_; }
  static const Rigid3d& TrueCamFromSensor(const SimRig& rig) { return rig.true_cam_from_sensor_; }
  static FisheyeCamera TrueCamera(const SimRig& rig) { return FisheyeCamera(rig.true_intrinsics_); }
  // Pixel of a sensor-frame point through the true camera (nullopt outside the valid field).
  static std::optional<Eigen::Vector2d> ProjectTrue(const SimRig& rig, const Eigen::Vector3d& x);

  // Truth of the camera's last Render* call. Throws std::logic_error before the first frame.
  static const FrameTruth& LastFrame(const TactileCamera& camera);

  // Full-image maps of the last frame (the ROI pasted over the undeformed background).
  static cv::Mat ContactMask(const TactileCamera& camera);   // CV_8U
  static cv::Mat DeformedMask(const TactileCamera& camera);  // CV_8U
  static cv::Mat Rho(const TactileCamera& camera);           // CV_64F, NaN without gel

  // Static background (no contact), full image:
  static cv::Mat BackgroundRho(const TactileCamera& camera);      // CV_64F, NaN without gel
  static cv::Mat BackgroundNormals(const TactileCamera& camera);  // CV_64FC3 n0, NaN without gel
  static cv::Mat FinMask(const TactileCamera& camera);            // CV_8U, 255 = a fin is seen
  static cv::Mat ImageCircleMask(const TactileCamera& camera);    // CV_8U, 255 = valid true ray
  // Noise-free, drift-free signal of the background (CV_32FC3, R, G, B in DN before
  // quantisation) and the locked exposure (DN per unit of Lighting::Shade radiance).
  static cv::Mat BackgroundSignal(const TactileCamera& camera);
  static double Exposure(const TactileCamera& camera);

  // The same frame with the rigid imprint the calibration pipeline assumes (no elastic edge, no
  // bulge). Updates LastFrame() (with rigid = true).
  static cv::Mat RenderRigidAtBall(TactileCamera& camera, const Eigen::Vector3d& ball_center_sensor,
                                   std::uint64_t frame_index, double run_time_s = 0.0);
};

}  // namespace gs360
