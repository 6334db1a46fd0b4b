#include "calib/pose.h"

#include <catch2/catch.hpp>
#include <cmath>
#include <memory>
#include <numbers>
#include <random>
#include <set>
#include <vector>

#include <opencv2/imgproc.hpp>

#include "calib/impression_centroid.h"
#include "calib/render.h"
#include "geometry/sampling.h"
#include "geometry/shapes.h"
#include "recon/surface_map.h"
#include "sim/ground_truth.h"
#include "sim/rig_model.h"
#include "sim/tactile_camera.h"
#include "tests/angles.h"

namespace gs360 {
namespace {

using gs360::test::kRadToDeg;

double CentreErrorMm(const Rigid3d& a, const Rigid3d& b) {
  return (a.Inverse().translation - b.Inverse().translation).norm();
}
double RotationErrorDeg(const Rigid3d& a, const Rigid3d& b) {
  return RotationDifferenceRad(a, b) * kRadToDeg;
}

// Random visible points of the sensor as the nominal camera sees them.
std::vector<PoseObservation> SampleSurface(const SimRig& rig, int count, std::uint64_t seed) {
  const FisheyeCamera nominal(rig.nominal_intrinsics());
  const Rigid3d cam_from_sensor = rig.nominal_cam_from_sensor();
  const SurfaceMap map = SurfaceMap::Build(nominal, cam_from_sensor, rig.gel_bvh(), &rig.fin_bvh());
  const Rigid3d sensor_from_cam = cam_from_sensor.Inverse();
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<int> du(0, map.width() - 1), dv(0, map.height() - 1);
  std::vector<PoseObservation> out;
  while (static_cast<int>(out.size()) < count) {
    const int u = du(rng), v = dv(rng);
    if (!map.visible(u, v) || map.view_angle(u, v) > 70.0 / kRadToDeg) continue;
    PoseObservation o;
    o.probe_index = static_cast<int>(out.size());
    o.contact_point_sensor = sensor_from_cam * map.point0(u, v);
    o.contact_normal_sensor = sensor_from_cam.RotateDirection(map.normal0(u, v)).normalized();
    o.ball_center_sensor =
        o.contact_point_sensor + o.contact_normal_sensor * (rig.ball_radius() - 1.0);
    out.push_back(o);
  }
  return out;
}

// Area-uniform visible points of the sensor (as the planner samples), seen by the nominal camera
// at most 70 deg from their normal.
std::vector<PoseObservation> SampleSurfaceUniform(const SimRig& rig, int count,
                                                  std::uint64_t seed) {
  const FisheyeCamera nominal(rig.nominal_intrinsics());
  const Rigid3d cam_from_sensor = rig.nominal_cam_from_sensor();
  const SurfaceMap map = SurfaceMap::Build(nominal, cam_from_sensor, rig.gel_bvh(), &rig.fin_bvh());
  const auto keep = [&](const SurfaceSample& s) {
    const Eigen::Vector3d x = cam_from_sensor * s.point;
    const auto px = nominal.CamToPixel(x);
    if (!px) return false;
    const int u = static_cast<int>(std::lround(px->x())),
              v = static_cast<int>(std::lround(px->y()));
    if (u < 0 || v < 0 || u >= map.width() || v >= map.height() || !map.visible(u, v)) return false;
    if ((map.point0(u, v) - x).norm() > 0.3) return false;  // hidden behind other gel
    const Eigen::Vector3d n = cam_from_sensor.RotateDirection(s.normal);
    return std::acos(std::abs(n.dot(x.normalized()))) <= 70.0 / kRadToDeg;
  };
  std::vector<PoseObservation> out;
  for (const SurfaceSample& s : SampleUniform(rig.gel_mesh(), count, seed, keep)) {
    PoseObservation o;
    o.probe_index = static_cast<int>(out.size());
    o.contact_point_sensor = s.point;
    o.contact_normal_sensor = s.normal;
    o.ball_center_sensor = s.point + s.normal * (rig.ball_radius() - 1.0);
    out.push_back(o);
  }
  return out;
}

std::shared_ptr<const SimRig> DefaultRig() {
  static const std::shared_ptr<const SimRig> rig = [] {
    const SimRigOptions options;
    return std::make_shared<const SimRig>(options);
  }();
  return rig;
}

Rigid3d Offset(const Rigid3d& pose, double mm, double deg) {
  const Rigid3d delta = Rigid3d::FromAxisAngle(Eigen::Vector3d(0.3, -1.0, 0.5), deg / kRadToDeg,
                                               Eigen::Vector3d(0.6, 0.2, -0.77).normalized() * mm);
  return delta * pose;
}

// The nominal camera 0.3 mm and 1 deg off its nominal pose (the truth), and its surface map.
struct OffsetCamera {
  explicit OffsetCamera(const SimRig& rig)
      : camera(rig.nominal_intrinsics()),
        nominal(rig.nominal_cam_from_sensor()),
        truth(Offset(nominal, 0.3, 1.0)),
        true_map(SurfaceMap::Build(camera, truth, rig.gel_bvh(), &rig.fin_bvh())) {}
  FisheyeCamera camera;
  Rigid3d nominal, truth;
  SurfaceMap true_map;
};

TEST_CASE("EstimateCamFromSensor: exact projections with noise and outliers", "[pose]") {
  const SimRig& rig = *DefaultRig();
  const FisheyeCamera camera(rig.nominal_intrinsics());
  const Rigid3d nominal = rig.nominal_cam_from_sensor();
  for (const auto& [mm, deg] : {std::pair{0.3, 1.0}, std::pair{1.0, 3.0}}) {
    const Rigid3d truth = Offset(nominal, mm, deg);
    std::vector<PoseObservation> obs = SampleSurface(rig, 600, 3);
    std::mt19937_64 rng(9);
    std::normal_distribution<double> noise(0.0, 0.3);
    std::uniform_real_distribution<double> far(8.0, 30.0), angle(0.0, 2.0 * std::numbers::pi);
    std::set<int> planted;
    for (PoseObservation& o : obs) {
      o.centroid_px = camera.ProjectUnchecked(truth * o.contact_point_sensor) +
                      Eigen::Vector2d(noise(rng), noise(rng));
      if (o.probe_index % 20 == 7) {  // 5% outliers
        const double a = angle(rng), d = far(rng);
        o.centroid_px += d * Eigen::Vector2d(std::cos(a), std::sin(a));
        planted.insert(o.probe_index);
      }
    }
    PoseOptions options;
    options.model_bias = false;
    options.max_view_angle_deg = 90.0;  // exact projections: every view angle is usable
    const PoseResult r = EstimateCamFromSensor(camera, obs, nominal, options);
    INFO("offset " << mm << " mm " << deg << " deg: refined "
                   << CentreErrorMm(r.cam_from_sensor, truth) << " mm "
                   << RotationErrorDeg(r.cam_from_sensor, truth) << " deg; paper "
                   << CentreErrorMm(r.paper_cam_from_sensor, truth) << " mm "
                   << RotationErrorDeg(r.paper_cam_from_sensor, truth) << " deg");
    CHECK(CentreErrorMm(r.cam_from_sensor, truth) < 0.01);
    CHECK(RotationErrorDeg(r.cam_from_sensor, truth) < 0.02);
    CHECK(CentreErrorMm(r.paper_cam_from_sensor, truth) < 0.1);
    CHECK(r.rms_px == Approx(0.3 * std::sqrt(2.0)).epsilon(0.15));
    CHECK(r.outliers == static_cast<int>(planted.size()));
    CHECK(std::set<int>(r.outlier_probe_indices.begin(), r.outlier_probe_indices.end()) == planted);
    CHECK(r.inliers + r.outliers == 600);
    CHECK(r.oblique == 0);
    CHECK(r.bias_rounds == 0);
  }
}

// The rendered imprint's hull centroid, as EstimateCamFromSensor predicts it.
Eigen::Vector2d RenderedHullCentroid(const SurfaceMap& map, const FisheyeCamera& camera,
                                     const Eigen::Vector3d& ball_cam, double radius) {
  const ProbeRender pr = RenderProbe(map, camera, ball_cam, radius);
  std::vector<cv::Point> points, hull;
  for (int y = 0; y < pr.contact.rows; ++y) {
    for (int x = 0; x < pr.contact.cols; ++x) {
      if (pr.contact.at<std::uint8_t>(y, x)) points.emplace_back(pr.roi.x + x, pr.roi.y + y);
    }
  }
  if (points.size() < 3) return Eigen::Vector2d::Constant(std::nan(""));
  cv::convexHull(points, hull);
  const cv::Moments m = cv::moments(hull);
  return {m.m10 / m.m00, m.m01 / m.m00};
}

TEST_CASE("EstimateCamFromSensor: the bias model removes the imprint's bias", "[pose]") {
  const SimRig& rig = *DefaultRig();
  const auto& [camera, nominal, truth, true_map] = OffsetCamera(rig);
  std::vector<PoseObservation> obs;
  for (PoseObservation o : SampleSurface(rig, 400, 5)) {
    o.centroid_px =
        RenderedHullCentroid(true_map, camera, truth * o.ball_center_sensor, rig.ball_radius());
    if (o.centroid_px.allFinite()) obs.push_back(o);
  }
  REQUIRE(obs.size() > 350);
  PoseOptions options;
  options.ball_radius_mm = rig.ball_radius();
  options.model_finder = false;  // the observations are the rendered contact's hull centroids
  const PoseScene scene{&rig.gel_bvh(), &rig.fin_bvh()};
  options.model_bias = false;
  const PoseResult plain = EstimateCamFromSensor(camera, obs, nominal, options, scene);
  options.model_bias = true;
  const PoseResult biased = EstimateCamFromSensor(camera, obs, nominal, options, scene);
  const double plain_mm = CentreErrorMm(plain.cam_from_sensor, truth);
  const double biased_mm = CentreErrorMm(biased.cam_from_sensor, truth);
  const double biased_deg = RotationErrorDeg(biased.cam_from_sensor, truth);
  INFO("no model " << plain_mm << " mm " << RotationErrorDeg(plain.cam_from_sensor, truth)
                   << " deg, rms " << plain.rms_px << "; model " << biased_mm << " mm "
                   << biased_deg << " deg, rms " << biased.rms_px << ", mean bias "
                   << biased.mean_bias_px);
  CHECK(biased.bias_rounds == options.bias_rounds);
  CHECK(biased.mean_bias_px > 0.3);
  CHECK(biased.rms_px < 0.1);
  CHECK(biased.rms_px < plain.rms_px / 3.0);
  CHECK(biased_mm < 0.005);
  CHECK(biased_deg < 0.005);
  CHECK(biased_mm < plain_mm);
}

// Measured on held-out dome rigs (docs/benchmarks.md, "Held-out rigs"): faint presses whose
// changed region spreads far beyond one imprint have centres many pixels off, all in the same
// direction; as a third of the observations they pulled the fit 0.2 deg off. Here the planted
// ones are 1.5 px off in one direction with regions 20 times their imprint; the rest are rigid
// imprint centroids whose regions are twice their imprint.
TEST_CASE("EstimateCamFromSensor: impressions spread far beyond their imprint are left out",
          "[pose]") {
  const SimRig& rig = *DefaultRig();
  const auto& [camera, nominal, truth, true_map] = OffsetCamera(rig);
  std::vector<PoseObservation> obs;
  int planted = 0;
  for (PoseObservation o : SampleSurface(rig, 400, 5)) {
    const Eigen::Vector3d ball = truth * o.ball_center_sensor;
    o.centroid_px = RenderedHullCentroid(true_map, camera, ball, rig.ball_radius());
    const int contact = RenderProbe(true_map, camera, ball, rig.ball_radius()).contact_pixels;
    if (!o.centroid_px.allFinite() || contact == 0) continue;
    o.region_px = 2.0 * contact;
    if (obs.size() % 3 == 0) {
      o.centroid_px += Eigen::Vector2d(1.5, 0.0);
      o.region_px = 20.0 * contact;
      ++planted;
    }
    obs.push_back(o);
  }
  REQUIRE(obs.size() > 350);
  PoseOptions options;
  options.ball_radius_mm = rig.ball_radius();
  options.model_finder = false;  // the observations are the rendered contact's hull centroids
  const PoseScene scene{&rig.gel_bvh(), &rig.fin_bvh()};
  options.max_region_ratio = 0.0;
  const PoseResult kept = EstimateCamFromSensor(camera, obs, nominal, options, scene);
  options.max_region_ratio = 3.0;
  const PoseResult left_out = EstimateCamFromSensor(camera, obs, nominal, options, scene);
  const double kept_deg = RotationErrorDeg(kept.cam_from_sensor, truth);
  const double out_deg = RotationErrorDeg(left_out.cam_from_sensor, truth);
  INFO("all kept " << CentreErrorMm(kept.cam_from_sensor, truth) << " mm " << kept_deg
                   << " deg; spread left out (" << left_out.spread << " of " << planted << ") "
                   << CentreErrorMm(left_out.cam_from_sensor, truth) << " mm " << out_deg
                   << " deg");
  CHECK(kept.spread == 0);
  // Every planted one goes, and none of the others (the view bound may leave out some of both).
  CHECK(left_out.spread + left_out.oblique >= planted);
  CHECK(left_out.spread <= planted);
  CHECK(kept_deg > 0.05);
  CHECK(out_deg < 0.01);
  CHECK(CentreErrorMm(left_out.cam_from_sensor, truth) < 0.01);
  // Without sizes (region_px 0) nothing is left out.
  for (PoseObservation& o : obs) o.region_px = 0.0;
  CHECK(EstimateCamFromSensor(camera, obs, nominal, options, scene).spread == 0);
  options.max_region_ratio = 0.5;
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("max_region_ratio"));
}

// Measured on held-out tall fingers (docs/benchmarks.md, "Held-out rigs"): the face-on imprints the
// view bound keeps were the large, faint ones near the base, their centres several pixels off in
// every direction, and the bounded fit 0.35-5.9 mm off; the oblique ones were within 0.5 px.
// Here the ones within a 30 deg bound get 4 px of scatter, the others 0.2 px.
TEST_CASE("EstimateCamFromSensor: the view bound is released when its set fits far worse",
          "[pose]") {
  const SimRig& rig = *DefaultRig();
  const FisheyeCamera camera(rig.nominal_intrinsics());
  const Rigid3d nominal = rig.nominal_cam_from_sensor();
  const Rigid3d truth = Offset(nominal, 0.3, 1.0);
  std::mt19937_64 rng(11);
  std::normal_distribution<double> fine(0.0, 0.2), coarse(0.0, 4.0);
  auto observe = [&](double face_on_sigma_scale) {
    std::vector<PoseObservation> obs = SampleSurface(rig, 600, 7);
    for (PoseObservation& o : obs) {
      const bool face_on = ObservationViewAngle(o, truth) < 30.0 * std::numbers::pi / 180.0;
      const double sx = face_on ? face_on_sigma_scale * coarse(rng) : fine(rng);
      const double sy = face_on ? face_on_sigma_scale * coarse(rng) : fine(rng);
      o.centroid_px =
          camera.ProjectUnchecked(truth * o.contact_point_sensor) + Eigen::Vector2d(sx, sy);
    }
    return obs;
  };
  PoseOptions options;
  options.model_bias = false;
  options.max_view_angle_deg = 30.0;
  const std::vector<PoseObservation> scattered = observe(1.0);
  const PoseResult released = EstimateCamFromSensor(camera, scattered, nominal, options);
  options.max_bound_rms_ratio = 0.0;
  const PoseResult bounded = EstimateCamFromSensor(camera, scattered, nominal, options);
  INFO("bounded " << CentreErrorMm(bounded.cam_from_sensor, truth) << " mm "
                  << RotationErrorDeg(bounded.cam_from_sensor, truth) << " deg, rms "
                  << bounded.rms_px << "; released "
                  << CentreErrorMm(released.cam_from_sensor, truth) << " mm "
                  << RotationErrorDeg(released.cam_from_sensor, truth) << " deg, rms "
                  << released.rms_px);
  CHECK(bounded.oblique > 0);
  CHECK_FALSE(bounded.view_bound_released);
  CHECK(released.view_bound_released);
  CHECK(released.oblique == 0);
  CHECK(released.view_bound_deg == 90.0);
  CHECK(CentreErrorMm(released.cam_from_sensor, truth) < 0.02);
  CHECK(CentreErrorMm(released.cam_from_sensor, truth) <
        0.5 * CentreErrorMm(bounded.cam_from_sensor, truth));
  // Where the face-on centres are as good as the oblique ones, the bound stays.
  options.max_bound_rms_ratio = 2.0;
  const PoseResult clean = EstimateCamFromSensor(camera, observe(0.05), nominal, options);
  CHECK_FALSE(clean.view_bound_released);
  CHECK(clean.oblique > 0);
  options.max_bound_rms_ratio = 0.5;
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("max_bound_rms_ratio"));
}

// Image direction (unit) of the imprint's near side: moving from the contact point along the
// surface toward the camera.
Eigen::Vector2d NearSideDirection(const FisheyeCamera& camera, const Rigid3d& cam_from_sensor,
                                  const PoseObservation& o) {
  const Eigen::Vector3d x = cam_from_sensor * o.contact_point_sensor;
  const Eigen::Vector3d n = cam_from_sensor.RotateDirection(o.contact_normal_sensor).normalized();
  Eigen::Vector3d toward = -x.normalized();
  toward -= toward.dot(n) * n;
  if (toward.norm() < 1e-9) return Eigen::Vector2d::Zero();
  const Eigen::Vector2d d =
      camera.ProjectUnchecked(x + 0.01 * toward.normalized()) - camera.ProjectUnchecked(x);
  return d.normalized();
}

// The failure measured on the virtual rig's stored runs (bench/bench_pose_db.cc): impressions seen
// more than 50 deg from their normal have centres ~1.5 px (median) toward their near side (their
// far side's shading falls under the region threshold), which the rigid bias model does not
// predict. On the cone that biased band is a third of the probes and pulled the refined pose
// 0.10 deg off. Here: rigid imprint centroids on an area-uniform cone sample, 0.2 px noise, and
// the measured 1.5 px near-side shift planted on the oblique ones.
TEST_CASE("EstimateCamFromSensor: oblique impressions are left out of the refinement", "[pose]") {
  SimRigOptions rig_options;
  rig_options.rig.shape.shape = SensorShape::kCone;
  const SimRig rig(rig_options);
  const auto& [camera, nominal, truth, true_map] = OffsetCamera(rig);
  std::mt19937_64 rng(17);
  std::normal_distribution<double> noise(0.0, 0.2);
  std::vector<PoseObservation> obs;
  int oblique = 0;
  for (PoseObservation o : SampleSurfaceUniform(rig, 500, 21)) {
    o.centroid_px =
        RenderedHullCentroid(true_map, camera, truth * o.ball_center_sensor, rig.ball_radius());
    if (!o.centroid_px.allFinite()) continue;
    o.centroid_px += Eigen::Vector2d(noise(rng), noise(rng));
    if (ObservationViewAngle(o, truth) * kRadToDeg > 50.0) {
      o.centroid_px += 1.5 * NearSideDirection(camera, truth, o);
      ++oblique;
    }
    obs.push_back(o);
  }
  REQUIRE(obs.size() > 450);
  REQUIRE(oblique > 100);
  PoseOptions options;
  options.max_view_angle_deg = 50.0;  // the planted band
  options.ball_radius_mm = rig.ball_radius();
  options.model_finder = false;  // the observations are the rendered contact's hull centroids
  const PoseScene scene{&rig.gel_bvh(), &rig.fin_bvh()};
  const PoseResult r = EstimateCamFromSensor(camera, obs, nominal, options, scene);
  options.max_view_angle_deg = 90.0;
  const PoseResult all = EstimateCamFromSensor(camera, obs, nominal, options, scene);
  const double mm = CentreErrorMm(r.cam_from_sensor, truth);
  const double deg = RotationErrorDeg(r.cam_from_sensor, truth);
  const double all_mm = CentreErrorMm(all.cam_from_sensor, truth);
  const double all_deg = RotationErrorDeg(all.cam_from_sensor, truth);
  INFO(oblique << " oblique of " << obs.size() << "; view bound " << r.view_bound_deg << " deg, "
               << r.oblique << " left out: " << mm << " mm " << deg << " deg, rms " << r.rms_px
               << "; all: " << all_mm << " mm " << all_deg << " deg, rms " << all.rms_px);
  CHECK(r.view_bound_deg == Approx(50.0));
  // The paper pose is within ~0.3 deg of the truth, so the split matches the planted one closely.
  CHECK(std::abs(r.oblique - oblique) < oblique / 10);
  CHECK(r.inliers + r.outliers + r.oblique == static_cast<int>(obs.size()));
  CHECK(mm < 0.003);
  CHECK(deg < 0.012);
  CHECK(r.rms_px < 0.35);  // the planted noise: 0.2 px per axis
  // The scene exercises the failure: with every observation the pose is pulled (about 0.005 mm
  // and 0.022 deg here) and the residuals carry the planted bias.
  CHECK(all_deg > 2.0 * deg);
  CHECK(all_mm > 2.0 * mm);
  CHECK(all.rms_px > 2.0 * r.rms_px);
}

// The same on the virtual rig's cone, pressed through the simulated camera (elastic gel, LED
// lighting, noise): the impression regions of the oblique probes are biased by their shading.
TEST_CASE("EstimateCamFromSensor: the view bound keeps the least oblique when too few qualify",
          "[pose]") {
  const SimRig& rig = *DefaultRig();
  const FisheyeCamera camera(rig.nominal_intrinsics());
  const Rigid3d nominal = rig.nominal_cam_from_sensor();
  const Rigid3d truth = Offset(nominal, 0.3, 1.0);
  std::vector<PoseObservation> obs = SampleSurface(rig, 300, 4);
  for (PoseObservation& o : obs) {
    o.centroid_px = camera.ProjectUnchecked(truth * o.contact_point_sensor);
  }
  PoseOptions options;
  options.model_bias = false;
  options.max_view_angle_deg = 5.0;  // almost nothing qualifies
  options.min_view_fraction = 0.4;
  const PoseResult r = EstimateCamFromSensor(camera, obs, nominal, options);
  CHECK(r.inliers + r.outliers == 120);  // ceil(0.4 * 300)
  CHECK(r.oblique == 180);
  CHECK(r.view_bound_deg > 5.0);
  CHECK(CentreErrorMm(r.cam_from_sensor, truth) < 1e-3);
  CHECK(RotationErrorDeg(r.cam_from_sensor, truth) < 1e-3);
  PoseOptions bad;
  bad.max_view_angle_deg = 0.0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("max_view_angle_deg"));
  bad = {};
  bad.min_view_fraction = 1.5;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("min_view_fraction"));
}

// Held-out rig 9 (docs/benchmarks.md): faint presses whose frames changed more elsewhere had their
// impression taken 30-165 px away. With the pixel the press should show at, a peak far from it is
// looked for again near it; with nothing near it, the far one stays (a nominal pose far off).
TEST_CASE("FindImpressionRegion: the peak is looked for near the expected pixel", "[pose]") {
  const cv::Mat reference(240, 320, CV_8UC3, cv::Scalar(80, 80, 80));
  cv::Mat press = reference.clone();
  cv::circle(press, cv::Point(60, 60), 8, cv::Scalar(140, 140, 140), cv::FILLED);    // strong, far
  cv::circle(press, cv::Point(240, 170), 8, cv::Scalar(100, 100, 100), cv::FILLED);  // the press
  const auto anywhere = FindImpressionRegion(press, reference);
  REQUIRE(anywhere);
  CHECK((anywhere->centroid - Eigen::Vector2d(60, 60)).norm() < 1.5);
  ImpressionCentroidOptions options;
  const auto near =
      FindImpressionRegion(press, reference, options, {}, Eigen::Vector2d(230.0, 160.0));
  REQUIRE(near);
  CHECK((near->centroid - Eigen::Vector2d(240, 170)).norm() < 1.5);
  // Nothing near it, or no expected pixel: the strongest change.
  for (const Eigen::Vector2d& expected :
       {Eigen::Vector2d(160.0, 40.0), Eigen::Vector2d(NAN, 0.0), Eigen::Vector2d(1e12, -1e12),
        Eigen::Vector2d(-45.0, 100.0)}) {
    const auto far = FindImpressionRegion(press, reference, options, {}, expected);
    REQUIRE(far);
    CHECK((far->centroid - Eigen::Vector2d(60, 60)).norm() < 1.5);
  }
  options.search_radius_px = 0.0;
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("search_radius_px"));
  // A run keeps only the near ones while at least half are near; else the nominal pose is off.
  CHECK(NominalPoseHolds(10, 5));
  CHECK_FALSE(NominalPoseHolds(10, 4));
  CHECK(NominalPoseHolds(0, 0));
}

// A second change in the window, apart from the press (LED drift at the gel's edge): left out.
TEST_CASE("FindImpressionRegion: the region is connected to the peak", "[pose]") {
  const cv::Mat reference(240, 320, CV_8UC3, cv::Scalar(80, 80, 80));
  cv::Mat press = reference.clone();
  cv::circle(press, cv::Point(150, 120), 10, cv::Scalar(140, 140, 140), cv::FILLED);
  cv::rectangle(press, cv::Rect(185, 90, 8, 60), cv::Scalar(110, 110, 110), cv::FILLED);
  const auto region = FindImpressionRegion(press, reference);
  REQUIRE(region);
  CHECK((region->centroid - Eigen::Vector2d(150, 120)).norm() < 1.0);
  CHECK(region->box.br().x < 165);
}

TEST_CASE("EstimateCamFromSensor: simulated impressions", "[pose]") {
  const auto rig = DefaultRig();
  const FisheyeCamera camera = SimGroundTruth::TrueCamera(*rig);
  const Rigid3d truth = SimGroundTruth::TrueCamFromSensor(*rig);
  TactileCameraOptions camera_options;
  camera_options.threads = 2;
  TactileCamera sim(rig, camera_options);
  const cv::Mat reference = sim.RenderReference(100000);
  std::vector<PoseObservation> obs;
  for (PoseObservation o : SampleSurface(*rig, 300, 11)) {
    const cv::Mat press = sim.RenderAtBall(o.ball_center_sensor, o.probe_index);
    const auto region = FindImpressionRegion(press, reference);
    if (!region) continue;
    o.centroid_px = region->centroid;
    obs.push_back(o);
  }
  REQUIRE(obs.size() > 280);
  PoseOptions options;
  options.ball_radius_mm = rig->ball_radius();
  const PoseScene scene{&rig->gel_bvh(), &rig->fin_bvh()};
  const Rigid3d nominal = rig->nominal_cam_from_sensor();
  const PoseResult r = EstimateCamFromSensor(camera, obs, nominal, options, scene);
  options.model_finder = false;
  const PoseResult hull = EstimateCamFromSensor(camera, obs, nominal, options, scene);
  const double mm = CentreErrorMm(r.cam_from_sensor, truth);
  const double deg = RotationErrorDeg(r.cam_from_sensor, truth);
  const double hull_mm = CentreErrorMm(hull.cam_from_sensor, truth);
  INFO("refined " << mm << " mm " << deg << " deg, rms " << r.rms_px << ", " << r.outliers
                  << " outliers; paper " << CentreErrorMm(r.paper_cam_from_sensor, truth) << " mm "
                  << RotationErrorDeg(r.paper_cam_from_sensor, truth) << " deg; the contact's hull "
                  << "as the model: " << hull_mm << " mm "
                  << RotationErrorDeg(hull.cam_from_sensor, truth) << " deg, rms " << hull.rms_px);
  // The nominal pose is 0.3 mm and 1 deg off.
  CHECK(mm < 0.08);
  CHECK(deg < 0.15);
  CHECK(r.inliers > 150);
  // The frames' imprints are the simulator's (elastic edge, bulge, LEDs), not the bias model's
  // rigid render: the finder's centre of that render predicts theirs better than its hull does.
  CHECK(mm < hull_mm);
}

// A dome seen face-on (held-out rig 3 of `gs360 bench heldout`: a hemisphere-capped cylinder as
// tall as its radius, no fins, the camera 1.1 mm below the base) through the simulated camera. Its
// imprints are lit from one side (the blue ring below them), so the region above a fraction of
// the global peak is a crescent whose hull centroid sits ~5 px toward the lit side, toward the
// image centre on every probe: the fit takes that for the camera moved along its axis (0.67 mm on
// that rig). The per-direction edge (calib/impression_centroid.h) divides each direction's
// lighting gain out.
TEST_CASE("FindImpressionRegion: a dome's face-on imprints lit from one side", "[pose]") {
  SimRigOptions rig_options;
  rig_options.rig.shape.cylinder.radius = 10.3;
  rig_options.rig.shape.cylinder.height = 11.8;
  rig_options.rig.fins.enabled = false;
  rig_options.rig.camera_z = -1.1;
  const auto rig = std::make_shared<const SimRig>(rig_options);
  const FisheyeCamera camera = SimGroundTruth::TrueCamera(*rig);
  const Rigid3d truth = SimGroundTruth::TrueCamFromSensor(*rig);
  const SurfaceMap true_map = SurfaceMap::Build(camera, truth, rig->gel_bvh(), nullptr);
  TactileCameraOptions camera_options;
  camera_options.threads = 2;
  LightingOptions& lighting = camera_options.lighting;  // rig 3's LEDs
  lighting.fin_led_heights = {0.325, 0.327};
  lighting.fin_led_radial = 0.57;
  lighting.red_intensity = 0.57;
  lighting.green_intensity = 1.55;
  lighting.blue_intensity = 13.9;
  lighting.blue_ring_count = 24;
  lighting.blue_ring_radius = 0.51;
  TactileCamera sim(rig, camera_options);
  const cv::Mat reference = sim.RenderReference(100000);
  std::vector<PoseObservation> obs, hull_obs;
  std::vector<double> error_px, hull_error_px;
  for (PoseObservation o : SampleSurfaceUniform(*rig, 300, 5)) {
    const Eigen::Vector2d rigid =
        RenderedHullCentroid(true_map, camera, truth * o.ball_center_sensor, rig->ball_radius());
    const auto region =
        FindImpressionRegion(sim.RenderAtBall(o.ball_center_sensor, o.probe_index), reference);
    if (!region || !rigid.allFinite()) continue;
    // Along the image radius (outward > 0): what the fit takes for the camera's axial position.
    const Eigen::Vector2d radial =
        (rigid - Eigen::Vector2d(camera.intrinsics().cx, camera.intrinsics().cy)).normalized();
    error_px.push_back((region->centroid - rigid).dot(radial));
    hull_error_px.push_back((region->hull_centroid - rigid).dot(radial));
    o.centroid_px = region->centroid;
    obs.push_back(o);
    o.centroid_px = region->hull_centroid;
    hull_obs.push_back(o);
  }
  REQUIRE(obs.size() > 150);
  auto median = [](std::vector<double> v) {
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
    return v[v.size() / 2];
  };
  PoseOptions options;
  options.ball_radius_mm = rig->ball_radius();
  const PoseScene scene{&rig->gel_bvh(), nullptr};
  const Rigid3d nominal = rig->nominal_cam_from_sensor();
  const PoseResult r = EstimateCamFromSensor(camera, obs, nominal, options, scene);
  const PoseResult hull = EstimateCamFromSensor(camera, hull_obs, nominal, options, scene);
  const double mm = CentreErrorMm(r.cam_from_sensor, truth);
  const double hull_mm = CentreErrorMm(hull.cam_from_sensor, truth);
  INFO(obs.size() << " imprints: centre off the rigid imprint's along the image radius by "
                  << median(error_px) << " px (median; hull centroid " << median(hull_error_px)
                  << " px); camera " << mm << " mm " << RotationErrorDeg(r.cam_from_sensor, truth)
                  << " deg off (hull centroids " << hull_mm << " mm "
                  << RotationErrorDeg(hull.cam_from_sensor, truth) << " deg)");
  CHECK(std::abs(median(error_px)) < 2.0);
  CHECK(mm < 0.5 * hull_mm);
  // The scene exercises the failure.
  CHECK(median(hull_error_px) < -3.5);
  CHECK(hull_mm > 0.25);
}

TEST_CASE("EstimateCamFromSensor: failures are clear", "[pose]") {
  const SimRig& rig = *DefaultRig();
  const FisheyeCamera camera(rig.nominal_intrinsics());
  std::vector<PoseObservation> obs = SampleSurface(rig, 5, 1);
  for (PoseObservation& o : obs) {
    o.centroid_px = camera.ProjectUnchecked(rig.nominal_cam_from_sensor() * o.contact_point_sensor);
  }
  PoseOptions options;
  options.model_bias = false;
  CHECK_THROWS_AS(EstimateCamFromSensor(camera, obs, rig.nominal_cam_from_sensor(), options),
                  PoseError);
  CHECK_THROWS_WITH(EstimateCamFromSensor(camera, obs, rig.nominal_cam_from_sensor(), options),
                    Catch::Contains("5 probe impressions, need at least 6"));
  options.model_bias = true;
  CHECK_THROWS_WITH(EstimateCamFromSensor(camera, obs, rig.nominal_cam_from_sensor(), options),
                    Catch::Contains("gel mesh"));
  PoseOptions bad;
  bad.ransac_probes = 3;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("ransac_probes"));
  bad = {};
  bad.threads = 0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("threads"));
}

}  // namespace
}  // namespace gs360
