#include "calib/pose.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>
#include <numbers>
#include <numeric>
#include <random>
#include <sstream>
#include <string>
#include <thread>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

#include "base/field_error.h"
#include "geometry/fisheye_cv.h"

namespace gs360 {
namespace {

template <typename T>
[[noreturn]] void ThrowField(const char* field, T value, const char* what) {
  ThrowFieldError(std::string("PoseOptions.") + field, static_cast<double>(value), what);
}

// pose(w, dt): rotation exp(w) R, translation t + dt (w rotates about the camera centre).
Rigid3d Perturb(const Rigid3d& pose, const Eigen::Matrix<double, 6, 1>& delta) {
  const Eigen::Vector3d w = delta.head<3>();
  const double angle = w.norm();
  const Eigen::Quaterniond q = angle > 0.0 ? Eigen::Quaterniond(Eigen::AngleAxisd(angle, w / angle))
                                           : Eigen::Quaterniond::Identity();
  return Rigid3d(q * pose.rotation, pose.translation + delta.tail<3>());
}

double HuberWeight(double r, double k) {
  return r <= k ? 1.0 : k / r;
}
double HuberCost(double r, double k) {
  return r <= k ? 0.5 * r * r : k * (r - 0.5 * k);
}

double Median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  const auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

Eigen::Vector2d Residual(const FisheyeCamera& camera, const Rigid3d& pose, const PoseObservation& o,
                         const Eigen::Vector2d& offset) {
  return camera.ProjectUnchecked(pose * o.contact_point_sensor) + offset - o.centroid_px;
}

// The pose shifted by +-kJacobianStep along each of its 6 parameters (Perturb), for central
// differences: [2k] = +, [2k + 1] = -.
constexpr double kJacobianStep = 1e-6;
// The residual counted for an observation the pose puts outside the lens's valid field, px.
constexpr double kOutsideFieldPx = 1000.0;
using Shifted = std::array<Rigid3d, 12>;
Shifted ShiftedPoses(const Rigid3d& pose) {
  Shifted shifted;
  for (int k = 0; k < 6; ++k) {
    Eigen::Matrix<double, 6, 1> d = Eigen::Matrix<double, 6, 1>::Zero();
    d[k] = kJacobianStep;
    shifted[2 * k] = Perturb(pose, d);
    shifted[2 * k + 1] = Perturb(pose, -d);
  }
  return shifted;
}

// d(pixel) / d(pose parameters) of the sensor point x, by central differences.
Eigen::Matrix<double, 2, 6> ProjectionJacobian(const FisheyeCamera& camera, const Shifted& shifted,
                                               const Eigen::Vector3d& x) {
  Eigen::Matrix<double, 2, 6> J;
  for (int k = 0; k < 6; ++k) {
    J.col(k) = (camera.ProjectUnchecked(shifted[2 * k] * x) -
                camera.ProjectUnchecked(shifted[2 * k + 1] * x)) /
               (2.0 * kJacobianStep);
  }
  return J;
}

// One robust Levenberg-Marquardt fit over the observations flagged in `use`.
Rigid3d LevenbergMarquardt(const FisheyeCamera& camera, std::span<const PoseObservation> obs,
                           std::span<const Eigen::Vector2d> offsets, const std::vector<bool>& use,
                           Rigid3d pose, const PoseOptions& options) {
  const Eigen::Vector2d zero = Eigen::Vector2d::Zero();
  auto offset = [&](std::size_t i) -> const Eigen::Vector2d& {
    return offsets.empty() ? zero : offsets[i];
  };
  // Every observation was seen, so a pose that puts one outside the lens's valid field is wrong;
  // there the unchecked projection folds back and can fit the centroids better than the truth
  // (a fit 22 mm and 24 deg off, on a finger seen from the side, did).
  const double max_theta = camera.MaxValidTheta();
  auto cost = [&](const Rigid3d& p) {
    double c = 0.0;
    for (std::size_t i = 0; i < obs.size(); ++i) {
      if (!use[i]) continue;
      const Eigen::Vector3d x = p * obs[i].contact_point_sensor;
      const double r = std::atan2(x.head<2>().norm(), x.z()) > max_theta
                           ? kOutsideFieldPx
                           : Residual(camera, p, obs[i], offset(i)).norm();
      c += obs[i].weight * HuberCost(r, options.huber_px);
    }
    return c;
  };
  double lambda = 1e-3;
  double current = cost(pose);
  for (int it = 0; it < options.max_iterations; ++it) {
    Eigen::Matrix<double, 6, 6> H = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, 6, 1> g = Eigen::Matrix<double, 6, 1>::Zero();
    const Shifted shifted = ShiftedPoses(pose);
    for (std::size_t i = 0; i < obs.size(); ++i) {
      if (!use[i]) continue;
      const Eigen::Vector2d r = Residual(camera, pose, obs[i], offset(i));
      const Eigen::Matrix<double, 2, 6> J =
          ProjectionJacobian(camera, shifted, obs[i].contact_point_sensor);
      const double w = obs[i].weight * HuberWeight(r.norm(), options.huber_px);
      H.noalias() += w * J.transpose() * J;
      g.noalias() += w * J.transpose() * r;
    }
    bool improved = false;
    for (int tries = 0; tries < 10 && !improved; ++tries) {
      Eigen::Matrix<double, 6, 6> A = H;
      A.diagonal() += lambda * H.diagonal().cwiseMax(1e-12);
      const Eigen::Matrix<double, 6, 1> step = A.ldlt().solve(-g);
      if (!step.allFinite()) break;
      const Rigid3d candidate = Perturb(pose, step);
      const double c = cost(candidate);
      if (c < current) {
        const double rel = (current - c) / std::max(current, 1e-300);
        pose = candidate;
        current = c;
        lambda = std::max(lambda * 0.3, 1e-9);
        improved = true;
        if (rel < 1e-12 || step.norm() < 1e-12) return pose;
      } else {
        lambda *= 10.0;
      }
    }
    if (!improved) break;
  }
  return pose;
}

// How well the observations flagged in `use` pin the pose down: the condition number of their
// weighted Jacobian at `pose`, its columns scaled to unit norm first so that radians and
// millimetres compare (sqrt of the extreme eigenvalues' ratio of the scaled J^T W J). Infinite
// when a direction of the pose moves no observation (collinear points, for one).
double FitCondition(const FisheyeCamera& camera, std::span<const PoseObservation> obs,
                    const std::vector<bool>& use, const Rigid3d& pose) {
  const Shifted shifted = ShiftedPoses(pose);
  Eigen::Matrix<double, 6, 6> H = Eigen::Matrix<double, 6, 6>::Zero();
  for (std::size_t i = 0; i < obs.size(); ++i) {
    if (!use[i]) continue;
    const Eigen::Matrix<double, 2, 6> J =
        ProjectionJacobian(camera, shifted, obs[i].contact_point_sensor);
    H.noalias() += obs[i].weight * J.transpose() * J;
  }
  const Eigen::Matrix<double, 6, 1> d = H.diagonal();
  if (!(d.minCoeff() > 0.0) || !d.allFinite()) return std::numeric_limits<double>::infinity();
  const Eigen::Matrix<double, 6, 1> s = d.cwiseSqrt().cwiseInverse();
  const Eigen::Matrix<double, 6, 6> scaled = s.asDiagonal() * H * s.asDiagonal();
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 6, 6>> eig(scaled,
                                                                       Eigen::EigenvaluesOnly);
  const double lo = eig.eigenvalues().minCoeff(), hi = eig.eigenvalues().maxCoeff();
  if (!(lo > 0.0)) return std::numeric_limits<double>::infinity();
  return std::sqrt(hi / lo);
}

// Area centroid of the convex hull of the rendered contact pixels: the region an impression
// detector sees (calib/impression_centroid.h), bridged across fins like the observed blob.
Eigen::Vector2d HullCentroid(const ProbeRender& pr) {
  std::vector<cv::Point> points;
  for (int y = 0; y < pr.contact.rows; ++y) {
    const std::uint8_t* row = pr.contact.ptr<std::uint8_t>(y);
    for (int x = 0; x < pr.contact.cols; ++x) {
      if (row[x]) points.emplace_back(pr.roi.x + x, pr.roi.y + y);
    }
  }
  if (points.size() < 3) return pr.contact_centroid;
  std::vector<cv::Point> hull;
  cv::convexHull(points, hull);
  const cv::Moments m = cv::moments(hull);
  if (!(m.m00 > 0.0)) return pr.contact_centroid;
  return {m.m10 / m.m00, m.m01 / m.m00};
}

// The impression finder's centre (header comment, model_finder) of a rendered imprint: the finder
// on the normal change |n - n0| of its contact pixels (0 elsewhere), blurred as the frames are, in
// the render's box grown so that the blur and the finder's rays stay inside. The hull centroid
// where the finder finds nothing.
Eigen::Vector2d FinderCentroid(const ProbeRender& pr, const ImpressionCentroidOptions& finder) {
  // The magnitude's scale is arbitrary: the finder's cuts are fractions of its maxima.
  constexpr float kScale = 100.0f;
  const int grow = 8 + static_cast<int>(std::ceil(3.0 * finder.blur_sigma_px));
  cv::Mat magnitude = cv::Mat::zeros(pr.roi.height + 2 * grow, pr.roi.width + 2 * grow, CV_32F);
  for (int y = 0; y < pr.contact.rows; ++y) {
    const std::uint8_t* contact = pr.contact.ptr<std::uint8_t>(y);
    const float* gx = pr.gx.ptr<float>(y);
    const float* gy = pr.gy.ptr<float>(y);
    float* out = magnitude.ptr<float>(y + grow) + grow;
    for (int x = 0; x < pr.contact.cols; ++x) {
      if (contact[x] == 0) continue;
      // |n - n0|^2 = 2 - 2 n.n0, with n.n0 = 1 / sqrt(1 + gx^2 + gy^2) (render.h's slopes).
      const float cos_turn = 1.0f / std::sqrt(1.0f + gx[x] * gx[x] + gy[x] * gy[x]);
      out[x] = kScale * std::sqrt(std::max(0.0f, 2.0f - 2.0f * cos_turn));
    }
  }
  if (finder.blur_sigma_px > 0.0) {
    cv::GaussianBlur(magnitude, magnitude, cv::Size(), finder.blur_sigma_px);
  }
  ImpressionCentroidOptions rendered = finder;
  rendered.min_peak_dn = 1e-3;
  rendered.min_threshold_dn = 0.0;
  rendered.max_area_fraction = 1.0;
  const auto region = FindImpressionRegionInMagnitude(magnitude, rendered);
  if (!region) return HullCentroid(pr);
  return region->centroid + Eigen::Vector2d(pr.roi.x - grow, pr.roi.y - grow);
}

std::string FormatCondition(double c) {
  if (!std::isfinite(c)) return "infinite";
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.3g", c);
  return buf;
}

std::string ObservationError(std::size_t i, const char* what) {
  return "EstimateCamFromSensor: observation " + std::to_string(i) + " has " + what;
}

}  // namespace

void PoseOptions::Check() const {
  if (ransac_probes < 6) ThrowField("ransac_probes", ransac_probes, "must be >= 6");
  if (!(ransac_threshold_px > 0.0)) {
    ThrowField("ransac_threshold_px", ransac_threshold_px, "must be > 0");
  }
  if (ransac_iterations < 1) ThrowField("ransac_iterations", ransac_iterations, "must be >= 1");
  if (max_iterations < 1) ThrowField("max_iterations", max_iterations, "must be >= 1");
  if (!(huber_px > 0.0)) ThrowField("huber_px", huber_px, "must be > 0");
  if (!(outlier_px > 0.0)) ThrowField("outlier_px", outlier_px, "must be > 0");
  if (!(max_view_angle_deg > 0.0 && max_view_angle_deg <= 90.0)) {
    ThrowField("max_view_angle_deg", max_view_angle_deg, "must be in (0, 90]");
  }
  if (!(min_view_fraction > 0.0 && min_view_fraction <= 1.0)) {
    ThrowField("min_view_fraction", min_view_fraction, "must be in (0, 1]");
  }
  if (min_observations < 6) ThrowField("min_observations", min_observations, "must be >= 6");
  if (bias_rounds < 1) ThrowField("bias_rounds", bias_rounds, "must be >= 1");
  if (!(max_bound_rms_ratio == 0.0 ||
        (max_bound_rms_ratio >= 1.0 && std::isfinite(max_bound_rms_ratio)))) {
    ThrowField("max_bound_rms_ratio", max_bound_rms_ratio, "must be 0 or finite and >= 1");
  }
  if (!(max_region_ratio == 0.0 || (max_region_ratio >= 1.0 && std::isfinite(max_region_ratio)))) {
    ThrowField("max_region_ratio", max_region_ratio, "must be 0 or finite and >= 1");
  }
  if (!(max_condition >= 1.0)) ThrowField("max_condition", max_condition, "must be >= 1");
  if (!(ball_radius_mm > 0.0) || !std::isfinite(ball_radius_mm)) {
    ThrowField("ball_radius_mm", ball_radius_mm, "must be finite and > 0");
  }
  if (threads < 1 || threads > 64) ThrowField("threads", threads, "must be in [1, 64]");
  render.Check();
  surface_map.Check();
}

double ObservationViewAngle(const PoseObservation& observation, const Rigid3d& cam_from_sensor) {
  const Eigen::Vector3d x = cam_from_sensor * observation.contact_point_sensor;
  const Eigen::Vector3d n = cam_from_sensor.RotateDirection(observation.contact_normal_sensor);
  const double xn = x.norm(), nn = n.norm();
  if (!(xn > 0.0) || !(nn > 0.0)) return 0.5 * std::numbers::pi;
  return std::acos(std::min(1.0, std::abs(x.dot(n)) / (xn * nn)));
}

PoseFit RefineCamFromSensor(const FisheyeCamera& camera,
                            std::span<const PoseObservation> observations,
                            std::span<const Eigen::Vector2d> offsets, const Rigid3d& initial,
                            const PoseOptions& options) {
  options.Check();
  if (!offsets.empty() && offsets.size() != observations.size()) {
    throw std::invalid_argument("RefineCamFromSensor: " + std::to_string(offsets.size()) +
                                " offsets for " + std::to_string(observations.size()) +
                                " observations");
  }
  const std::size_t n = observations.size();
  if (static_cast<int>(n) < options.min_observations) {
    throw PoseError("RefineCamFromSensor: " + std::to_string(n) + " observations, need at least " +
                    std::to_string(options.min_observations));
  }
  const Eigen::Vector2d zero = Eigen::Vector2d::Zero();
  std::vector<bool> use(n, true);
  Rigid3d pose = initial;
  std::vector<double> norms(n);
  for (int round = 0; round < 6; ++round) {
    pose = LevenbergMarquardt(camera, observations, offsets, use, pose, options);
    std::vector<double> inlier_norms;
    for (std::size_t i = 0; i < n; ++i) {
      norms[i] =
          Residual(camera, pose, observations[i], offsets.empty() ? zero : offsets[i]).norm();
      if (use[i]) inlier_norms.push_back(norms[i]);
    }
    // Robust sigma of the 2D residual from the median of its norm (Rayleigh: median = 1.1774 s).
    const double sigma = Median(inlier_norms) / 1.1774;
    const double bound = std::max(options.outlier_px, 4.0 * sigma);
    std::vector<bool> next(n);
    int count = 0;
    for (std::size_t i = 0; i < n; ++i) {
      next[i] = norms[i] <= bound;
      count += next[i] ? 1 : 0;
    }
    if (count < options.min_observations) {
      throw PoseError("RefineCamFromSensor: only " + std::to_string(count) +
                      " observations within " + std::to_string(bound) +
                      " px of the fit, need at least " + std::to_string(options.min_observations));
    }
    if (next == use) break;
    use = std::move(next);
  }
  PoseFit fit;
  fit.cam_from_sensor = pose;
  fit.inlier = use;
  double sum = 0.0, wsum = 0.0;
  for (std::size_t i = 0; i < n; ++i) {
    if (!use[i]) continue;
    ++fit.inliers;
    sum += observations[i].weight * norms[i] * norms[i];
    wsum += observations[i].weight;
  }
  fit.rms_px = std::sqrt(sum / wsum);
  fit.condition = FitCondition(camera, observations, use, pose);
  return fit;
}

namespace {

void CheckObservations(std::span<const PoseObservation> observations, const PoseOptions& options,
                       const PoseScene& scene) {
  if (options.model_bias && scene.gel == nullptr) {
    throw std::invalid_argument(
        "EstimateCamFromSensor: PoseOptions.model_bias needs the gel mesh (PoseScene::gel)");
  }
  if (options.model_bias && options.model_finder) scene.finder.Check();
  for (std::size_t i = 0; i < observations.size(); ++i) {
    const PoseObservation& o = observations[i];
    if (!o.contact_point_sensor.allFinite() || !o.ball_center_sensor.allFinite() ||
        !o.contact_normal_sensor.allFinite()) {
      throw std::invalid_argument(ObservationError(i, "a non-finite point"));
    }
    if (!o.centroid_px.allFinite()) {
      throw std::invalid_argument(ObservationError(i, "a non-finite centroid"));
    }
    if (!(o.weight > 0.0) || !std::isfinite(o.weight)) {
      throw std::invalid_argument(ObservationError(i, "a weight that is not finite and > 0"));
    }
    if (!(o.region_px >= 0.0) || !std::isfinite(o.region_px)) {
      throw std::invalid_argument(ObservationError(i, "a region size that is not finite and >= 0"));
    }
  }
  const std::size_t n = observations.size();
  if (static_cast<int>(n) < options.min_observations) {
    throw PoseError("EstimateCamFromSensor: " + std::to_string(n) +
                    " probe impressions, need at least " +
                    std::to_string(options.min_observations));
  }
}

// 1. The paper's estimate: RANSAC PnP on undistorted centroids of a random subset. Sets the
// result's paper_* fields.
void EstimatePaperPose(const FisheyeCamera& camera, std::span<const PoseObservation> observations,
                       const Rigid3d& nominal_cam_from_sensor, const PoseOptions& options,
                       PoseResult* result) {
  const std::size_t n = observations.size();
  std::vector<int> order(n);
  std::iota(order.begin(), order.end(), 0);
  std::mt19937_64 rng(options.seed);
  std::shuffle(order.begin(), order.end(), rng);
  order.resize(std::min<std::size_t>(n, static_cast<std::size_t>(options.ransac_probes)));
  std::vector<cv::Point3d> object;
  std::vector<cv::Point2d> distorted, normalised;
  for (int i : order) {
    const PoseObservation& o = observations[static_cast<std::size_t>(i)];
    object.emplace_back(o.contact_point_sensor.x(), o.contact_point_sensor.y(),
                        o.contact_point_sensor.z());
    distorted.emplace_back(o.centroid_px.x(), o.centroid_px.y());
  }
  const FisheyeIntrinsics& in = camera.intrinsics();
  cv::fisheye::undistortPoints(distorted, normalised, ToCvK(in), ToCvD(in));
  const Eigen::Matrix3d r0 = nominal_cam_from_sensor.RotationMatrix();
  cv::Matx33d r0_cv;
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) r0_cv(a, b) = r0(a, b);
  }
  cv::Vec3d rvec,
      tvec(nominal_cam_from_sensor.translation.x(), nominal_cam_from_sensor.translation.y(),
           nominal_cam_from_sensor.translation.z());
  cv::Rodrigues(r0_cv, rvec);
  std::vector<int> ransac_inliers;
  bool ok = false;
  try {
    ok = cv::solvePnPRansac(object, normalised, cv::Matx33d::eye(), cv::noArray(), rvec, tvec,
                            /*useExtrinsicGuess=*/true, options.ransac_iterations,
                            static_cast<float>(options.ransac_threshold_px / in.fx), 0.999,
                            ransac_inliers, cv::SOLVEPNP_ITERATIVE);
  } catch (const cv::Exception& e) {
    throw PoseError(std::string("EstimateCamFromSensor: solvePnPRansac failed: ") + e.what());
  }
  if (!ok || static_cast<int>(ransac_inliers.size()) < options.min_observations) {
    throw PoseError("EstimateCamFromSensor: solvePnPRansac found no pose with at least " +
                    std::to_string(options.min_observations) + " inliers among " +
                    std::to_string(order.size()) + " probes (" +
                    std::to_string(ransac_inliers.size()) + " inliers)");
  }
  cv::Matx33d r_cv;
  cv::Rodrigues(rvec, r_cv);
  Eigen::Matrix<double, 3, 4> m;
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) m(a, b) = r_cv(a, b);
    m(a, 3) = tvec[a];
  }
  result->paper_cam_from_sensor = Rigid3d::FromMatrix(m);
  result->paper_inliers = static_cast<int>(ransac_inliers.size());
  double sum = 0.0;
  for (int k : ransac_inliers) {
    const PoseObservation& o = observations[static_cast<std::size_t>(order[k])];
    sum +=
        Residual(camera, result->paper_cam_from_sensor, o, Eigen::Vector2d::Zero()).squaredNorm();
  }
  result->paper_rms_px = std::sqrt(sum / static_cast<double>(ransac_inliers.size()));
}

// 2. The observations the refinement uses: those seen at most max_view_angle_deg from their
// normal at `start`, the paper estimate (at least min_view_fraction of them, the least oblique).
// Sets the result's view_bound_deg and oblique.
std::vector<PoseObservation> ChooseObservations(std::span<const PoseObservation> observations,
                                                const Rigid3d& start, const PoseOptions& options,
                                                PoseResult* result) {
  const std::size_t n = observations.size();
  std::vector<std::size_t> chosen;
  std::vector<double> view(n);
  for (std::size_t i = 0; i < n; ++i) {
    view[i] = ObservationViewAngle(observations[i], start);
  }
  std::vector<double> sorted = view;
  std::sort(sorted.begin(), sorted.end());
  const std::size_t keep =
      std::min(n, std::max(static_cast<std::size_t>(options.min_observations),
                           static_cast<std::size_t>(
                               std::ceil(options.min_view_fraction * static_cast<double>(n)))));
  const double bound =
      std::max(options.max_view_angle_deg * std::numbers::pi / 180.0, sorted[keep - 1]);
  for (std::size_t i = 0; i < n; ++i) {
    if (view[i] <= bound) chosen.push_back(i);
  }
  result->view_bound_deg = bound * 180.0 / std::numbers::pi;
  result->oblique = static_cast<int>(n - chosen.size());
  std::vector<PoseObservation> used;
  used.reserve(chosen.size());
  for (std::size_t i : chosen) used.push_back(observations[i]);
  return used;
}

// 4. One round of the bias model: each observation's offset from its contact point's projection
// to the centre of its imprint rendered under `pose` (0 where the render has no contact).
// `contact_px` (optional) receives each render's contact pixel count. Returns how many renders had
// no contact.
int BiasOffsets(const FisheyeCamera& camera, const Rigid3d& pose,
                const std::vector<PoseObservation>& used, const PoseOptions& options,
                const PoseScene& scene, std::vector<Eigen::Vector2d>* offsets,
                std::vector<int>* contact_px = nullptr) {
  const std::size_t n_used = used.size();
  const SurfaceMap map =
      SurfaceMap::Build(camera, pose, *scene.gel, scene.fins, options.surface_map);
  std::vector<char> empty(n_used, 0);
  auto work = [&](std::size_t begin, std::size_t end) {
    for (std::size_t i = begin; i < end; ++i) {
      const PoseObservation& o = used[i];
      const ProbeRender pr = RenderProbe(map, camera, pose * o.ball_center_sensor,
                                         options.ball_radius_mm, options.render);
      if (contact_px) (*contact_px)[i] = pr.contact_pixels;
      if (pr.contact_pixels == 0) {
        (*offsets)[i].setZero();
        empty[i] = 1;
        continue;
      }
      const Eigen::Vector2d centre =
          options.model_finder ? FinderCentroid(pr, scene.finder) : HullCentroid(pr);
      (*offsets)[i] = centre - camera.ProjectUnchecked(pose * o.contact_point_sensor);
    }
  };
  const std::size_t threads =
      std::min<std::size_t>(static_cast<std::size_t>(options.threads), n_used);
  std::vector<std::thread> pool;
  const std::size_t chunk = (n_used + threads - 1) / threads;
  for (std::size_t t = 1; t < threads; ++t) {
    pool.emplace_back(work, std::min(n_used, t * chunk), std::min(n_used, (t + 1) * chunk));
  }
  work(0, std::min(n_used, chunk));
  for (std::thread& t : pool) t.join();
  return static_cast<int>(std::count(empty.begin(), empty.end(), static_cast<char>(1)));
}

// 4b. The observations whose region is spread far beyond their rendered imprint, relative to the
// median observation (options.max_region_ratio), are removed from `used` and `offsets`; unless
// fewer than min_observations would remain. Returns how many were removed.
int DropSpread(const std::vector<int>& contact_px, const PoseOptions& options,
               std::vector<PoseObservation>* used, std::vector<Eigen::Vector2d>* offsets) {
  if (options.max_region_ratio <= 0.0) return 0;
  const std::size_t n = used->size();
  std::vector<double> ratio(n, 0.0), known;
  for (std::size_t i = 0; i < n; ++i) {
    if ((*used)[i].region_px > 0.0 && contact_px[i] > 0) {
      ratio[i] = (*used)[i].region_px / contact_px[i];
      known.push_back(ratio[i]);
    }
  }
  if (known.empty()) return 0;
  const double bound = options.max_region_ratio * Median(std::move(known));
  std::vector<PoseObservation> kept_obs;
  std::vector<Eigen::Vector2d> kept_offsets;
  for (std::size_t i = 0; i < n; ++i) {
    if (ratio[i] > bound) continue;
    kept_obs.push_back((*used)[i]);
    kept_offsets.push_back((*offsets)[i]);
  }
  if (kept_obs.size() < static_cast<std::size_t>(options.min_observations)) return 0;
  const int dropped = static_cast<int>(n - kept_obs.size());
  *used = std::move(kept_obs);
  *offsets = std::move(kept_offsets);
  return dropped;
}

}  // namespace

namespace {

// A refinement over one set of observations, with the bias model's rounds.
struct SubsetFit {
  PoseFit fit;
  std::vector<PoseObservation> used;  // after DropSpread
  int spread = 0, bias_rounds = 0, no_rendered_contact = 0;
  double mean_bias_px = 0.0;
};

// 3. Refinement over `used` from `start` without offsets; 4. the bias model: offsets from
// rendered imprints under the current pose, then refit (the spread ones left out after the first
// render).
SubsetFit FitSubset(const FisheyeCamera& camera, std::vector<PoseObservation> used,
                    const Rigid3d& start, const PoseOptions& options, const PoseScene& scene) {
  SubsetFit out;
  out.fit = RefineCamFromSensor(camera, used, {}, start, options);
  if (options.model_bias) {
    std::vector<Eigen::Vector2d> offsets(used.size(), Eigen::Vector2d::Zero());
    for (int round = 0; round < options.bias_rounds; ++round) {
      const Rigid3d pose = out.fit.cam_from_sensor;
      std::vector<int> contact_px(used.size(), 0);
      out.no_rendered_contact =
          BiasOffsets(camera, pose, used, options, scene, &offsets, &contact_px);
      if (round == 0) out.spread = DropSpread(contact_px, options, &used, &offsets);
      out.fit = RefineCamFromSensor(camera, used, offsets, pose, options);
      out.bias_rounds = round + 1;
      double sum = 0.0;
      for (const Eigen::Vector2d& b : offsets) sum += b.norm();
      out.mean_bias_px = sum / static_cast<double>(used.size());
    }
  }
  out.used = std::move(used);
  return out;
}

// 5. The view bound's check: when the bound left observations out and its fit's inliers scatter
// more than max_bound_rms_ratio times those of a fit over every observation, the bounded set's
// own centres are what is wrong (on tall fingers the face-on imprints near the base are the
// large, faint ones), and the fit over all replaces it. A fit over all that fails keeps the
// bounded one.
void CheckViewBound(const FisheyeCamera& camera, std::span<const PoseObservation> observations,
                    const Rigid3d& start, const PoseOptions& options, const PoseScene& scene,
                    SubsetFit* bounded, PoseResult* result) {
  if (result->oblique == 0 || options.max_bound_rms_ratio <= 0.0) return;
  try {
    SubsetFit all =
        FitSubset(camera, {observations.begin(), observations.end()}, start, options, scene);
    if (!(bounded->fit.rms_px > options.max_bound_rms_ratio * all.fit.rms_px)) return;
    *bounded = std::move(all);
    result->view_bound_released = true;
    result->oblique = 0;
    result->view_bound_deg = 90.0;
  } catch (const PoseError&) {
  }
}

}  // namespace

PoseResult EstimateCamFromSensor(const FisheyeCamera& camera,
                                 std::span<const PoseObservation> observations,
                                 const Rigid3d& nominal_cam_from_sensor, const PoseOptions& options,
                                 const PoseScene& scene) {
  const auto started = std::chrono::steady_clock::now();
  options.Check();
  CheckObservations(observations, options, scene);
  PoseResult result;
  EstimatePaperPose(camera, observations, nominal_cam_from_sensor, options, &result);
  const Rigid3d& start = result.paper_cam_from_sensor;
  SubsetFit best = FitSubset(camera, ChooseObservations(observations, start, options, &result),
                             start, options, scene);
  CheckViewBound(camera, observations, start, options, scene, &best, &result);
  const PoseFit& fit = best.fit;
  const std::size_t n_used = best.used.size();
  result.spread = best.spread;
  result.bias_rounds = best.bias_rounds;
  result.no_rendered_contact = best.no_rendered_contact;
  result.mean_bias_px = best.mean_bias_px;
  result.condition = fit.condition;
  if (!(fit.condition <= options.max_condition)) {
    throw PoseError("EstimateCamFromSensor: the " + std::to_string(n_used) +
                    " impressions do not pin the camera pose down (condition number " +
                    FormatCondition(fit.condition) + ", more than max_condition " +
                    FormatCondition(options.max_condition) +
                    "): their contact points are clustered or nearly on one line; probe over "
                    "more of the gel");
  }
  result.cam_from_sensor = fit.cam_from_sensor;
  result.rms_px = fit.rms_px;
  result.inliers = fit.inliers;
  result.outliers = static_cast<int>(n_used) - fit.inliers;
  for (std::size_t i = 0; i < n_used; ++i) {
    if (!fit.inlier[i]) result.outlier_probe_indices.push_back(best.used[i].probe_index);
  }
  result.seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  return result;
}

}  // namespace gs360
