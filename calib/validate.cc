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
const auto& kBands = kValidationBands;
constexpr int kBandCount = static_cast<int>(kValidationBands.size());
enum Band : int { kAll = 0, kHeightBase = 1, kViewLow = 4, kFinsNear = 7 };
constexpr int kTruthCount = 2;
// Indexed [truth][method][band].
struct Accumulator {
  std::vector<BandErrors> cells =
      std::vector<BandErrors>(static_cast<std::size_t>(kTruthCount * kMethodCount * kBandCount));
  BandErrors& at(int truth, int method, int band) {
    return cells[static_cast<std::size_t>((truth * kMethodCount + method) * kBandCount + band)];
  }
  const BandErrors& at(int truth, int method, int band) const {
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

namespace {

// One worker's results, merged in thread order.
struct ThreadState {
  Accumulator acc;
  std::int64_t missed = 0, contact_pixels = 0, uncovered = 0;
  std::int64_t roi_pixels = 0, roi_max = 0, rois = 0;
  double mlp_s = 0.0, integration_s[kMethodCount] = {};
  std::vector<std::pair<int, ValidationExample>> examples;
  std::vector<std::pair<int, std::pair<Eigen::Vector3d, double>>> probe_errors;
  std::vector<std::pair<int, Json>> probe_peaks;
};

// At most max_probes of the held-out probes: a seeded subset beyond, in plan order.
std::vector<int> SelectProbes(const std::vector<int>& held_out_all, int max_probes) {
  std::vector<int> held_out = held_out_all;
  if (static_cast<int>(held_out.size()) > max_probes) {
    std::mt19937_64 rng(0x7e57ULL);
    for (std::size_t i = held_out.size(); i > 1; --i) {
      std::swap(held_out[i - 1], held_out[static_cast<std::size_t>(rng() % i)]);
    }
    held_out.resize(static_cast<std::size_t>(max_probes));
    std::sort(held_out.begin(), held_out.end());
  }
  return held_out;
}

// Examples: evenly spread over the held-out probes.
std::vector<int> ExampleProbes(const std::vector<int>& held_out, int examples) {
  std::vector<int> example_probes;
  for (int k = 0; k < examples && !held_out.empty(); ++k) {
    example_probes.push_back(held_out[static_cast<std::size_t>(k) * held_out.size() /
                                      static_cast<std::size_t>(examples)]);
  }
  return example_probes;
}

// The region holding the rendered contact's centroid (or the nearest one, at most 10 px away);
// null when there is none.
const ContactRegion* MatchRegion(const std::vector<ContactRegion>& regions,
                                 const ProbeRender& render) {
  const ContactRegion* region = nullptr;
  double best = std::numeric_limits<double>::infinity();
  for (const ContactRegion& r : regions) {
    const cv::Rect& b = r.blob;
    const double du = std::max(
        {b.x - render.contact_centroid.x(), 0.0, render.contact_centroid.x() - (b.x + b.width)});
    const double dv = std::max(
        {b.y - render.contact_centroid.y(), 0.0, render.contact_centroid.y() - (b.y + b.height)});
    const double dist = std::hypot(du, dv);
    if (dist < best) best = dist, region = &r;
  }
  if (region != nullptr && best > 10.0) region = nullptr;
  return region;
}

// The rigid render's exact slopes (CV_32FC2) over `roi`, 0 outside its contact.
cv::Mat OracleSlopes(const cv::Rect& roi, const ProbeRender& render) {
  cv::Mat oracle(roi.size(), CV_32FC2, cv::Scalar::all(0));
  const cv::Rect both = roi & render.roi;
  for (int v = both.y; v < both.y + both.height; ++v) {
    for (int u = both.x; u < both.x + both.width; ++u) {
      const int ry = v - render.roi.y, rx = u - render.roi.x;
      if (!render.contact.at<std::uint8_t>(ry, rx)) continue;
      oracle.at<cv::Vec2f>(v - roi.y, u - roi.x) =
          cv::Vec2f(render.gx.at<float>(ry, rx), render.gy.at<float>(ry, rx));
    }
  }
  return oracle;
}

// One probe in evaluation: the rigid render, the probe's bands, its physical truth, and every
// method's reconstruction of the region matched to it.
struct ProbeCase {
  Eigen::Vector3d c_cam;
  ProbeRender render;
  int height = 0, fins = 0;
  std::unique_ptr<ProbeSurfaceTruth> physical;
  RegionReconstruction recs[kMethodCount];
  cv::Rect roi;  // the matched region's (empty: none)
};

// Evaluates held-out probes into a ThreadState; const, so workers share one.
class ProbeEvaluator {
 public:
  ProbeEvaluator(const Reconstructor& rec, double ball_radius, double gel_height_mm,
                 const ValidationTruth* truth, const ValidationOptions& options,
                 std::vector<int> example_probes)
      : rec_(rec),
        map_(rec.map()),
        cam_from_sensor_(map_.cam_from_sensor()),
        sensor_from_cam_(cam_from_sensor_.Inverse()),
        ball_radius_(ball_radius),
        gel_height_mm_(gel_height_mm),
        truth_(truth),
        n_truths_(truth != nullptr ? 2 : 1),
        fin_near_mm_(options.fin_near_mm),
        example_probes_(std::move(example_probes)) {
    const IntegrationMethod default_method = rec.options().integration.method;
    for (int m = 0; m < kMethodCount; ++m) {
      methods_[m] = rec.options().integration;
      if (m != kRenderSlopes) methods_[m].method = kMethodIds[m];
      if (m != kRenderSlopes && kMethodIds[m] == default_method) default_index_ = m;
      if (m != kRenderSlopes && kMethodIds[m] == IntegrationMethod::kPoisson) poisson_index_ = m;
    }
  }

  int n_truths() const { return n_truths_; }

  // Adds the errors of the probe at `plan_index` to *st.
  void Evaluate(int plan_index, const ValidationProbe& probe, ThreadState* st) const {
    ProbeCase pc;
    pc.c_cam = cam_from_sensor_ * probe.ball_center_sensor;
    pc.render = RenderProbe(map_, rec_.camera(), pc.c_cam, ball_radius_);
    if (pc.render.contact_pixels == 0) return;
    const double z = probe.contact_point_sensor.z();
    pc.height =
        kHeightBase + (z < gel_height_mm_ / 3.0 ? 0 : (z < 2.0 * gel_height_mm_ / 3.0 ? 1 : 2));
    const bool near_fins = std::min(std::abs(probe.contact_point_sensor.x()),
                                    std::abs(probe.contact_point_sensor.y())) < fin_near_mm_;
    pc.fins = near_fins ? kFinsNear : kFinsNear + 1;
    if (truth_ != nullptr) pc.physical = truth_->ForProbe(probe.ball_center_sensor, ball_radius_);

    const cv::Mat diff = rec_.Difference(probe.frame, probe.reference);
    const std::vector<ContactRegion> regions = DetectContactRegions(diff, rec_.options().detection);
    const ContactRegion* region = MatchRegion(regions, pc.render);
    if (region == nullptr || region->roi.width < 3 || region->roi.height < 3) ++st->missed;
    if (region != nullptr && region->roi.width >= 3 && region->roi.height >= 3) {
      Reconstruct(diff, *region, &pc, st);
    }
    pc.roi = region != nullptr ? region->roi : cv::Rect();
    const auto [probe_error_sum, probe_error_n] = AddPixelErrors(pc, st);
    AddPeakErrors(pc, st);
    st->probe_peaks.push_back({plan_index, PeakRow(plan_index, probe, pc)});
    if (probe_error_n > 0) {
      st->probe_errors.push_back(
          {plan_index,
           {probe.contact_point_sensor, probe_error_sum / static_cast<double>(probe_error_n)}});
    }
    if (std::find(example_probes_.begin(), example_probes_.end(), plan_index) !=
            example_probes_.end() &&
        !pc.roi.empty()) {
      st->examples.push_back({plan_index, MakeExample(plan_index, probe, pc)});
    }
  }

 private:
  // Every method's reconstruction of the region: the MLP's slopes, and the render's for the
  // diagnostic.
  void Reconstruct(const cv::Mat& diff, const ContactRegion& region, ProbeCase* pc,
                   ThreadState* st) const {
    const std::int64_t area = region.roi.area();
    st->roi_pixels += area;
    st->roi_max = std::max(st->roi_max, area);
    ++st->rois;
    const auto tm = std::chrono::steady_clock::now();
    const cv::Mat slopes = rec_.PredictSlopes(diff, region.roi);
    st->mlp_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - tm).count();
    const cv::Mat oracle = OracleSlopes(region.roi, pc->render);
    for (int m = 0; m < kMethodCount; ++m) {
      pc->recs[m] = rec_.IntegrateSlopes(m == kRenderSlopes ? oracle : slopes, region, methods_[m]);
      st->integration_s[m] += pc->recs[m].integration_seconds;
    }
  }

  // Depth and normal errors of every contact pixel, per truth, method and band. Returns the sum
  // and count of the first method's depth errors against the last truth (the probe's error).
  std::pair<double, std::int64_t> AddPixelErrors(const ProbeCase& pc, ThreadState* st) const {
    const ProbeRender& render = pc.render;
    const cv::Rect& roi = pc.roi;
    double probe_error_sum = 0.0;
    std::int64_t probe_error_n = 0;
    for (int y = 0; y < render.roi.height; ++y) {
      for (int x = 0; x < render.roi.width; ++x) {
        if (!render.contact.at<std::uint8_t>(y, x)) continue;
        const int u = render.roi.x + x, v = render.roi.y + y;
        ++st->contact_pixels;
        const Eigen::Vector3d d = map_.ray(u, v);
        const Eigen::Vector3d x_r = render.rho.at<double>(y, x) * d;
        const Eigen::Vector3d n_r = (pc.c_cam - x_r) / ball_radius_;
        const bool inside = roi.contains(cv::Point(u, v));
        if (!inside) ++st->uncovered;
        const int view = ViewBand(map_.view_angle(u, v));
        for (int m = 0; m < kMethodCount; ++m) {
          double rho = map_.rho0(u, v);
          Eigen::Vector3d n = map_.normal0(u, v);
          if (inside) {
            const double r = pc.recs[m].rho.at<double>(v - roi.y, u - roi.x);
            const cv::Vec3d nn = pc.recs[m].normals.at<cv::Vec3d>(v - roi.y, u - roi.x);
            if (std::isfinite(r)) rho = r;
            if (std::isfinite(nn[0])) n = Eigen::Vector3d(nn[0], nn[1], nn[2]);
          }
          const Eigen::Vector3d x_m = rho * d;
          for (int t = 0; t < n_truths_; ++t) {
            double depth_err, normal_err;
            if (t == 0) {
              depth_err = std::abs((x_m - x_r).dot(n_r));
              normal_err = AngleDeg(n, n_r);
            } else {
              Eigen::Vector3d n_t;
              depth_err = pc.physical->Distance(sensor_from_cam_ * x_m, &n_t);
              normal_err = AngleDeg(sensor_from_cam_.RotateDirection(n), n_t);
            }
            if (m == 0 && t == n_truths_ - 1) probe_error_sum += depth_err, ++probe_error_n;
            for (const int band : {static_cast<int>(kAll), pc.height, view, pc.fins}) {
              BandErrors& e = st->acc.at(t, m, band);
              e.depth.push_back(static_cast<float>(depth_err));
              e.normal.push_back(static_cast<float>(normal_err));
            }
          }
        }
      }
    }
    return {probe_error_sum, probe_error_n};
  }

  // One row of validation.json's "probe_peaks": where the probe is, how its imprint is seen, and
  // each method's peak indentation against each truth's (which probes make the peak error).
  Json PeakRow(int plan_index, const ValidationProbe& probe, const ProbeCase& pc) const {
    const Eigen::Vector3d& p = probe.contact_point_sensor;
    const int u = static_cast<int>(std::lround(pc.render.contact_centroid.x()));
    const int v = static_cast<int>(std::lround(pc.render.contact_centroid.y()));
    const bool on_map = u >= 0 && v >= 0 && u < map_.width() && v < map_.height();
    Json peaks = Json::object();
    for (int m = 0; m < kMethodCount; ++m) {
      peaks[kMethods[m]] = pc.roi.empty() ? Json(nullptr) : Number(pc.recs[m].peak_indentation_mm);
    }
    Json row = {{"plan_index", plan_index},
                {"contact_point_mm", {p.x(), p.y(), p.z()}},
                {"contact_pixels", pc.render.contact_pixels},
                {"view_deg", on_map ? Number(map_.view_angle(u, v) * kRadToDeg) : Json(nullptr)},
                {"peak_mm", peaks},
                {"rigid_mm", pc.render.max_indentation_mm}};
    if (pc.physical) row["physical_mm"] = pc.physical->PeakIndentation();
    return row;
  }

  // Peak indentation errors per truth and method, in the bands of the probe's contact point.
  void AddPeakErrors(const ProbeCase& pc, ThreadState* st) const {
    const double truth_peak[2] = {pc.render.max_indentation_mm,
                                  pc.physical ? pc.physical->PeakIndentation() : 0.0};
    for (int m = 0; m < kMethodCount; ++m) {
      const double peak = pc.roi.empty() ? 0.0 : pc.recs[m].peak_indentation_mm;
      for (int t = 0; t < n_truths_; ++t) {
        for (const int band : {static_cast<int>(kAll), pc.height, pc.fins}) {
          BandErrors& e = st->acc.at(t, m, band);
          e.peak.push_back(static_cast<float>(std::abs(peak - truth_peak[t])));
          e.peak_signed.push_back(static_cast<float>(peak - truth_peak[t]));
          ++e.probes;
        }
      }
    }
  }

  // The frame, the rigid render's indentation and the default method's and plain Poisson's over
  // the region and the render (clipped to the image).
  ValidationExample MakeExample(int plan_index, const ValidationProbe& probe,
                                const ProbeCase& pc) const {
    const ProbeRender& render = pc.render;
    const cv::Rect& roi = pc.roi;
    ValidationExample ex;
    ex.plan_index = plan_index;
    ex.recon_method = kMethods[default_index_];
    const cv::Rect box = roi | render.roi;
    const cv::Rect clipped = box & cv::Rect(0, 0, probe.frame.cols, probe.frame.rows);
    ex.frame_roi = probe.frame(clipped).clone();
    ex.truth_depth = cv::Mat(clipped.size(), CV_64F, cv::Scalar::all(0.0));
    ex.recon_depth = ex.truth_depth.clone();
    ex.poisson_depth = ex.truth_depth.clone();
    for (int v = clipped.y; v < clipped.y + clipped.height; ++v) {
      for (int u = clipped.x; u < clipped.x + clipped.width; ++u) {
        if (!map_.visible(u, v)) continue;
        const double cosine = std::abs(map_.ray(u, v).dot(map_.normal0(u, v)));
        if (render.roi.contains(cv::Point(u, v))) {
          const double r = render.rho.at<double>(v - render.roi.y, u - render.roi.x);
          if (std::isfinite(r)) {
            ex.truth_depth.at<double>(v - clipped.y, u - clipped.x) =
                (map_.rho0(u, v) - r) * cosine;
          }
        }
        if (roi.contains(cv::Point(u, v))) {
          const double a = pc.recs[default_index_].indentation.at<double>(v - roi.y, u - roi.x);
          const double b = pc.recs[poisson_index_].indentation.at<double>(v - roi.y, u - roi.x);
          if (std::isfinite(a)) ex.recon_depth.at<double>(v - clipped.y, u - clipped.x) = a;
          if (std::isfinite(b)) ex.poisson_depth.at<double>(v - clipped.y, u - clipped.x) = b;
        }
      }
    }
    return ex;
  }

  const Reconstructor& rec_;
  const SurfaceMap& map_;
  const Rigid3d& cam_from_sensor_;
  const Rigid3d sensor_from_cam_;
  const double ball_radius_;
  const double gel_height_mm_;
  const ValidationTruth* const truth_;
  const int n_truths_;
  const double fin_near_mm_;
  const std::vector<int> example_probes_;
  IntegrationOptions methods_[kMethodCount];
  int default_index_ = 0, poisson_index_ = 0;
};

// The workers' states merged in thread order (deterministic for a thread count).
ThreadState Merge(std::vector<ThreadState>& states) {
  ThreadState total;
  for (ThreadState& st : states) {
    for (std::size_t i = 0; i < st.acc.cells.size(); ++i) {
      const BandErrors& e = st.acc.cells[i];
      BandErrors& dst = total.acc.cells[i];
      dst.depth.insert(dst.depth.end(), e.depth.begin(), e.depth.end());
      dst.normal.insert(dst.normal.end(), e.normal.begin(), e.normal.end());
      dst.peak.insert(dst.peak.end(), e.peak.begin(), e.peak.end());
      dst.peak_signed.insert(dst.peak_signed.end(), e.peak_signed.begin(), e.peak_signed.end());
      dst.probes += e.probes;
    }
    total.missed += st.missed;
    total.contact_pixels += st.contact_pixels;
    total.uncovered += st.uncovered;
    total.roi_pixels += st.roi_pixels;
    total.roi_max = std::max(total.roi_max, st.roi_max);
    total.rois += st.rois;
    total.mlp_s += st.mlp_s;
    for (int m = 0; m < kMethodCount; ++m) total.integration_s[m] += st.integration_s[m];
    for (auto& e : st.examples) total.examples.push_back(std::move(e));
    for (auto& e : st.probe_errors) total.probe_errors.push_back(e);
    for (auto& e : st.probe_peaks) total.probe_peaks.push_back(std::move(e));
  }
  return total;
}

// validation.json's "probe_peaks", in plan order.
Json ProbePeaks(std::vector<std::pair<int, Json>> rows) {
  std::sort(rows.begin(), rows.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  Json out = Json::array();
  for (auto& r : rows) out.push_back(std::move(r.second));
  return out;
}

// validation.json's "results": per truth, method and band (bands no probe fell in left out).
Json BandResults(const Accumulator& acc, int n_truths) {
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
  return results;
}

}  // namespace

ValidationResult Validate(const Reconstructor& rec, const std::vector<int>& held_out_all,
                          const ValidationProbeLoader& load, double ball_radius,
                          double gel_height_mm, const ValidationTruth* truth,
                          const ValidationOptions& options) {
  options.Check();
  const auto t0 = std::chrono::steady_clock::now();
  const std::vector<int> held_out = SelectProbes(held_out_all, options.max_probes);
  const int threads =
      std::max(1, std::min<int>(options.threads, static_cast<int>(held_out.size())));
  std::vector<ThreadState> states(static_cast<std::size_t>(threads));
  const ProbeEvaluator evaluator(rec, ball_radius, gel_height_mm, truth, options,
                                 ExampleProbes(held_out, options.examples));
  auto work = [&](int thread) {
    ThreadState& st = states[static_cast<std::size_t>(thread)];
    for (std::size_t k = static_cast<std::size_t>(thread); k < held_out.size();
         k += static_cast<std::size_t>(threads)) {
      evaluator.Evaluate(held_out[k], load(held_out[k], thread), &st);
    }
  };
  std::vector<std::thread> pool;
  for (int t = 1; t < threads; ++t) pool.emplace_back(work, t);
  work(0);
  for (auto& th : pool) th.join();

  ThreadState total = Merge(states);
  ValidationResult result;
  std::sort(total.examples.begin(), total.examples.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  std::sort(total.probe_errors.begin(), total.probe_errors.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  for (auto& e : total.examples) result.examples.push_back(std::move(e.second));
  for (auto& e : total.probe_errors) result.probe_errors.push_back(e.second);

  const int n_truths = evaluator.n_truths();
  const IntegrationMethod default_method = rec.options().integration.method;
  const double evaluated = static_cast<double>(held_out.size());
  Json ms_per_probe{{"mlp", evaluated > 0 ? 1000.0 * total.mlp_s / evaluated : 0.0}};
  for (int m = 0; m < kMethodCount; ++m) {
    if (m == kRenderSlopes) continue;
    ms_per_probe[std::string("integration_") + kMethods[m]] =
        evaluated > 0 ? 1000.0 * total.integration_s[m] / evaluated : 0.0;
  }
  const std::int64_t rois = total.rois;
  result.report = Json{
      {"probes_held_out", held_out_all.size()},
      {"probes_evaluated", held_out.size()},
      {"probes_missed", total.missed},
      {"contact_pixels", total.contact_pixels},
      {"contact_pixels_outside_roi", total.uncovered},
      {"roi_pixels_mean",
       rois > 0 ? static_cast<double>(total.roi_pixels) / static_cast<double>(rois) : 0.0},
      {"roi_pixels_max", total.roi_max},
      {"truths", n_truths == 2 ? Json{"rigid", "physical"} : Json{"rigid"}},
      {"truth_description", truth != nullptr ? truth->Describe() : std::string()},
      {"methods", {"heightfield", "discontinuity", "poisson"}},
      {"diagnostics", {"render_slopes"}},
      {"default_method", std::string(ToString(default_method))},
      {"results", BandResults(total.acc, n_truths)},
      {"probe_peaks", ProbePeaks(std::move(total.probe_peaks))},
      {"ms_per_probe", ms_per_probe},
      {"seconds", std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count()},
  };
  return result;
}

}  // namespace gs360
