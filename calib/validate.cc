#include "calib/validate.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <random>
#include <stdexcept>
#include <thread>

namespace gs360 {
namespace {

using Json = nlohmann::json;
constexpr double kRadToDeg = 180.0 / 3.14159265358979323846;
const char* const kTruths[] = {"rigid", "physical"};
// The three integrators on the MLP's slopes, then the diagnostic: the default integrator on the
// rigid render's exact slopes (separates integration error from slope error).
const char* const kMethods[] = {"heightfield", "discontinuity", "poisson", "render_slopes"};
constexpr int kMethodCount = 4;
constexpr int kRenderSlopes = 3;
constexpr IntegrationMethod kMethodIds[] = {IntegrationMethod::kHeightField,
                                            IntegrationMethod::kDiscontinuityAware,
                                            IntegrationMethod::kPoisson};

// Errors of one (truth, method) pair, per band.
struct BandErrors {
  std::vector<float> depth;        // mm, per pixel
  std::vector<float> normal;       // deg, per pixel
  std::vector<float> peak;         // mm, per probe: |reconstructed - true peak indentation|
  std::vector<float> peak_signed;  // mm, per probe: reconstructed - true (< 0: too shallow)
  std::int64_t probes = 0;
};
// Bands by index: the per-pixel loop only adds to a fixed table (no keys built per pixel).
const char* const kBands[] = {"all",        "height:base", "height:middle",
                              "height:tip", "view:<30",    "view:30-50",
                              "view:>50",   "fins:near",   "fins:far"};
constexpr int kBandCount = 9;
enum Band : int { kAll = 0, kHeightBase = 1, kViewLow = 4, kFinsNear = 7 };
constexpr int kTruthCount = 2;
// Indexed [truth][method][band].
struct Accumulator {
  std::vector<BandErrors> cells =
      std::vector<BandErrors>(static_cast<std::size_t>(kTruthCount * kMethodCount * kBandCount));
  BandErrors& at(int truth, int method, int band) {
    return cells[static_cast<std::size_t>((truth * kMethodCount + method) * kBandCount + band)];
  }
};

double Mean(const std::vector<float>& v) {
  if (v.empty()) return std::numeric_limits<double>::quiet_NaN();
  double s = 0.0;
  for (float x : v) s += x;
  return s / static_cast<double>(v.size());
}

double Percentile(std::vector<float> v, double q) {
  if (v.empty()) return std::numeric_limits<double>::quiet_NaN();
  const std::size_t k =
      std::min(v.size() - 1, static_cast<std::size_t>(q * static_cast<double>(v.size())));
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
  return v[k];
}

Json Number(double v) {
  return std::isfinite(v) ? Json(v) : Json(nullptr);
}

int ViewBand(double angle_rad) {
  const double deg = angle_rad * kRadToDeg;
  return kViewLow + (deg < 30.0 ? 0 : (deg <= 50.0 ? 1 : 2));
}

double AngleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::atan2(a.cross(b).norm(), a.dot(b)) * kRadToDeg;
}

}  // namespace

void ValidationOptions::Check() const {
  if (max_probes < 1) {
    throw std::invalid_argument("ValidationOptions.max_probes must be >= 1, got " +
                                std::to_string(max_probes));
  }
  if (!(fin_near_mm >= 0.0)) {
    throw std::invalid_argument("ValidationOptions.fin_near_mm must be >= 0, got " +
                                std::to_string(fin_near_mm));
  }
  if (examples < 0) {
    throw std::invalid_argument("ValidationOptions.examples must be >= 0, got " +
                                std::to_string(examples));
  }
  if (threads < 1 || threads > 64) {
    throw std::invalid_argument("ValidationOptions.threads must be in [1, 64], got " +
                                std::to_string(threads));
  }
}

ValidationResult Validate(const Reconstructor& rec, const std::vector<int>& held_out_all,
                          const ValidationProbeLoader& load, double ball_radius,
                          double gel_height_mm, const ValidationTruth* truth,
                          const ValidationOptions& options) {
  options.Check();
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<int> held_out = held_out_all;
  if (static_cast<int>(held_out.size()) > options.max_probes) {
    std::mt19937_64 rng(0x7e57ULL);
    for (std::size_t i = held_out.size(); i > 1; --i) {
      std::swap(held_out[i - 1], held_out[static_cast<std::size_t>(rng() % i)]);
    }
    held_out.resize(static_cast<std::size_t>(options.max_probes));
    std::sort(held_out.begin(), held_out.end());
  }
  const SurfaceMap& map = rec.map();
  const Rigid3d& cam_from_sensor = map.cam_from_sensor();
  const Rigid3d sensor_from_cam = cam_from_sensor.Inverse();
  const int n_truths = truth != nullptr ? 2 : 1;
  IntegrationOptions methods[kMethodCount];
  const IntegrationMethod default_method = rec.options().integration.method;
  int default_index = 0, poisson_index = 0;
  for (int m = 0; m < kMethodCount; ++m) {
    methods[m] = rec.options().integration;
    if (m != kRenderSlopes) methods[m].method = kMethodIds[m];
    if (m != kRenderSlopes && kMethodIds[m] == default_method) default_index = m;
    if (m != kRenderSlopes && kMethodIds[m] == IntegrationMethod::kPoisson) poisson_index = m;
  }

  struct ThreadState {
    Accumulator acc;
    std::int64_t missed = 0, contact_pixels = 0, uncovered = 0;
    std::int64_t roi_pixels = 0, roi_max = 0, rois = 0;
    double mlp_s = 0.0, integration_s[kMethodCount] = {};
    std::vector<std::pair<int, ValidationExample>> examples;
    std::vector<std::pair<int, std::pair<Eigen::Vector3d, double>>> probe_errors;
  };
  const int threads =
      std::max(1, std::min<int>(options.threads, static_cast<int>(held_out.size())));
  std::vector<ThreadState> states(static_cast<std::size_t>(threads));
  // Examples: evenly spread over the held-out probes.
  std::vector<int> example_probes;
  for (int k = 0; k < options.examples && !held_out.empty(); ++k) {
    example_probes.push_back(held_out[static_cast<std::size_t>(k) * held_out.size() /
                                      static_cast<std::size_t>(options.examples)]);
  }

  auto work = [&](int thread) {
    ThreadState& st = states[static_cast<std::size_t>(thread)];
    for (std::size_t k = static_cast<std::size_t>(thread); k < held_out.size();
         k += static_cast<std::size_t>(threads)) {
      const ValidationProbe probe = load(held_out[k], thread);
      const Eigen::Vector3d c_cam = cam_from_sensor * probe.ball_center_sensor;
      const ProbeRender render = RenderProbe(map, rec.camera(), c_cam, ball_radius);
      if (render.contact_pixels == 0) continue;
      const double z = probe.contact_point_sensor.z();
      const int height =
          kHeightBase + (z < gel_height_mm / 3.0 ? 0 : (z < 2.0 * gel_height_mm / 3.0 ? 1 : 2));
      const bool near_fins =
          std::min(std::abs(probe.contact_point_sensor.x()),
                   std::abs(probe.contact_point_sensor.y())) < options.fin_near_mm;
      const int fins = near_fins ? kFinsNear : kFinsNear + 1;
      std::unique_ptr<ProbeSurfaceTruth> physical;
      if (truth != nullptr) physical = truth->ForProbe(probe.ball_center_sensor, ball_radius);

      const cv::Mat diff = rec.Difference(probe.frame, probe.reference);
      const std::vector<ContactRegion> regions =
          DetectContactRegions(diff, rec.options().detection);
      // The region holding the rendered contact's centroid (or the nearest one).
      const ContactRegion* region = nullptr;
      double best = std::numeric_limits<double>::infinity();
      for (const ContactRegion& r : regions) {
        const cv::Rect& b = r.blob;
        const double du = std::max({b.x - render.contact_centroid.x(), 0.0,
                                    render.contact_centroid.x() - (b.x + b.width)});
        const double dv = std::max({b.y - render.contact_centroid.y(), 0.0,
                                    render.contact_centroid.y() - (b.y + b.height)});
        const double dist = std::hypot(du, dv);
        if (dist < best) best = dist, region = &r;
      }
      if (region != nullptr && best > 10.0) region = nullptr;
      if (region == nullptr || region->roi.width < 3 || region->roi.height < 3) ++st.missed;

      RegionReconstruction recs[kMethodCount];
      cv::Mat slopes;
      if (region != nullptr && region->roi.width >= 3 && region->roi.height >= 3) {
        const std::int64_t area = region->roi.area();
        st.roi_pixels += area;
        st.roi_max = std::max(st.roi_max, area);
        ++st.rois;
        const auto tm = std::chrono::steady_clock::now();
        slopes = rec.PredictSlopes(diff, region->roi);
        st.mlp_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - tm).count();
        cv::Mat oracle(region->roi.size(), CV_32FC2, cv::Scalar::all(0));
        const cv::Rect both = region->roi & render.roi;
        for (int v = both.y; v < both.y + both.height; ++v) {
          for (int u = both.x; u < both.x + both.width; ++u) {
            const int ry = v - render.roi.y, rx = u - render.roi.x;
            if (!render.contact.at<std::uint8_t>(ry, rx)) continue;
            oracle.at<cv::Vec2f>(v - region->roi.y, u - region->roi.x) =
                cv::Vec2f(render.gx.at<float>(ry, rx), render.gy.at<float>(ry, rx));
          }
        }
        for (int m = 0; m < kMethodCount; ++m) {
          recs[m] = rec.IntegrateSlopes(m == kRenderSlopes ? oracle : slopes, *region, methods[m]);
          st.integration_s[m] += recs[m].integration_seconds;
        }
      }
      const cv::Rect roi = region != nullptr ? region->roi : cv::Rect();
      const double truth_peak[2] = {render.max_indentation_mm,
                                    physical ? physical->PeakIndentation() : 0.0};
      double probe_error_sum = 0.0;
      std::int64_t probe_error_n = 0;
      for (int y = 0; y < render.roi.height; ++y) {
        for (int x = 0; x < render.roi.width; ++x) {
          if (!render.contact.at<std::uint8_t>(y, x)) continue;
          const int u = render.roi.x + x, v = render.roi.y + y;
          ++st.contact_pixels;
          const Eigen::Vector3d d = map.ray(u, v);
          const Eigen::Vector3d x_r = render.rho.at<double>(y, x) * d;
          const Eigen::Vector3d n_r = (c_cam - x_r) / ball_radius;
          const bool inside = roi.contains(cv::Point(u, v));
          if (!inside) ++st.uncovered;
          const int view = ViewBand(map.view_angle(u, v));
          for (int m = 0; m < kMethodCount; ++m) {
            double rho = map.rho0(u, v);
            Eigen::Vector3d n = map.normal0(u, v);
            if (inside) {
              const double r = recs[m].rho.at<double>(v - roi.y, u - roi.x);
              const cv::Vec3d nn = recs[m].normals.at<cv::Vec3d>(v - roi.y, u - roi.x);
              if (std::isfinite(r)) rho = r;
              if (std::isfinite(nn[0])) n = Eigen::Vector3d(nn[0], nn[1], nn[2]);
            }
            const Eigen::Vector3d x_m = rho * d;
            for (int t = 0; t < n_truths; ++t) {
              double depth_err, normal_err;
              if (t == 0) {
                depth_err = std::abs((x_m - x_r).dot(n_r));
                normal_err = AngleDeg(n, n_r);
              } else {
                Eigen::Vector3d n_t;
                depth_err = physical->Distance(sensor_from_cam * x_m, &n_t);
                normal_err = AngleDeg(sensor_from_cam.RotateDirection(n), n_t);
              }
              if (m == 0 && t == n_truths - 1) probe_error_sum += depth_err, ++probe_error_n;
              for (const int band : {static_cast<int>(kAll), height, view, fins}) {
                BandErrors& e = st.acc.at(t, m, band);
                e.depth.push_back(static_cast<float>(depth_err));
                e.normal.push_back(static_cast<float>(normal_err));
              }
            }
          }
        }
      }
      for (int m = 0; m < kMethodCount; ++m) {
        const double peak = roi.empty() ? 0.0 : recs[m].peak_indentation_mm;
        for (int t = 0; t < n_truths; ++t) {
          for (const int band : {static_cast<int>(kAll), height, fins}) {
            BandErrors& e = st.acc.at(t, m, band);
            e.peak.push_back(static_cast<float>(std::abs(peak - truth_peak[t])));
            e.peak_signed.push_back(static_cast<float>(peak - truth_peak[t]));
            ++e.probes;
          }
        }
      }
      if (probe_error_n > 0) {
        st.probe_errors.push_back(
            {held_out[k],
             {probe.contact_point_sensor, probe_error_sum / static_cast<double>(probe_error_n)}});
      }
      if (std::find(example_probes.begin(), example_probes.end(), held_out[k]) !=
              example_probes.end() &&
          !roi.empty()) {
        ValidationExample ex;
        ex.plan_index = held_out[k];
        ex.recon_method = kMethods[default_index];
        const cv::Rect box = roi | render.roi;
        const cv::Rect clipped = box & cv::Rect(0, 0, probe.frame.cols, probe.frame.rows);
        ex.frame_roi = probe.frame(clipped).clone();
        ex.truth_depth = cv::Mat(clipped.size(), CV_64F, cv::Scalar::all(0.0));
        ex.recon_depth = ex.truth_depth.clone();
        ex.poisson_depth = ex.truth_depth.clone();
        for (int v = clipped.y; v < clipped.y + clipped.height; ++v) {
          for (int u = clipped.x; u < clipped.x + clipped.width; ++u) {
            if (!map.visible(u, v)) continue;
            const double cosine = std::abs(map.ray(u, v).dot(map.normal0(u, v)));
            if (render.roi.contains(cv::Point(u, v))) {
              const double r = render.rho.at<double>(v - render.roi.y, u - render.roi.x);
              if (std::isfinite(r)) {
                ex.truth_depth.at<double>(v - clipped.y, u - clipped.x) =
                    (map.rho0(u, v) - r) * cosine;
              }
            }
            if (roi.contains(cv::Point(u, v))) {
              const double a = recs[default_index].indentation.at<double>(v - roi.y, u - roi.x);
              const double b = recs[poisson_index].indentation.at<double>(v - roi.y, u - roi.x);
              if (std::isfinite(a)) ex.recon_depth.at<double>(v - clipped.y, u - clipped.x) = a;
              if (std::isfinite(b)) ex.poisson_depth.at<double>(v - clipped.y, u - clipped.x) = b;
            }
          }
        }
        st.examples.push_back({held_out[k], std::move(ex)});
      }
    }
  };
  std::vector<std::thread> pool;
  for (int t = 1; t < threads; ++t) pool.emplace_back(work, t);
  work(0);
  for (auto& th : pool) th.join();

  // Merge in thread order (deterministic for a thread count).
  Accumulator acc;
  ValidationResult result;
  std::int64_t missed = 0, contact_pixels = 0, uncovered = 0, roi_pixels = 0, roi_max = 0, rois = 0;
  double mlp_s = 0.0, integ_s[kMethodCount] = {};
  std::vector<std::pair<int, ValidationExample>> examples;
  std::vector<std::pair<int, std::pair<Eigen::Vector3d, double>>> probe_errors;
  for (ThreadState& st : states) {
    for (std::size_t i = 0; i < st.acc.cells.size(); ++i) {
      const BandErrors& e = st.acc.cells[i];
      BandErrors& dst = acc.cells[i];
      dst.depth.insert(dst.depth.end(), e.depth.begin(), e.depth.end());
      dst.normal.insert(dst.normal.end(), e.normal.begin(), e.normal.end());
      dst.peak.insert(dst.peak.end(), e.peak.begin(), e.peak.end());
      dst.peak_signed.insert(dst.peak_signed.end(), e.peak_signed.begin(), e.peak_signed.end());
      dst.probes += e.probes;
    }
    missed += st.missed;
    contact_pixels += st.contact_pixels;
    uncovered += st.uncovered;
    roi_pixels += st.roi_pixels;
    roi_max = std::max(roi_max, st.roi_max);
    rois += st.rois;
    mlp_s += st.mlp_s;
    for (int m = 0; m < kMethodCount; ++m) integ_s[m] += st.integration_s[m];
    for (auto& e : st.examples) examples.push_back(std::move(e));
    for (auto& e : st.probe_errors) probe_errors.push_back(e);
  }
  std::sort(examples.begin(), examples.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  std::sort(probe_errors.begin(), probe_errors.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  for (auto& e : examples) result.examples.push_back(std::move(e.second));
  for (auto& e : probe_errors) result.probe_errors.push_back(e.second);

  Json results = Json::object();
  for (int t = 0; t < n_truths; ++t) {
    for (int m = 0; m < kMethodCount; ++m) {
      for (int b = 0; b < kBandCount; ++b) {
        const BandErrors& e = acc.at(t, m, b);
        if (e.depth.empty() && e.probes == 0) continue;  // a band no probe fell in
        results[kTruths[t]][kMethods[m]][kBands[b]] =
            Json{{"pixels", e.depth.size()},
                 {"probes", e.probes},
                 {"mean_mm", Number(Mean(e.depth))},
                 {"p95_mm", Number(Percentile(e.depth, 0.95))},
                 {"median_normal_deg", Number(Percentile(e.normal, 0.5))},
                 {"peak_error_mm", Number(Mean(e.peak))},
                 {"peak_bias_mm", Number(Mean(e.peak_signed))}};
      }
    }
  }
  const double evaluated = static_cast<double>(held_out.size());
  Json ms_per_probe{{"mlp", evaluated > 0 ? 1000.0 * mlp_s / evaluated : 0.0}};
  for (int m = 0; m < kMethodCount; ++m) {
    if (m == kRenderSlopes) continue;
    ms_per_probe[std::string("integration_") + kMethods[m]] =
        evaluated > 0 ? 1000.0 * integ_s[m] / evaluated : 0.0;
  }
  result.report = Json{
      {"probes_held_out", held_out_all.size()},
      {"probes_evaluated", held_out.size()},
      {"probes_missed", missed},
      {"contact_pixels", contact_pixels},
      {"contact_pixels_outside_roi", uncovered},
      {"roi_pixels_mean",
       rois > 0 ? static_cast<double>(roi_pixels) / static_cast<double>(rois) : 0.0},
      {"roi_pixels_max", roi_max},
      {"truths", n_truths == 2 ? Json{"rigid", "physical"} : Json{"rigid"}},
      {"truth_description", truth != nullptr ? truth->Describe() : std::string()},
      {"methods", {"heightfield", "discontinuity", "poisson"}},
      {"diagnostics", {"render_slopes"}},
      {"default_method", std::string(ToString(default_method))},
      {"results", results},
      {"ms_per_probe", ms_per_probe},
      {"seconds", std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count()},
  };
  return result;
}

}  // namespace gs360
