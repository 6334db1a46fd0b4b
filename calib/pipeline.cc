#include "calib/pipeline.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>
#include <mutex>
#include <numeric>
#include <stdexcept>
#include <thread>

#include <opencv2/imgcodecs.hpp>

#include "calib/onnx_export.h"
#include "calib/report.h"
#include "geometry/bvh.h"
#include "geometry/hash.h"

namespace gs360 {
namespace {

using Json = nlohmann::json;
using Clock = std::chrono::steady_clock;

double Since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

std::string FromBytes(std::span<const std::uint8_t> b) {
  return std::string(b.begin(), b.end());
}

void Put(std::vector<std::uint8_t>* out, const void* data, std::size_t size) {
  if (size == 0) return;
  const std::size_t at = out->size();
  out->resize(at + size);
  std::memcpy(out->data() + at, data, size);
}

template <typename T>
void PutPod(std::vector<std::uint8_t>* out, const T& v) {
  Put(out, &v, sizeof(T));
}

class ByteReader {
 public:
  ByteReader(std::span<const std::uint8_t> b, std::string what) : b_(b), what_(std::move(what)) {}
  template <typename T>
  T Pod() {
    if (sizeof(T) > b_.size() - pos_) {
      throw std::runtime_error(what_ + " artifact is truncated at byte " + std::to_string(pos_));
    }
    T v;
    std::memcpy(&v, b_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    return v;
  }
  bool AtEnd() const { return pos_ == b_.size(); }

 private:
  std::span<const std::uint8_t> b_;
  std::size_t pos_ = 0;
  std::string what_;
};

// A report file; a failed write (full disk, no permission) is an error naming the file.
void WriteTextFile(const std::filesystem::path& path, const std::string& text) {
  std::ofstream out(path, std::ios::trunc);
  out << text;
  out.flush();
  if (!out) throw std::runtime_error("export: cannot write " + path.string());
}

void HashMesh(Hasher& h, const TriangleMesh& m) {
  h.AddPod(static_cast<std::uint64_t>(m.vertices.size()));
  for (const auto& v : m.vertices) h.AddDouble(v.x()).AddDouble(v.y()).AddDouble(v.z());
  h.AddPod(static_cast<std::uint64_t>(m.triangles.size()));
  for (const auto& t : m.triangles) h.AddPod(t.x()).AddPod(t.y()).AddPod(t.z());
}

void HashPose(Hasher& h, const Rigid3d& p) {
  h.AddDouble(p.rotation.w()).AddDouble(p.rotation.x()).AddDouble(p.rotation.y());
  h.AddDouble(p.rotation.z());
  h.AddDouble(p.translation.x()).AddDouble(p.translation.y()).AddDouble(p.translation.z());
}

// Options enter the hashes through their JSON text (stable key order in nlohmann::json).
Json TrainOptionsJson(const TrainOptions& o) {
  return Json{{"hidden", o.hidden},
              {"activation", std::string(ToString(o.activation))},
              {"fourier", {o.fourier.inputs, o.fourier.frequencies, o.fourier.base}},
              {"batch_size", o.batch_size},
              {"learning_rate", o.learning_rate},
              {"beta1", o.beta1},
              {"beta2", o.beta2},
              {"epsilon", o.epsilon},
              {"schedule", std::string(ToString(o.schedule))},
              {"min_learning_rate", o.min_learning_rate},
              {"plateau_factor", o.plateau_factor},
              {"plateau_epochs", o.plateau_epochs},
              {"plateau_threshold", o.plateau_threshold},
              {"max_epochs", o.max_epochs},
              {"patience", o.patience},
              {"seed", o.seed},
              {"threads", o.threads}};
}

// The stages' bookkeeping: cache lookup, forced re-runs, reports.
class StageRunner {
 public:
  StageRunner(RunDatabase& db, std::int64_t run_id, const std::string& from_stage,
              const CalibrationLog& log, std::vector<StageReport>* reports)
      : db_(db), run_id_(run_id), log_(log), reports_(reports) {
    const auto& stages = CalibrationStages();
    from_index_ = static_cast<int>(stages.size());
    if (!from_stage.empty()) {
      auto it = std::find(stages.begin(), stages.end(), from_stage);
      if (it == stages.end()) {
        std::string names;
        for (const auto& s : stages) names += (names.empty() ? "" : ", ") + s;
        throw std::invalid_argument("--from: unknown stage \"" + from_stage +
                                    "\" (stages: " + names + ")");
      }
      from_index_ = static_cast<int>(it - stages.begin());
    }
  }

  // Returns the stage's blob: the cached one, or compute()'s (stored).
  template <typename Compute>
  // `force`: run even if cached (e.g. the stage's files were deleted).
  std::vector<std::uint8_t> Run(const std::string& stage, const std::string& hash, Compute compute,
                                Json* metrics_out = nullptr, bool force = false) {
    const auto t0 = Clock::now();
    const auto& stages = CalibrationStages();
    const int index =
        static_cast<int>(std::find(stages.begin(), stages.end(), stage) - stages.begin());
    StageReport report;
    report.stage = stage;
    report.input_hash = hash;
    std::vector<std::uint8_t> blob;
    std::optional<ArtifactRecord> cached;
    if (index < from_index_ && !force) cached = db_.GetArtifact(run_id_, stage, hash);
    if (cached) {
      blob = std::move(cached->blob);
      report.cached = true;
      report.metrics = Json::parse(cached->metrics_json);
      Log(stage, "cached (" + hash + ")");
    } else {
      Log(stage, "running");
      Json metrics;
      blob = compute(&metrics);
      metrics["seconds"] = Since(t0);
      report.metrics = metrics;
      db_.PutArtifact(run_id_, stage, hash, blob, metrics.dump());
    }
    report.seconds = Since(t0);
    if (metrics_out != nullptr) *metrics_out = report.metrics;
    reports_->push_back(std::move(report));
    return blob;
  }

  void Log(const std::string& stage, const std::string& message) const {
    if (log_) log_(stage, message);
  }

 private:
  RunDatabase& db_;
  std::int64_t run_id_;
  const CalibrationLog& log_;
  std::vector<StageReport>* reports_;
  int from_index_ = 0;
};

// A captured probe with everything the stages need to know about it.
struct ProbeInfo {
  int plan_index = 0;
  std::int64_t frame_id = 0;
  std::int64_t reference_id = 0;
  Eigen::Vector3d point_sensor = Eigen::Vector3d::Zero();
  Eigen::Vector3d normal_sensor = Eigen::Vector3d::UnitZ();
  Eigen::Vector3d ball_sensor = Eigen::Vector3d::Zero();
};

// Runs f(k, thread) for k in [0, n) on `threads` threads, each with its own read-only database
// connection (SQLite connections are per thread). Exceptions are rethrown on the caller.
template <typename F>
void ParallelOverProbes(const std::filesystem::path& db_path, std::size_t n, int threads, F f) {
  threads = std::max(1, std::min<int>(threads, static_cast<int>(n)));
  std::mutex error_mutex;
  std::exception_ptr error;
  auto work = [&](int t) {
    try {
      RunDatabaseOptions ro;
      ro.read_only = true;
      RunDatabase conn(db_path, ro);
      for (std::size_t k = static_cast<std::size_t>(t); k < n;
           k += static_cast<std::size_t>(threads)) {
        {
          std::lock_guard<std::mutex> lock(error_mutex);
          if (error) return;
        }
        f(k, t, conn);
      }
    } catch (...) {
      std::lock_guard<std::mutex> lock(error_mutex);
      if (!error) error = std::current_exception();
    }
  };
  std::vector<std::thread> pool;
  for (int t = 1; t < threads; ++t) pool.emplace_back(work, t);
  work(0);
  for (auto& th : pool) th.join();
  if (error) std::rethrow_exception(error);
}

// Decoded frames with a small per-thread cache of reference frames.
class FrameLoader {
 public:
  cv::Mat Press(RunDatabase& conn, const ProbeInfo& p) { return conn.LoadFrame(p.frame_id); }
  cv::Mat Reference(RunDatabase& conn, const ProbeInfo& p) {
    auto it = refs_.find(p.reference_id);
    if (it != refs_.end()) return it->second;
    if (refs_.size() > 8) refs_.clear();
    cv::Mat ref = conn.LoadFrame(p.reference_id);
    refs_[p.reference_id] = ref;
    return ref;
  }

 private:
  std::map<std::int64_t, cv::Mat> refs_;
};

std::vector<std::uint8_t> SparseRenders(const std::vector<std::pair<int, ProbeRender>>& renders) {
  std::vector<std::uint8_t> b;
  PutPod(&b, static_cast<std::uint32_t>(renders.size()));
  for (const auto& [plan_index, r] : renders) {
    PutPod(&b, static_cast<std::int32_t>(plan_index));
    PutPod(&b, r.roi.x), PutPod(&b, r.roi.y), PutPod(&b, r.roi.width), PutPod(&b, r.roi.height);
    PutPod(&b, r.max_indentation_mm);
    PutPod(&b, r.contact_centroid.x()), PutPod(&b, r.contact_centroid.y());
    PutPod(&b, static_cast<std::int32_t>(r.contact_pixels));
    for (int y = 0; y < r.roi.height; ++y) {
      for (int x = 0; x < r.roi.width; ++x) {
        if (!r.contact.at<std::uint8_t>(y, x)) continue;
        PutPod(&b, static_cast<std::uint16_t>(x));
        PutPod(&b, static_cast<std::uint16_t>(y));
        PutPod(&b, r.gx.at<float>(y, x));
        PutPod(&b, r.gy.at<float>(y, x));
        PutPod(&b, r.rho.at<double>(y, x));
        PutPod(&b, static_cast<std::uint8_t>(r.steep.empty() ? 0 : r.steep.at<std::uint8_t>(y, x)));
      }
    }
  }
  return b;
}

std::map<int, ProbeRender> RendersFromSparse(std::span<const std::uint8_t> bytes,
                                             const SurfaceMap& map) {
  ByteReader r(bytes, "render");
  std::map<int, ProbeRender> out;
  const auto n = r.Pod<std::uint32_t>();
  for (std::uint32_t i = 0; i < n; ++i) {
    ProbeRender pr;
    const int plan_index = r.Pod<std::int32_t>();
    pr.roi.x = r.Pod<int>(), pr.roi.y = r.Pod<int>();
    pr.roi.width = r.Pod<int>(), pr.roi.height = r.Pod<int>();
    pr.max_indentation_mm = r.Pod<double>();
    const double cu = r.Pod<double>(), cv = r.Pod<double>();
    pr.contact_centroid = Eigen::Vector2d(cu, cv);
    pr.contact_pixels = r.Pod<std::int32_t>();
    pr.contact = cv::Mat(pr.roi.size(), CV_8U, cv::Scalar::all(0));
    pr.steep = cv::Mat(pr.roi.size(), CV_8U, cv::Scalar::all(0));
    pr.gx = cv::Mat(pr.roi.size(), CV_32F, cv::Scalar::all(0));
    pr.gy = cv::Mat(pr.roi.size(), CV_32F, cv::Scalar::all(0));
    pr.rho = cv::Mat(pr.roi.size(), CV_64F, cv::Scalar::all(std::nan("")));
    for (int y = 0; y < pr.roi.height; ++y) {
      for (int x = 0; x < pr.roi.width; ++x) {
        const int u = pr.roi.x + x, v = pr.roi.y + y;
        if (map.visible(u, v)) pr.rho.at<double>(y, x) = map.rho0(u, v);
      }
    }
    for (int k = 0; k < pr.contact_pixels; ++k) {
      const int x = r.Pod<std::uint16_t>(), y = r.Pod<std::uint16_t>();
      if (x >= pr.roi.width || y >= pr.roi.height) {
        throw std::runtime_error("render artifact: pixel outside its roi (corrupt)");
      }
      pr.contact.at<std::uint8_t>(y, x) = 255;
      pr.gx.at<float>(y, x) = r.Pod<float>();
      pr.gy.at<float>(y, x) = r.Pod<float>();
      pr.rho.at<double>(y, x) = r.Pod<double>();
      pr.steep.at<std::uint8_t>(y, x) = r.Pod<std::uint8_t>();
    }
    out[plan_index] = std::move(pr);
  }
  if (!r.AtEnd()) throw std::runtime_error("render artifact has trailing bytes (corrupt)");
  return out;
}

}  // namespace

const std::vector<std::string>& CalibrationStages() {
  static const std::vector<std::string> kStages = {"intrinsics",  "impressions", "pose",
                                                   "surface_map", "render",      "dataset",
                                                   "train",       "validate",    "export"};
  return kStages;
}

void CalibrationOptions::Check() const {
  intrinsics.Check();
  surface_map.Check();
  impression.Check();
  pose.Check();
  render.Check();
  dataset.Check();
  train.Check();
  validation.Check();
  reconstruction.Check();
  if (threads < 1 || threads > 64) {
    throw std::invalid_argument("CalibrationOptions.threads must be in [1, 64], got " +
                                std::to_string(threads));
  }
  if (!from_stage.empty()) {
    const auto& s = CalibrationStages();
    if (std::find(s.begin(), s.end(), from_stage) == s.end()) {
      throw std::invalid_argument("CalibrationOptions.from_stage: unknown stage \"" + from_stage +
                                  "\"");
    }
  }
}

CalibrationResult RunCalibration(RunDatabase& db, std::int64_t run_id,
                                 const CalibrationInputs& inputs, const CalibrationOptions& options,
                                 const ValidationTruth* truth, const CalibrationLog& log) {
  options.Check();
  const auto t_start = Clock::now();
  CalibrationResult result;
  StageRunner runner(db, run_id, options.from_stage, log, &result.stages);
  const auto run = db.GetRun(run_id);
  if (!run)
    throw std::runtime_error("calibrate: no run " + std::to_string(run_id) + " in " +
                             db.path().string());
  const Rigid3d sensor_from_machine = inputs.machine_from_sensor.Inverse();

  // ---- the captured probes and their frames ----
  std::vector<ProbeInfo> probes;
  Hasher frames_hash;
  for (const CapturedProbe& cp : db.ListCapturedProbes(run_id)) {
    ProbeInfo p;
    p.plan_index = cp.probe.plan_index;
    p.frame_id = cp.frame_id;
    p.point_sensor = cp.probe.plan.point_sensor;
    p.normal_sensor = cp.probe.plan.normal_sensor;
    const Eigen::Vector3d mpos = cp.probe.machine_position.value_or(cp.probe.plan.press_machine);
    p.ball_sensor = sensor_from_machine * (mpos + inputs.tool_offset);
    const auto ref = db.NearestReferenceFrame(run_id, cp.frame_time);
    if (!ref)
      throw std::runtime_error("calibrate: run " + std::to_string(run_id) +
                               " has no reference frame");
    p.reference_id = ref->id;
    const auto info = db.GetFrameInfo(p.frame_id);
    frames_hash.AddPod(p.plan_index).Add(info ? info->checksum : std::string("?"));
    frames_hash.Add(ref->checksum);
    frames_hash.AddDouble(p.ball_sensor.x())
        .AddDouble(p.ball_sensor.y())
        .AddDouble(p.ball_sensor.z());
    probes.push_back(p);
  }
  if (probes.size() < 20) {
    throw std::runtime_error("calibrate: run " + std::to_string(run_id) + " has " +
                             std::to_string(probes.size()) +
                             " captured probes; the calibration needs at least 20");
  }
  const std::string frames_key = frames_hash.Hex();
  Hasher geometry_hash;
  HashMesh(geometry_hash, inputs.gel_mesh);
  HashMesh(geometry_hash, inputs.fin_mesh);
  geometry_hash.AddDouble(inputs.ball_radius);
  const std::string geometry_key = geometry_hash.Hex();

  // ---- 1. intrinsics ----
  std::string intrinsics_key;
  {
    Hasher h;
    h.Add("intrinsics/1").Add(IntrinsicsToJson(inputs.nominal_intrinsics).dump());
    std::vector<cv::Mat> images;
    for (const auto& path : inputs.checkerboard_images) {
      std::ifstream in(path, std::ios::binary);
      if (!in)
        throw std::runtime_error("intrinsics: cannot read checkerboard image " + path.string());
      std::vector<std::uint8_t> bytes((std::istreambuf_iterator<char>(in)),
                                      std::istreambuf_iterator<char>());
      h.Add(bytes.data(), bytes.size());
      cv::Mat img = cv::imdecode(bytes, cv::IMREAD_GRAYSCALE);
      if (img.empty())
        throw std::runtime_error("intrinsics: " + path.string() + " is not a readable image");
      images.push_back(img);
    }
    const IntrinsicsOptions& io = options.intrinsics;
    h.Add(Json{{"cols", io.board_cols},
               {"rows", io.board_rows},
               {"square", io.square_mm},
               {"min_images", io.min_images},
               {"max_rms", io.max_rms_px},
               {"coverage", io.min_radial_coverage},
               {"subpix", io.subpix_window},
               {"iterations", io.max_iterations},
               {"eps", io.epsilon}}
              .dump());
    intrinsics_key = h.Hex();
    const auto blob = runner.Run("intrinsics", intrinsics_key, [&](Json* metrics) {
      Json out;
      if (images.empty()) {
        out = IntrinsicsToJson(inputs.nominal_intrinsics);
        (*metrics)["source"] = "nominal (no checkerboard images given)";
      } else {
        IntrinsicsResult r;
        try {
          r = CalibrateIntrinsics(images, inputs.nominal_intrinsics, options.intrinsics);
        } catch (const std::exception& e) {
          throw std::runtime_error(std::string("intrinsics: ") + e.what());
        }
        out = IntrinsicsToJson(r.intrinsics);
        (*metrics)["source"] = "checkerboards";
        (*metrics)["rms_px"] = r.rms_px;
        (*metrics)["images_used"] = r.used.size();
        (*metrics)["images_rejected"] = r.rejected.size();
        (*metrics)["radial_coverage"] = r.radial_coverage;
      }
      (*metrics)["intrinsics"] = out;
      const std::string text = out.dump();
      return std::vector<std::uint8_t>(text.begin(), text.end());
    });
    result.intrinsics = IntrinsicsFromJson(Json::parse(FromBytes(blob)));
  }
  const FisheyeCamera camera(result.intrinsics);

  // ---- 2. impressions ----
  struct Found {
    bool ok = false;
    Eigen::Vector2d centroid = Eigen::Vector2d::Zero();
    double peak = 0.0;
    int pixels = 0;
  };
  std::vector<Found> impressions(probes.size());
  std::string impressions_key;
  {
    Hasher h;
    h.Add("impressions/1").Add(frames_key);
    const ImpressionCentroidOptions& io = options.impression;
    h.AddDouble(io.blur_sigma_px).AddDouble(io.min_peak_dn).AddDouble(io.threshold_fraction);
    h.AddDouble(io.min_threshold_dn).AddDouble(io.window_px);
    impressions_key = h.Hex();
    const auto blob = runner.Run("impressions", impressions_key, [&](Json* metrics) {
      std::vector<Found> found(probes.size());
      std::vector<FrameLoader> loaders(static_cast<std::size_t>(options.threads));
      ParallelOverProbes(db.path(), probes.size(), options.threads,
                         [&](std::size_t k, int t, RunDatabase& conn) {
                           FrameLoader& fl = loaders[static_cast<std::size_t>(t)];
                           const cv::Mat press = fl.Press(conn, probes[k]);
                           const cv::Mat ref = fl.Reference(conn, probes[k]);
                           const auto imp = FindImpressionRegion(press, ref, options.impression);
                           if (imp) found[k] = {true, imp->centroid, imp->peak_dn, imp->pixels};
                         });
      std::vector<std::uint8_t> out;
      int ok = 0;
      for (const Found& f : found) {
        PutPod(&out, static_cast<std::uint8_t>(f.ok));
        PutPod(&out, f.centroid.x()), PutPod(&out, f.centroid.y());
        PutPod(&out, f.peak), PutPod(&out, static_cast<std::int32_t>(f.pixels));
        ok += f.ok ? 1 : 0;
      }
      (*metrics)["probes"] = probes.size();
      (*metrics)["impressions_found"] = ok;
      return out;
    });
    ByteReader r(blob, "impressions");
    for (Found& f : impressions) {
      f.ok = r.Pod<std::uint8_t>() != 0;
      const double x = r.Pod<double>(), y = r.Pod<double>();
      f.centroid = Eigen::Vector2d(x, y);
      f.peak = r.Pod<double>();
      f.pixels = r.Pod<std::int32_t>();
    }
  }

  const Bvh gel_bvh(inputs.gel_mesh);
  std::unique_ptr<Bvh> fin_bvh;
  if (!inputs.fin_mesh.Empty()) fin_bvh = std::make_unique<Bvh>(inputs.fin_mesh);

  // ---- 3. pose ----
  std::string pose_key;
  Json pose_metrics;
  {
    Hasher h;
    h.Add("pose/1").Add(impressions_key).Add(intrinsics_key).Add(geometry_key);
    HashPose(h, inputs.nominal_cam_from_sensor);
    const PoseOptions& po = options.pose;
    h.AddPod(po.ransac_probes).AddDouble(po.ransac_threshold_px).AddPod(po.ransac_iterations);
    h.AddPod(po.max_iterations).AddDouble(po.huber_px).AddDouble(po.outlier_px);
    h.AddPod(po.min_observations).AddPod(po.model_bias).AddPod(po.bias_rounds);
    h.Add("view").AddDouble(po.max_view_angle_deg).AddDouble(po.min_view_fraction);
    h.AddDouble(po.render.margin_px).AddDouble(po.render.max_slope_deg);
    h.AddDouble(po.surface_map.max_view_angle_deg).AddDouble(po.surface_map.fin_margin_px);
    h.AddPod(po.seed);
    pose_key = h.Hex();
    const auto blob = runner.Run(
        "pose", pose_key,
        [&](Json* metrics) {
          std::vector<PoseObservation> obs;
          for (std::size_t k = 0; k < probes.size(); ++k) {
            if (!impressions[k].ok) continue;
            PoseObservation o;
            o.probe_index = probes[k].plan_index;
            o.contact_point_sensor = probes[k].point_sensor;
            o.contact_normal_sensor = probes[k].normal_sensor;
            o.ball_center_sensor = probes[k].ball_sensor;
            o.centroid_px = impressions[k].centroid;
            obs.push_back(o);
          }
          PoseResult r;
          try {
            PoseOptions run_options = options.pose;
            run_options.ball_radius_mm = inputs.ball_radius;
            run_options.threads = options.threads;
            r = EstimateCamFromSensor(camera, obs, inputs.nominal_cam_from_sensor, run_options,
                                      PoseScene{&gel_bvh, fin_bvh.get()});
          } catch (const std::exception& e) {
            throw std::runtime_error(std::string("pose: ") + e.what());
          }
          Json out{{"cam_from_sensor", PoseToJson(r.cam_from_sensor)},
                   {"paper_cam_from_sensor", PoseToJson(r.paper_cam_from_sensor)}};
          (*metrics)["observations"] = obs.size();
          (*metrics)["rms_px"] = r.rms_px;
          (*metrics)["paper_rms_px"] = r.paper_rms_px;
          (*metrics)["inliers"] = r.inliers;
          (*metrics)["paper_inliers"] = r.paper_inliers;
          (*metrics)["bias_rounds"] = r.bias_rounds;
          (*metrics)["mean_bias_px"] = r.mean_bias_px;
          (*metrics)["outliers"] = r.outliers;
          (*metrics)["oblique_excluded"] = r.oblique;
          (*metrics)["view_bound_deg"] = r.view_bound_deg;
          (*metrics)["moved_from_nominal_mm"] =
              TranslationDifferenceMm(r.cam_from_sensor, inputs.nominal_cam_from_sensor);
          (*metrics)["moved_from_nominal_deg"] =
              RotationDifferenceRad(r.cam_from_sensor, inputs.nominal_cam_from_sensor) * 180.0 /
              M_PI;
          const std::string text = out.dump();
          return std::vector<std::uint8_t>(text.begin(), text.end());
        },
        &pose_metrics);
    const Json pose = Json::parse(FromBytes(blob));
    result.cam_from_sensor = PoseFromJson(pose.at("cam_from_sensor"));
    if (truth != nullptr) {
      if (const auto true_pose = truth->TrueCamFromSensor()) {
        const Rigid3d paper = PoseFromJson(pose.at("paper_cam_from_sensor"));
        pose_metrics["error_mm"] = TranslationDifferenceMm(result.cam_from_sensor, *true_pose);
        pose_metrics["error_deg"] =
            RotationDifferenceRad(result.cam_from_sensor, *true_pose) * 180.0 / M_PI;
        pose_metrics["paper_error_mm"] = TranslationDifferenceMm(paper, *true_pose);
        pose_metrics["paper_error_deg"] = RotationDifferenceRad(paper, *true_pose) * 180.0 / M_PI;
      }
    }
  }

  // ---- 4. surface map at the calibrated pose ----
  std::shared_ptr<const SurfaceMap> map;
  std::string map_key;
  {
    Hasher h;
    h.Add("surface_map/1").Add(pose_key).Add(intrinsics_key).Add(geometry_key);
    h.AddDouble(options.surface_map.max_view_angle_deg)
        .AddDouble(options.surface_map.fin_margin_px);
    map_key = h.Hex();
    SurfaceMapOptions mo = options.surface_map;
    mo.threads = options.threads;
    const auto blob = runner.Run("surface_map", map_key, [&](Json* metrics) {
      const SurfaceMap m =
          SurfaceMap::Build(camera, result.cam_from_sensor, gel_bvh, fin_bvh.get(), mo);
      (*metrics)["visible"] = m.stats().visible;
      (*metrics)["fin"] = m.stats().fin;
      (*metrics)["grazing"] = m.stats().grazing;
      (*metrics)["no_hit"] = m.stats().no_hit;
      (*metrics)["build_seconds"] = m.stats().build_seconds;
      return m.Serialize();
    });
    map = std::make_shared<const SurfaceMap>(SurfaceMap::Deserialize(blob));
  }

  // ---- 5. render ----
  std::map<int, ProbeRender> renders;
  std::string render_key;
  {
    Hasher h;
    h.Add("render/2").Add(map_key).Add(frames_key);
    h.AddDouble(options.render.margin_px).AddDouble(options.render.max_slope_deg);
    render_key = h.Hex();
    const auto blob = runner.Run("render", render_key, [&](Json* metrics) {
      std::vector<std::pair<int, ProbeRender>> out(probes.size());
      std::vector<std::thread> pool;
      const int threads = options.threads;
      auto work = [&](int t) {
        for (std::size_t k = static_cast<std::size_t>(t); k < probes.size();
             k += static_cast<std::size_t>(threads)) {
          out[k] = {probes[k].plan_index,
                    RenderProbe(*map, camera, result.cam_from_sensor * probes[k].ball_sensor,
                                inputs.ball_radius, options.render)};
        }
      };
      for (int t = 1; t < threads; ++t) pool.emplace_back(work, t);
      work(0);
      for (auto& th : pool) th.join();
      std::int64_t contact = 0;
      int with_contact = 0;
      for (const auto& [i, r] : out) {
        contact += r.contact_pixels;
        with_contact += r.contact_pixels > 0 ? 1 : 0;
      }
      (*metrics)["probes"] = out.size();
      (*metrics)["probes_with_contact"] = with_contact;
      (*metrics)["contact_pixels"] = contact;
      return SparseRenders(out);
    });
    renders = RendersFromSparse(blob, *map);
  }

  // ---- 6. dataset ----
  Dataset dataset;
  std::string dataset_key;
  {
    // The sample budget becomes a per-probe cap over the probes that will contribute.
    std::size_t contributing = 0;
    for (const auto& [index, render] : renders) {
      contributing += render.contact_pixels >= options.dataset.min_contact_pixels ? 1 : 0;
    }
    DatasetOptions d = options.dataset;
    d.max_contact_samples_per_probe = d.ContactSamplesPerProbe(contributing);
    Hasher h;
    h.Add("dataset/2").Add(render_key).Add(frames_key);
    h.AddPod(d.max_contact_samples_per_probe).AddDouble(d.non_contact_fraction);
    h.AddPod(d.min_contact_pixels).AddDouble(d.validation_fraction).AddDouble(d.test_fraction);
    h.AddPod(d.seed);
    if (d.edge_exclusion_mm > 0.0) h.Add("edge").AddDouble(d.edge_exclusion_mm);
    h.Add(ReconstructionOptionsToJson(options.reconstruction).at("difference").dump());
    dataset_key = h.Hex();
    const auto blob = runner.Run("dataset", dataset_key, [&](Json* metrics) {
      const cv::Mat visible = map->VisibleMask();
      std::vector<Dataset> parts(probes.size());
      std::vector<FrameLoader> loaders(static_cast<std::size_t>(options.threads));
      ParallelOverProbes(
          db.path(), probes.size(), options.threads, [&](std::size_t k, int t, RunDatabase& conn) {
            auto it = renders.find(probes[k].plan_index);
            if (it == renders.end() ||
                it->second.contact_pixels < options.dataset.min_contact_pixels) {
              return;
            }
            FrameLoader& fl = loaders[static_cast<std::size_t>(t)];
            const cv::Mat press = fl.Press(conn, probes[k]);
            const cv::Mat ref = fl.Reference(conn, probes[k]);
            const cv::Mat diff =
                NormalizedDifference(press, ref, visible, options.reconstruction.difference);
            cv::Mat penetration;
            if (options.dataset.edge_exclusion_mm > 0.0) {
              penetration = NormalPenetration(*map, it->second.roi,
                                              result.cam_from_sensor * probes[k].ball_sensor,
                                              inputs.ball_radius);
            }
            const cv::Mat context = ContextFeatures(
                diff, visible, it->second.roi, options.reconstruction.difference.context_sigmas_px);
            AppendProbeSamples(diff, it->second, probes[k].plan_index, d, &parts[k], penetration,
                               context);
          });
      Dataset all;
      std::size_t n = 0;
      for (const Dataset& p : parts) n += p.probe.size();
      all.x.resize(FeatureCount(options.reconstruction.difference), static_cast<Eigen::Index>(n));
      all.y.resize(2, static_cast<Eigen::Index>(n));
      Eigen::Index c = 0;
      for (std::size_t k = 0; k < parts.size(); ++k) {
        const Dataset& p = parts[k];
        if (p.probe.empty()) continue;
        all.x.middleCols(c, p.x.cols()) = p.x;
        all.y.middleCols(c, p.y.cols()) = p.y;
        c += p.x.cols();
        all.probe.insert(all.probe.end(), p.probe.begin(), p.probe.end());
        all.contact.insert(all.contact.end(), p.contact.begin(), p.contact.end());
        all.probes.push_back(probes[k].plan_index);
      }
      if (all.probes.size() < 10) {
        throw std::runtime_error("dataset: only " + std::to_string(all.probes.size()) +
                                 " probes have a rendered contact of at least " +
                                 std::to_string(options.dataset.min_contact_pixels) +
                                 " pixels; is the camera pose right?");
      }
      all.probe_split = SplitProbes(all.probes, options.dataset);
      (*metrics)["samples"] = n;
      (*metrics)["contact_samples_per_probe"] = d.max_contact_samples_per_probe;
      (*metrics)["probes"] = all.probes.size();
      (*metrics)["train_samples"] = all.Count(Split::kTrain);
      (*metrics)["validation_samples"] = all.Count(Split::kValidation);
      (*metrics)["test_probes"] = all.ProbesIn(Split::kTest).size();
      return all.Serialize();
    });
    dataset = Dataset::Deserialize(blob);
  }

  // ---- 7. train ----
  Mlp mlp;
  std::string train_key;
  std::vector<TrainEpoch> curve;
  {
    Hasher h;
    TrainOptions to = options.train;
    to.threads = options.threads;
    h.Add("train/1").Add(dataset_key).Add(TrainOptionsJson(to).dump());
    train_key = h.Hex();
    Json metrics_out;
    const auto blob = runner.Run(
        "train", train_key,
        [&](Json* metrics) {
          const Eigen::MatrixXf xt = dataset.X(Split::kTrain), yt = dataset.Y(Split::kTrain);
          const Eigen::MatrixXf xv = dataset.X(Split::kValidation),
                                yv = dataset.Y(Split::kValidation);
          TrainResult r = Train(xt, yt, xv, yv, to, [&](int epoch, double tl, double vl) {
            if (epoch % 5 == 0) {
              runner.Log("train", "epoch " + std::to_string(epoch) + ": train loss " +
                                      std::to_string(tl) + ", validation loss " +
                                      std::to_string(vl));
            }
          });
          Json c = Json::array();
          for (const TrainEpoch& e : r.curve) {
            c.push_back({e.epoch, e.train_loss, e.val_loss, e.seconds, e.learning_rate});
          }
          (*metrics)["curve"] = c;
          (*metrics)["best_epoch"] = r.best_epoch;
          (*metrics)["best_val_loss"] = r.best_val_loss;
          (*metrics)["epochs"] = r.curve.size();
          (*metrics)["stopped_early"] = r.stopped_early;
          (*metrics)["train_samples"] = xt.cols();
          (*metrics)["validation_samples"] = xv.cols();
          (*metrics)["parameters"] = r.mlp.ParameterCount();
          return r.mlp.Serialize();
        },
        &metrics_out);
    mlp = Mlp::Deserialize(blob);
    if (metrics_out.contains("curve")) {
      for (const auto& e : metrics_out["curve"]) {
        TrainEpoch te;
        te.epoch = e[0].get<int>();
        te.train_loss = e[1].get<double>();
        te.val_loss = e[2].get<double>();
        te.seconds = e[3].get<double>();
        te.learning_rate = e[4].get<double>();
        curve.push_back(te);
      }
    }
  }

  // The reference the model ships with: the run's latest no-contact frame.
  const auto latest_ref = db.LatestFrame(run_id, FrameKind::kReference);
  if (!latest_ref) throw std::runtime_error("calibrate: run has no reference frame");
  const cv::Mat reference = db.LoadFrame(latest_ref->id);
  const Reconstructor reconstructor(map, camera, mlp, reference, options.reconstruction);

  // ---- 8. validate ----
  std::string validate_key;
  std::string html;
  {
    Hasher h;
    const ValidationOptions& vo = options.validation;
    h.Add("validate/4").Add(train_key).Add(map_key).Add(dataset_key);
    h.Add(ReconstructionOptionsToJson(options.reconstruction).dump());
    h.AddPod(vo.max_probes).AddDouble(vo.fin_near_mm).AddPod(vo.examples);
    h.Add(truth != nullptr ? truth->Describe() : std::string("no truth"));
    validate_key = h.Hex();
    const auto blob = runner.Run("validate", validate_key, [&](Json* metrics) {
      std::map<int, std::size_t> by_index;
      for (std::size_t k = 0; k < probes.size(); ++k) by_index[probes[k].plan_index] = k;
      std::vector<int> held_out;
      for (int p : dataset.ProbesIn(Split::kTest)) held_out.push_back(p);
      std::vector<std::unique_ptr<RunDatabase>> conns;
      std::vector<FrameLoader> loaders(static_cast<std::size_t>(options.validation.threads));
      for (int t = 0; t < options.validation.threads; ++t) {
        RunDatabaseOptions ro;
        ro.read_only = true;
        conns.push_back(std::make_unique<RunDatabase>(db.path(), ro));
      }
      const ValidationProbeLoader load = [&](int plan_index, int thread) {
        const ProbeInfo& p = probes[by_index.at(plan_index)];
        ValidationProbe vp;
        vp.plan_index = plan_index;
        vp.contact_point_sensor = p.point_sensor;
        vp.ball_center_sensor = p.ball_sensor;
        RunDatabase& conn = *conns[static_cast<std::size_t>(thread)];
        vp.frame = loaders[static_cast<std::size_t>(thread)].Press(conn, p);
        vp.reference = loaders[static_cast<std::size_t>(thread)].Reference(conn, p);
        return vp;
      };
      const double height = inputs.gel_mesh.Bounds().max().z();
      ValidationResult v = Validate(reconstructor, held_out, load, inputs.ball_radius, height,
                                    truth, options.validation);
      v.report["pose"] = pose_metrics;
      // Per evaluated probe: contact point (sensor frame, mm) and mean depth error (mm), for
      // error maps outside the HTML report (the daemon's dashboard).
      Json probe_errors = Json::array();
      for (const auto& [point, error] : v.probe_errors) {
        probe_errors.push_back({point.x(), point.y(), point.z(), error});
      }
      v.report["probe_errors"] = probe_errors;
      ReportInputs ri;
      ri.title = "gs360 calibration: run " + std::to_string(run_id) + " (" + inputs.sensor + ")";
      ri.validation = v.report;
      Json stages = Json::array();
      for (const StageReport& s : result.stages) {
        stages.push_back({{"stage", s.stage},
                          {"input_hash", s.input_hash},
                          {"cached", s.cached},
                          {"seconds", s.seconds},
                          {"metrics", s.metrics}});
      }
      ri.stages = stages;
      ri.curve = curve;
      ri.examples = v.examples;
      ri.probe_errors = v.probe_errors;
      ri.gel_height_mm = height;
      (*metrics)["summary"] = v.report;
      const Json out{{"validation", v.report}, {"html", RenderReportHtml(ri)}};
      const std::string text = out.dump();
      return std::vector<std::uint8_t>(text.begin(), text.end());
    });
    const Json out = Json::parse(FromBytes(blob));
    result.validation = out.at("validation");
    html = out.at("html").get<std::string>();
  }

  // ---- 9. export ----
  {
    const std::filesystem::path dir = options.export_dir.empty()
                                          ? std::filesystem::absolute(db.path()).parent_path()
                                          : options.export_dir;
    const std::string name =
        options.model_name.empty() ? "run-" + std::to_string(run_id) : options.model_name;
    const std::string version =
        options.model_version.empty() ? train_key.substr(0, 8) : options.model_version;
    const std::string stem = name + "-" + version;
    result.model_path = dir / (stem + ".gs360model");
    result.onnx_path = dir / (stem + ".onnx");
    result.report_path = dir / (stem + "-report.html");
    result.validation_path = dir / (stem + "-validation.json");
    Hasher h;
    h.Add("export/1").Add(validate_key).Add(name).Add(version).Add(dir.string());
    runner.Run(
        "export", h.Hex(),
        [&](Json* metrics) {
          std::filesystem::create_directories(dir);
          ModelBundle bundle;
          bundle.name = name;
          bundle.version = version;
          bundle.gs360_version = "0.1.0";
          bundle.created_at =
              static_cast<double>(std::chrono::duration_cast<std::chrono::seconds>(
                                      std::chrono::system_clock::now().time_since_epoch())
                                      .count());
          bundle.sensor = inputs.sensor;
          bundle.intrinsics = result.intrinsics;
          bundle.cam_from_sensor = result.cam_from_sensor;
          bundle.gel_mesh = inputs.gel_mesh;
          bundle.fin_mesh = inputs.fin_mesh;
          bundle.surface_map = options.surface_map;
          bundle.reference = reference;
          bundle.mlp = mlp;
          bundle.reconstruction = options.reconstruction;
          bundle.metrics = Json{{"run_id", run_id},
                                {"validation", result.validation.value("results", Json::object())}};
          const std::vector<std::uint8_t> bytes = WriteModelBundle(result.model_path, bundle);
          OnnxExportOptions onnx;
          for (double sigma : options.reconstruction.difference.context_sigmas_px) {
            onnx.input_description +=
                ", then dR/du, dR/dv, dG/du, dG/dv, dB/du, dB/dv (per px) of the change smoothed "
                "by a Gaussian of sigma " +
                std::to_string(sigma) + " px";
          }
          WriteOnnxFile(result.onnx_path, mlp, onnx);
          const auto existing = db.GetModel(name, version);
          if (!existing) {
            db.PutModel(name, version, bytes, Json{{"file", result.model_path.string()}}.dump(),
                        run_id);
          }
          (*metrics)["model"] = result.model_path.string();
          (*metrics)["onnx"] = result.onnx_path.string();
          (*metrics)["bundle_bytes"] = bytes.size();
          (*metrics)["onnx_bytes"] = std::filesystem::file_size(result.onnx_path);
          const std::string text = Json{{"model", result.model_path.string()}}.dump();
          return std::vector<std::uint8_t>(text.begin(), text.end());
        },
        nullptr,
        // The files are the product: write them again if someone deleted them.
        !std::filesystem::exists(result.model_path) || !std::filesystem::exists(result.onnx_path));
    std::filesystem::create_directories(dir);
    WriteTextFile(result.report_path, html);
    WriteTextFile(result.validation_path, result.validation.dump(2));
  }
  result.seconds = Since(t_start);
  return result;
}

}  // namespace gs360
