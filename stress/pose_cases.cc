// Pose from impressions at its edges: few, clustered, collinear, outlying, oblique, non-finite.
// Observations are made here from a known camera pose (projections of points on the default
// cylinder plus noise), so each case knows the truth and runs in milliseconds.

#include <cmath>
#include <numbers>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "calib/pose.h"
#include "geometry/shapes.h"
#include "rig/rig_config.h"
#include "stress/stress_cases.h"

namespace gs360::stress {
namespace {

constexpr double kDeg = std::numbers::pi / 180.0;

Rigid3d NominalPose() {
  const RigConfig rig;
  return rig.cam_from_sensor();
}

struct PoseScenario {
  FisheyeCamera camera;
  Rigid3d nominal;  // what calibration starts from (the rig's CAD pose)
  Rigid3d truth;    // what the observations were made with
  std::shared_ptr<const RevolutionProfile> profile;
  std::mt19937_64 rng;
  double noise_px = 0.3;

  explicit PoseScenario(std::uint64_t seed, const SensorShapeOptions& shape = {})
      : nominal(NominalPose()), profile(MakeProfile(shape)), rng(seed) {
    // About as far from the CAD pose as a real mount is (the virtual rig's default).
    truth = Rigid3d::FromAxisAngle(Eigen::Vector3d(0.3, -0.8, 0.5).normalized(), 1.0 * kDeg,
                                   Eigen::Vector3d(0.2, -0.1, 0.15)) *
            nominal;
  }

  // The observation of the surface point at profile parameter t and azimuth phi, or false when
  // the camera does not see it.
  bool Observe(double t, double phi, PoseObservation* o) {
    o->contact_point_sensor = profile->SurfacePoint(t, phi);
    o->contact_normal_sensor = profile->SurfaceNormal(t, phi);
    o->ball_center_sensor = o->contact_point_sensor + 2.0 * o->contact_normal_sensor;
    const auto px = camera.CamToPixel(truth * o->contact_point_sensor);
    if (!px || !camera.InImage(*px)) return false;
    std::normal_distribution<double> noise(0.0, noise_px);
    o->centroid_px = *px + Eigen::Vector2d(noise(rng), noise(rng));
    return ObservationViewAngle(*o, truth) < 85.0 * kDeg;
  }

  // `count` observations at t in [t0, t1], phi in [phi0, phi1], uniformly.
  std::vector<PoseObservation> Draw(int count, double t0, double t1, double phi0, double phi1) {
    std::uniform_real_distribution<double> t(t0, t1), phi(phi0, phi1);
    std::vector<PoseObservation> out;
    for (int guard = 0; static_cast<int>(out.size()) < count && guard < 100 * count; ++guard) {
      PoseObservation o;
      o.probe_index = static_cast<int>(out.size());
      if (Observe(t(rng), phi(rng), &o)) out.push_back(o);
    }
    return out;
  }

  std::vector<PoseObservation> Spread(int count) {
    return Draw(count, 0.05, 0.95, 0.0, 2.0 * std::numbers::pi);
  }
};

PoseOptions FastOptions() {
  PoseOptions o;
  o.model_bias = false;  // no gel mesh: these cases are about the fit, not the imprint model
  o.threads = 1;
  return o;
}

struct PoseOffset {
  double rotation_deg = 0.0, centre_mm = 0.0;
};
PoseOffset Compare(const Rigid3d& a, const Rigid3d& b) {
  // Camera centres in the sensor frame: the translation part that a user would measure.
  const Eigen::Vector3d ca = a.Inverse().translation, cb = b.Inverse().translation;
  return {RotationDifferenceRad(a, b) / kDeg, (ca - cb).norm()};
}

// Runs the estimate; true with `observed` filled when it returns within the bounds, or when it
// throws PoseError and `error_ok`.
bool Within(PoseScenario& s, const std::vector<PoseObservation>& obs, const PoseOptions& options,
            double max_deg, double max_mm, bool error_ok, std::string* observed) {
  try {
    const PoseResult r = EstimateCamFromSensor(s.camera, obs, s.nominal, options);
    const PoseOffset e = Compare(r.cam_from_sensor, s.truth);
    *observed = Format(
        "%zu impressions: %.4f deg, %.4f mm off; condition %.3g, rms %.2f px, "
        "%d outliers, %d oblique left out",
        obs.size(), e.rotation_deg, e.centre_mm, r.condition, r.rms_px, r.outliers, r.oblique);
    return e.rotation_deg <= max_deg && e.centre_mm <= max_mm;
  } catch (const PoseError& e) {
    *observed = Format("%zu impressions: PoseError: %s", obs.size(), e.what());
    return error_ok;
  }
}

bool ErrorMentions(PoseScenario& s, const std::vector<PoseObservation>& obs,
                   const PoseOptions& options, const std::string& needle, std::string* observed) {
  try {
    const PoseResult r = EstimateCamFromSensor(s.camera, obs, s.nominal, options);
    const PoseOffset e = Compare(r.cam_from_sensor, s.truth);
    *observed = Format("no error: %.4f deg, %.4f mm off, condition %.3g", e.rotation_deg,
                       e.centre_mm, r.condition);
    return false;
  } catch (const std::exception& e) {
    *observed = e.what();
    return std::string(e.what()).find(needle) != std::string::npos;
  }
}

StressCase Spread() {
  return {"pose", "2,000 impressions spread over the gel, 0.3 px noise",
          "within 0.02 deg and 0.02 mm of the truth",
          [](const StressContext& c, std::string* observed) {
            PoseScenario s(c.seed);
            return Within(s, s.Spread(2000), FastOptions(), 0.02, 0.02, false, observed);
          }};
}

StressCase Few() {
  return {"pose", "6 impressions (the fewest allowed)", "within 0.5 deg and 0.5 mm, or a PoseError",
          [](const StressContext& c, std::string* observed) {
            PoseScenario s(c.seed);
            return Within(s, s.Spread(6), FastOptions(), 0.5, 0.5, true, observed);
          }};
}

StressCase TooFew() {
  return {"pose", "5 impressions", "PoseError: need at least 6",
          [](const StressContext& c, std::string* observed) {
            PoseScenario s(c.seed);
            return ErrorMentions(s, s.Spread(5), FastOptions(), "need at least 6", observed);
          }};
}

StressCase Clustered() {
  return {"pose", "200 impressions within 1 mm of one point",
          "PoseError naming the condition number, or within 0.5 deg and 0.5 mm",
          [](const StressContext& c, std::string* observed) {
            PoseScenario s(c.seed);
            // 1 mm on a 30 mm profile of radius 10: dt ~ 1/38, dphi ~ 0.1 rad.
            const auto obs = s.Draw(200, 0.50, 0.526, 0.70, 0.80);
            const bool ok = Within(s, obs, FastOptions(), 0.5, 0.5, false, observed);
            return ok || observed->find("condition number") != std::string::npos;
          }};
}

StressCase Collinear() {
  return {"pose", "200 impressions along one line of the gel (0.01 mm wide)",
          "PoseError naming the condition number",
          [](const StressContext& c, std::string* observed) {
            PoseScenario s(c.seed);
            // One generatrix of the cylinder's side: z varies, the azimuth 0.0003 rad (0.003 mm).
            const auto obs = s.Draw(200, 0.05, 0.6, 1.0, 1.0003);
            return ErrorMentions(s, obs, FastOptions(), "condition number", observed);
          }};
}

StressCase Outliers() {
  return {"pose", "2,000 impressions, 20 % of them 10-40 px off",
          "within 0.02 deg and 0.02 mm; the outliers found",
          [](const StressContext& c, std::string* observed) {
            PoseScenario s(c.seed);
            auto obs = s.Spread(2000);
            std::uniform_real_distribution<double> angle(0.0, 2.0 * std::numbers::pi), len(10, 40);
            for (std::size_t i = 0; i < obs.size(); i += 5) {
              const double a = angle(s.rng), l = len(s.rng);
              obs[i].centroid_px += l * Eigen::Vector2d(std::cos(a), std::sin(a));
            }
            return Within(s, obs, FastOptions(), 0.02, 0.02, false, observed);
          }};
}

// Oblique imprints' centres move toward their near side (calib/pose.h): here up to 4 px toward
// the image centre, from 0 at 50 deg to 4 px at 85 deg. The default finger is seen at 65 deg at
// most; a finger 90 mm tall is seen above 80 deg at the top of its side.
StressCase Grazing() {
  return {"pose", "1,000 impressions on a 90 mm finger, 300 seen above 80 deg and biased 3-4 px",
          "within 0.05 deg and 0.05 mm (the view bound leaves the oblique ones out)",
          [](const StressContext& c, std::string* observed) {
            SensorShapeOptions tall;
            tall.cylinder.height = 90.0;
            PoseScenario s(c.seed, tall);
            std::vector<PoseObservation> obs, grazing;
            for (const PoseObservation& o : s.Draw(6000, 0.0, 1.0, 0.0, 2.0 * std::numbers::pi)) {
              const bool steep = ObservationViewAngle(o, s.truth) > 80.0 * kDeg;
              if (steep && grazing.size() < 300) grazing.push_back(o);
              if (!steep && obs.size() < 700) obs.push_back(o);
            }
            obs.insert(obs.end(), grazing.begin(), grazing.end());
            const Eigen::Vector2d centre(s.camera.intrinsics().cx, s.camera.intrinsics().cy);
            for (PoseObservation& o : obs) {
              const double view = ObservationViewAngle(o, s.truth) / kDeg;
              if (view <= 50.0) continue;
              const Eigen::Vector2d to_centre = (centre - o.centroid_px).normalized();
              o.centroid_px += 4.0 * (view - 50.0) / 35.0 * to_centre;
            }
            const bool ok = Within(s, obs, FastOptions(), 0.05, 0.05, false, observed);
            *observed += Format(" (%zu above 80 deg)", grazing.size());
            return ok && grazing.size() == 300;
          }};
}

StressCase NonFinite() {
  return {"pose", "one impression centre NaN", "std::invalid_argument naming the observation",
          [](const StressContext& c, std::string* observed) {
            PoseScenario s(c.seed);
            auto obs = s.Spread(100);
            obs[42].centroid_px.x() = std::nan("");
            return ErrorMentions(s, obs, FastOptions(), "observation 42", observed);
          }};
}

}  // namespace

std::vector<StressCase> PoseCases() {
  return {Spread(), Few(), TooFew(), Clustered(), Collinear(), Outliers(), Grazing(), NonFinite()};
}

}  // namespace gs360::stress
