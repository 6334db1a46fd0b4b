#include "calib/pipeline.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>
#include <mutex>
#include <numeric>
#include <optional>
#include <stdexcept>
#include <thread>

#include <opencv2/imgcodecs.hpp>

#include "base/fields.h"
#include "base/hash.h"
#include "base/version.h"
#include "calib/onnx_export.h"
#include "calib/report.h"
#include "geometry/bvh.h"

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

// The stages' bookkeeping: cache lookup, forced re-runs, the selection, reports.
class StageRunner {
 public:
  StageRunner(RunDatabase& db, std::int64_t run_id, const CalibrationOptions& options,
              const CalibrationLog& log, std::vector<StageReport>* reports)
      : db_(db), run_id_(run_id), log_(log), reports_(reports) {
    const int n = static_cast<int>(CalibrationStages().size());
    from_index_ = options.from_stage.empty() ? n : IndexOf(options.from_stage);
    if (!options.only_stage.empty()) only_index_ = IndexOf(options.only_stage);
  }

  static int IndexOf(const std::string& stage) {
    const auto& stages = CalibrationStages();
    const auto it = std::find(stages.begin(), stages.end(), stage);
    if (it == stages.end()) throw std::logic_error("no calibration stage " + stage);
    return static_cast<int>(it - stages.begin());
  }

  // Returns the stage's blob: the cached one, or compute()'s (stored).
  // `force`: run even if cached (e.g. the stage's files were deleted).
  template <typename Compute>
  std::vector<std::uint8_t> Run(const std::string& stage, const std::string& hash, Compute compute,
                                Json* metrics_out = nullptr, bool force = false) {
    const auto t0 = Clock::now();
    const int index = IndexOf(stage);
    StageReport report;
    report.stage = stage;
    report.input_hash = hash;
    std::vector<std::uint8_t> blob;
    std::optional<ArtifactRecord> cached;
    const bool forced = force || index >= from_index_ || index == only_index_;
    if (!forced) cached = db_.GetArtifact(run_id_, stage, hash);
    if (cached) {
      blob = std::move(cached->blob);
      report.cached = true;
      report.metrics = Json::parse(cached->metrics_json);
      Log(stage, "cached (" + hash + ")");
    } else {
      if (only_index_ >= 0 && index < only_index_) {
        throw std::runtime_error("calibrate: only " + CalibrationStages()[only_index_] +
                                 " was asked for, but its input " + stage +
                                 " has no stored result for these options; run `gs360 "
                                 "calibrate --to " +
                                 stage + "` first");
      }
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
  int only_index_ = -1;
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

// The probes' samples in probe order, as one dataset (split not yet assigned).
Dataset MergeProbeSamples(const std::vector<Dataset>& parts, const std::vector<ProbeInfo>& probes,
                          int features) {
  Dataset all;
  std::size_t n = 0;
  for (const Dataset& p : parts) n += p.probe.size();
  all.x.resize(features, static_cast<Eigen::Index>(n));
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
  return all;
}

// One calibration call: the stages as member functions sharing what upstream stages produced.
// Each stage computes its key from its StageSpec (StageKey), then runs or loads its artifact.
// Where the train stage keeps its per-epoch state (an artifact beside the stages' own).
constexpr const char* kTrainCheckpointStage = "train-checkpoint";

class Calibration {
 public:
  Calibration(RunDatabase& db, std::int64_t run_id, const CalibrationInputs& inputs,
              const CalibrationOptions& options, const ValidationTruth* truth,
              const CalibrationLog& log)
      : db_(db),
        run_id_(run_id),
        inputs_(inputs),
        options_(options),
        truth_(truth),
        options_json_(FieldsToJson(options)),
        runner_(db, run_id, options, log, &result_.stages) {}

  CalibrationResult Run() {
    using Step = void (Calibration::*)();
    static const std::map<std::string, Step> kSteps = {
        {"intrinsics", &Calibration::Intrinsics},
        {"impressions", &Calibration::Impressions},
        {"pose", &Calibration::Pose},
        {"surface_map", &Calibration::BuildSurfaceMap},
        {"render", &Calibration::Render},
        {"dataset", &Calibration::BuildDataset},
        {"train", &Calibration::TrainMlp},
        {"validate", &Calibration::ValidateModel},
        {"export", &Calibration::Export}};
    const auto t_start = Clock::now();
    LoadProbes();
    const std::string& last = !options_.only_stage.empty() ? options_.only_stage
                              : !options_.to_stage.empty() ? options_.to_stage
                                                           : CalibrationStages().back();
    for (const std::string& stage : CalibrationStages()) {
      (this->*kSteps.at(stage))();
      if (stage == last) break;
    }
    result_.seconds = Since(t_start);
    return std::move(result_);
  }

 private:
  // The stage's key from its spec, recorded for the stages downstream.
  const std::string& Key(const std::string& stage) {
    const auto& specs = CalibrationStageSpecs();
    const auto it = std::find_if(specs.begin(), specs.end(),
                                 [&](const StageSpec& s) { return s.name == stage; });
    keys_[stage] = StageKey(*it, options_json_, keys_);
    return keys_[stage];
  }

  const FisheyeCamera& Camera() const { return *camera_; }

  const Bvh& GelBvh() {
    if (!gel_bvh_) gel_bvh_ = std::make_unique<Bvh>(inputs_.gel_mesh);
    return *gel_bvh_;
  }
  const Bvh* FinBvh() {
    if (!fin_bvh_ && !inputs_.fin_mesh.Empty()) fin_bvh_ = std::make_unique<Bvh>(inputs_.fin_mesh);
    return fin_bvh_.get();
  }

  void LoadProbes();
  void Intrinsics();
  void Impressions();
  void Pose();
  void BuildSurfaceMap();
  void Render();
  void BuildDataset();
  void TrainMlp();
  TrainCheckpointing TrainCheckpoints(const std::string& key);
  void ValidateModel();
  Json ValidateProbes();
  void Export();
  Json ExportModel(const std::string& name, const std::string& version);

  struct Found {
    bool ok = false;
    Eigen::Vector2d centroid = Eigen::Vector2d::Zero();
    double peak = 0.0;
    int pixels = 0;
    bool near = false;  // near where the nominal pose puts the press (not stored)
  };

  RunDatabase& db_;
  std::int64_t run_id_;
  const CalibrationInputs& inputs_;
  const CalibrationOptions& options_;
  const ValidationTruth* truth_;
  const Json options_json_;
  CalibrationResult result_;
  StageRunner runner_;
  std::map<std::string, std::string> keys_;  // every input's and finished stage's key

  std::vector<ProbeInfo> probes_;
  std::optional<FisheyeCamera> camera_;
  std::unique_ptr<Bvh> gel_bvh_, fin_bvh_;
  std::vector<Found> impressions_;
  Json pose_metrics_;
  std::shared_ptr<const SurfaceMap> map_;
  std::map<int, ProbeRender> renders_;
  Dataset dataset_;
  Mlp mlp_;
  std::vector<TrainEpoch> curve_;
  cv::Mat reference_;
  std::string html_;
};

// The captured probes, their frames, and the keys of the inputs that are not stages.
void Calibration::LoadProbes() {
  const auto run = db_.GetRun(run_id_);
  if (!run) {
    throw std::runtime_error("calibrate: no run " + std::to_string(run_id_) + " in " +
                             db_.path().string());
  }
  const Rigid3d sensor_from_machine = inputs_.machine_from_sensor.Inverse();
  Hasher frames_hash;
  for (const CapturedProbe& cp : db_.ListCapturedProbes(run_id_)) {
    if (options_.plan_index_limit > 0 && cp.probe.plan_index >= options_.plan_index_limit) {
      continue;
    }
    ProbeInfo p;
    p.plan_index = cp.probe.plan_index;
    p.frame_id = cp.frame_id;
    p.point_sensor = cp.probe.plan.point_sensor;
    p.normal_sensor = cp.probe.plan.normal_sensor;
    const Eigen::Vector3d mpos = cp.probe.machine_position.value_or(cp.probe.plan.press_machine);
    p.ball_sensor = sensor_from_machine * (mpos + inputs_.tool_offset);
    const auto ref = db_.NearestReferenceFrame(run_id_, cp.frame_time);
    if (!ref) {
      throw std::runtime_error("calibrate: run " + std::to_string(run_id_) +
                               " has no reference frame");
    }
    p.reference_id = ref->id;
    const auto info = db_.GetFrameInfo(p.frame_id);
    frames_hash.AddPod(p.plan_index).Add(info ? info->checksum : std::string("?"));
    frames_hash.Add(ref->checksum);
    frames_hash.AddDouble(p.ball_sensor.x())
        .AddDouble(p.ball_sensor.y())
        .AddDouble(p.ball_sensor.z());
    probes_.push_back(p);
  }
  if (probes_.size() < 20) {
    throw std::runtime_error("calibrate: run " + std::to_string(run_id_) + " has " +
                             std::to_string(probes_.size()) + " captured probes" +
                             (options_.plan_index_limit > 0
                                  ? " below plan index " + std::to_string(options_.plan_index_limit)
                                  : std::string()) +
                             "; the calibration needs at least 20");
  }
  keys_["frames"] = frames_hash.Hex();
  Hasher geometry;
  HashMesh(geometry, inputs_.gel_mesh);
  HashMesh(geometry, inputs_.fin_mesh);
  geometry.AddDouble(inputs_.ball_radius);
  keys_["geometry"] = geometry.Hex();
  keys_["nominal_intrinsics"] =
      Hasher().Add(IntrinsicsToJson(inputs_.nominal_intrinsics).dump()).Hex();
  Hasher pose;
  HashPose(pose, inputs_.nominal_cam_from_sensor);
  keys_["nominal_pose"] = pose.Hex();
  keys_["truth"] =
      Hasher().Add(truth_ != nullptr ? truth_->Describe() : std::string("no truth")).Hex();
}

void Calibration::Intrinsics() {
  Hasher boards;
  std::vector<cv::Mat> images;
  // A truncated or undecodable file is one rejected image (an empty Mat), PNG and JPEG alike.
  std::vector<std::string> unreadable;
  for (const auto& path : inputs_.checkerboard_images) {
    std::ifstream in(path, std::ios::binary);
    if (!in)
      throw std::runtime_error("intrinsics: cannot read checkerboard image " + path.string());
    std::vector<std::uint8_t> bytes((std::istreambuf_iterator<char>(in)),
                                    std::istreambuf_iterator<char>());
    boards.Add(bytes.data(), bytes.size());
    std::optional<std::string> problem = ImageFileProblem(bytes);
    cv::Mat img;
    if (!problem) img = cv::imdecode(bytes, cv::IMREAD_GRAYSCALE);
    if (!problem && img.empty()) problem = "not a decodable image";
    unreadable.push_back(problem.value_or(""));
    images.push_back(problem ? cv::Mat() : img);
  }
  keys_["checkerboards"] = boards.Hex();
  const auto blob = runner_.Run("intrinsics", Key("intrinsics"), [&](Json* metrics) {
    Json out;
    if (images.empty()) {
      out = IntrinsicsToJson(inputs_.nominal_intrinsics);
      (*metrics)["source"] = "nominal (no checkerboard images given)";
    } else {
      IntrinsicsResult r;
      try {
        r = CalibrateIntrinsics(images, inputs_.nominal_intrinsics, options_.intrinsics);
      } catch (const std::exception& e) {
        std::string message = std::string("intrinsics: ") + e.what();
        for (std::size_t i = 0; i < unreadable.size(); ++i) {
          if (unreadable[i].empty()) continue;
          message +=
              "; " + inputs_.checkerboard_images[i].filename().string() + ": " + unreadable[i];
        }
        throw std::runtime_error(message);
      }
      for (IntrinsicsImageReport& image : r.images) {
        const std::string& why = unreadable[static_cast<std::size_t>(image.index)];
        if (!why.empty()) image.reason = why;
      }
      out = IntrinsicsToJson(r.intrinsics);
      (*metrics)["source"] = "checkerboards";
      (*metrics)["rms_px"] = r.rms_px;
      (*metrics)["images_used"] = r.used.size();
      (*metrics)["images_rejected"] = r.rejected.size();
      (*metrics)["radial_coverage"] = r.radial_coverage;
      Json per_image = Json::array();
      for (const IntrinsicsImageReport& image : r.images) {
        per_image.push_back(
            {{"file",
              inputs_.checkerboard_images[static_cast<std::size_t>(image.index)].filename()},
             {"used", image.used},
             {"reason", image.reason},
             {"corners", image.corners},
             {"rms_px", image.rms_px}});
      }
      (*metrics)["images"] = std::move(per_image);
    }
    (*metrics)["intrinsics"] = out;
    const std::string text = out.dump();
    return std::vector<std::uint8_t>(text.begin(), text.end());
  });
  result_.intrinsics = IntrinsicsFromJson(Json::parse(FromBytes(blob)));
  camera_.emplace(result_.intrinsics);
}

void Calibration::Impressions() {
  const auto blob = runner_.Run("impressions", Key("impressions"), [&](Json* metrics) {
    std::vector<Found> found(probes_.size());
    std::vector<FrameLoader> loaders(static_cast<std::size_t>(options_.threads));
    ParallelOverProbes(
        db_.path(), probes_.size(), options_.threads, [&](std::size_t k, int t, RunDatabase& conn) {
          FrameLoader& fl = loaders[static_cast<std::size_t>(t)];
          const cv::Mat press = fl.Press(conn, probes_[k]);
          const cv::Mat ref = fl.Reference(conn, probes_[k]);
          const auto imp = FindImpressionRegion(
              press, ref, options_.impression, {},
              Camera().ProjectUnchecked(inputs_.nominal_cam_from_sensor * probes_[k].point_sensor));
          if (imp) found[k] = {true, imp->centroid, imp->peak_dn, imp->pixels, imp->near_expected};
        });
    (*metrics)["far_from_nominal_dropped"] = DropFarFromNominal(found, &Found::ok, &Found::near);
    std::vector<std::uint8_t> out;
    int ok = 0;
    for (const Found& f : found) {
      PutPod(&out, static_cast<std::uint8_t>(f.ok));
      PutPod(&out, f.centroid.x()), PutPod(&out, f.centroid.y());
      PutPod(&out, f.peak), PutPod(&out, static_cast<std::int32_t>(f.pixels));
      ok += f.ok ? 1 : 0;
    }
    (*metrics)["probes"] = probes_.size();
    (*metrics)["impressions_found"] = ok;
    return out;
  });
  impressions_.assign(probes_.size(), Found{});
  ByteReader r(blob, "impressions");
  for (Found& f : impressions_) {
    f.ok = r.Pod<std::uint8_t>() != 0;
    const double x = r.Pod<double>(), y = r.Pod<double>();
    f.centroid = Eigen::Vector2d(x, y);
    f.peak = r.Pod<double>();
    f.pixels = r.Pod<std::int32_t>();
  }
}

void Calibration::Pose() {
  const auto compute = [&](Json* metrics) {
    std::vector<PoseObservation> obs;
    for (std::size_t k = 0; k < probes_.size(); ++k) {
      if (!impressions_[k].ok) continue;
      PoseObservation o;
      o.probe_index = probes_[k].plan_index;
      o.contact_point_sensor = probes_[k].point_sensor;
      o.contact_normal_sensor = probes_[k].normal_sensor;
      o.ball_center_sensor = probes_[k].ball_sensor;
      o.centroid_px = impressions_[k].centroid;
      o.region_px = impressions_[k].pixels;
      obs.push_back(o);
    }
    PoseResult r;
    try {
      PoseOptions run_options = options_.pose;
      run_options.ball_radius_mm = inputs_.ball_radius;
      run_options.threads = options_.threads;
      r = EstimateCamFromSensor(Camera(), obs, inputs_.nominal_cam_from_sensor, run_options,
                                PoseScene{&GelBvh(), FinBvh(), options_.impression});
    } catch (const std::exception& e) {
      throw std::runtime_error(std::string("pose: ") + e.what());
    }
    const Rigid3d& nominal = inputs_.nominal_cam_from_sensor;
    (*metrics)["observations"] = obs.size();
    (*metrics)["rms_px"] = r.rms_px;
    (*metrics)["paper_rms_px"] = r.paper_rms_px;
    (*metrics)["condition"] = r.condition;
    (*metrics)["inliers"] = r.inliers;
    (*metrics)["paper_inliers"] = r.paper_inliers;
    (*metrics)["bias_rounds"] = r.bias_rounds;
    (*metrics)["mean_bias_px"] = r.mean_bias_px;
    (*metrics)["outliers"] = r.outliers;
    (*metrics)["oblique_excluded"] = r.oblique;
    (*metrics)["spread_excluded"] = r.spread;
    (*metrics)["view_bound_deg"] = r.view_bound_deg;
    (*metrics)["moved_from_nominal_mm"] = TranslationDifferenceMm(r.cam_from_sensor, nominal);
    (*metrics)["moved_from_nominal_deg"] =
        RotationDifferenceRad(r.cam_from_sensor, nominal) * 180.0 / M_PI;
    const std::string text = Json{{"cam_from_sensor", PoseToJson(r.cam_from_sensor)},
                                  {"paper_cam_from_sensor", PoseToJson(r.paper_cam_from_sensor)}}
                                 .dump();
    return std::vector<std::uint8_t>(text.begin(), text.end());
  };
  const auto blob = runner_.Run("pose", Key("pose"), compute, &pose_metrics_);
  const Json pose = Json::parse(FromBytes(blob));
  result_.cam_from_sensor = PoseFromJson(pose.at("cam_from_sensor"));
  const auto true_pose = truth_ != nullptr ? truth_->TrueCamFromSensor() : std::nullopt;
  if (true_pose) {
    const Rigid3d paper = PoseFromJson(pose.at("paper_cam_from_sensor"));
    pose_metrics_["error_mm"] = TranslationDifferenceMm(result_.cam_from_sensor, *true_pose);
    pose_metrics_["error_deg"] =
        RotationDifferenceRad(result_.cam_from_sensor, *true_pose) * 180.0 / M_PI;
    pose_metrics_["paper_error_mm"] = TranslationDifferenceMm(paper, *true_pose);
    pose_metrics_["paper_error_deg"] = RotationDifferenceRad(paper, *true_pose) * 180.0 / M_PI;
  }
}

// The surface map at the calibrated pose.
void Calibration::BuildSurfaceMap() {
  SurfaceMapOptions mo = options_.surface_map;
  mo.threads = options_.threads;
  const auto blob = runner_.Run("surface_map", Key("surface_map"), [&](Json* metrics) {
    const SurfaceMap m =
        SurfaceMap::Build(Camera(), result_.cam_from_sensor, GelBvh(), FinBvh(), mo);
    (*metrics)["visible"] = m.stats().visible;
    (*metrics)["fin"] = m.stats().fin;
    (*metrics)["grazing"] = m.stats().grazing;
    (*metrics)["no_hit"] = m.stats().no_hit;
    (*metrics)["build_seconds"] = m.stats().build_seconds;
    return m.Serialize();
  });
  map_ = std::make_shared<const SurfaceMap>(SurfaceMap::Deserialize(blob));
}

void Calibration::Render() {
  const auto blob = runner_.Run("render", Key("render"), [&](Json* metrics) {
    std::vector<std::pair<int, ProbeRender>> out(probes_.size());
    std::vector<std::thread> pool;
    const int threads = options_.threads;
    auto work = [&](int t) {
      for (std::size_t k = static_cast<std::size_t>(t); k < probes_.size();
           k += static_cast<std::size_t>(threads)) {
        out[k] = {probes_[k].plan_index,
                  RenderProbe(*map_, Camera(), result_.cam_from_sensor * probes_[k].ball_sensor,
                              inputs_.ball_radius, options_.render)};
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
  renders_ = RendersFromSparse(blob, *map_);
}

void Calibration::BuildDataset() {
  // The sample budget becomes a per-probe cap over the probes that will contribute.
  std::size_t contributing = 0;
  for (const auto& [index, render] : renders_) {
    contributing += render.contact_pixels >= options_.dataset.min_contact_pixels ? 1 : 0;
  }
  DatasetOptions d = options_.dataset;
  d.max_contact_samples_per_probe = d.ContactSamplesPerProbe(contributing);
  keys_["samples_per_probe"] = std::to_string(d.max_contact_samples_per_probe);
  const DifferenceOptions& difference = options_.reconstruction.difference;
  const auto blob = runner_.Run("dataset", Key("dataset"), [&](Json* metrics) {
    const cv::Mat visible = map_->VisibleMask();
    std::vector<Dataset> parts(probes_.size());
    std::vector<FrameLoader> loaders(static_cast<std::size_t>(options_.threads));
    ParallelOverProbes(
        db_.path(), probes_.size(), options_.threads, [&](std::size_t k, int t, RunDatabase& conn) {
          auto it = renders_.find(probes_[k].plan_index);
          if (it == renders_.end() || it->second.contact_pixels < d.min_contact_pixels) return;
          FrameLoader& fl = loaders[static_cast<std::size_t>(t)];
          const cv::Mat diff = NormalizedDifference(
              fl.Press(conn, probes_[k]), fl.Reference(conn, probes_[k]), visible, difference);
          cv::Mat penetration;
          if (d.edge_exclusion_mm > 0.0) {
            penetration = NormalPenetration(*map_, it->second.roi,
                                            result_.cam_from_sensor * probes_[k].ball_sensor,
                                            inputs_.ball_radius);
          }
          const cv::Mat context =
              ContextFeatures(diff, visible, it->second.roi, difference.context_sigmas_px);
          AppendProbeSamples(diff, it->second, probes_[k].plan_index, d, &parts[k], penetration,
                             context);
        });
    Dataset all = MergeProbeSamples(parts, probes_, FeatureCount(difference));
    if (all.probes.size() < 10) {
      throw std::runtime_error("dataset: only " + std::to_string(all.probes.size()) +
                               " probes have a rendered contact of at least " +
                               std::to_string(d.min_contact_pixels) +
                               " pixels; is the camera pose right?");
    }
    all.probe_split = SplitProbes(all.probes, d);
    (*metrics)["samples"] = all.probe.size();
    (*metrics)["contact_samples_per_probe"] = d.max_contact_samples_per_probe;
    (*metrics)["probes"] = all.probes.size();
    (*metrics)["train_samples"] = all.Count(Split::kTrain);
    (*metrics)["validation_samples"] = all.Count(Split::kValidation);
    (*metrics)["test_probes"] = all.ProbesIn(Split::kTest).size();
    return all.Serialize();
  });
  dataset_ = Dataset::Deserialize(blob);
}

// The training's state after each epoch, under the train stage's key: a calibration killed
// while it trains resumes after the last finished epoch, with the result of an uninterrupted one.
TrainCheckpointing Calibration::TrainCheckpoints(const std::string& key) {
  TrainCheckpointing checkpoints;
  try {
    if (auto saved = db_.GetArtifact(run_id_, kTrainCheckpointStage, key)) {
      const int epoch = TrainCheckpointEpoch(saved->blob);
      checkpoints.resume_from = std::move(saved->blob);
      runner_.Log("train", "resuming from the checkpoint after epoch " + std::to_string(epoch));
    }
  } catch (const std::exception& e) {  // corrupt or foreign: start over, say so
    runner_.Log("train", std::string("the checkpoint cannot be used (") + e.what() +
                             "): training from the first epoch");
  }
  checkpoints.save = [this, key](int epoch, const std::vector<std::uint8_t>& state) {
    db_.PutArtifact(run_id_, kTrainCheckpointStage, key, state, Json{{"epoch", epoch}}.dump());
  };
  return checkpoints;
}

void Calibration::TrainMlp() {
  TrainOptions to = options_.train;
  to.threads = options_.threads;
  Json metrics_out;
  const std::string key = Key("train");
  const auto blob = runner_.Run(
      "train", key,
      [&](Json* metrics) {
        const Eigen::MatrixXf xt = dataset_.X(Split::kTrain), yt = dataset_.Y(Split::kTrain);
        const Eigen::MatrixXf xv = dataset_.X(Split::kValidation),
                              yv = dataset_.Y(Split::kValidation);
        auto log = [&](int epoch, double tl, double vl) {
          if (epoch % 5 == 0) {
            runner_.Log("train", "epoch " + std::to_string(epoch) + ": train loss " +
                                     std::to_string(tl) + ", validation loss " +
                                     std::to_string(vl));
          }
        };
        TrainCheckpointing checkpoints = TrainCheckpoints(key);
        TrainResult r;
        try {
          r = Train(xt, yt, xv, yv, to, log, checkpoints);
        } catch (const std::invalid_argument& e) {
          if (checkpoints.resume_from.empty()) throw;
          runner_.Log("train", std::string("the checkpoint does not fit (") + e.what() +
                                   "): training from the first epoch");
          checkpoints.resume_from.clear();
          r = Train(xt, yt, xv, yv, to, log, checkpoints);
        }
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
  mlp_ = Mlp::Deserialize(blob);
  for (const auto& e : metrics_out.value("curve", Json::array())) {
    curve_.push_back({e[0].get<int>(), e[1].get<double>(), e[2].get<double>(), e[3].get<double>(),
                      e[4].get<double>()});
  }
  // The reference the model ships with: the run's latest no-contact frame.
  const auto latest_ref = db_.LatestFrame(run_id_, FrameKind::kReference);
  if (!latest_ref) throw std::runtime_error("calibrate: run has no reference frame");
  reference_ = db_.LoadFrame(latest_ref->id);
}

void Calibration::ValidateModel() {
  const auto blob = runner_.Run("validate", Key("validate"), [&](Json* metrics) {
    const Json out = ValidateProbes();
    (*metrics)["summary"] = out.at("validation");
    const std::string text = out.dump();
    return std::vector<std::uint8_t>(text.begin(), text.end());
  });
  const Json out = Json::parse(FromBytes(blob));
  result_.validation = out.at("validation");
  html_ = out.at("html").get<std::string>();
}

// The held-out probes through the reconstructor: {"validation": ..., "html": the report}.
Json Calibration::ValidateProbes() {
  const Reconstructor reconstructor(map_, Camera(), mlp_, reference_, options_.reconstruction);
  std::map<int, std::size_t> by_index;
  for (std::size_t k = 0; k < probes_.size(); ++k) by_index[probes_[k].plan_index] = k;
  const std::vector<std::int32_t> test = dataset_.ProbesIn(Split::kTest);
  const std::vector<int> held_out(test.begin(), test.end());
  const int threads = options_.validation.threads;
  std::vector<std::unique_ptr<RunDatabase>> conns;
  std::vector<FrameLoader> loaders(static_cast<std::size_t>(threads));
  for (int t = 0; t < threads; ++t) {
    RunDatabaseOptions ro;
    ro.read_only = true;
    conns.push_back(std::make_unique<RunDatabase>(db_.path(), ro));
  }
  const ValidationProbeLoader load = [&](int plan_index, int thread) {
    const ProbeInfo& p = probes_[by_index.at(plan_index)];
    ValidationProbe vp;
    vp.plan_index = plan_index;
    vp.contact_point_sensor = p.point_sensor;
    vp.ball_center_sensor = p.ball_sensor;
    RunDatabase& conn = *conns[static_cast<std::size_t>(thread)];
    vp.frame = loaders[static_cast<std::size_t>(thread)].Press(conn, p);
    vp.reference = loaders[static_cast<std::size_t>(thread)].Reference(conn, p);
    return vp;
  };
  const double height = inputs_.gel_mesh.Bounds().max().z();
  ValidationResult v = Validate(reconstructor, held_out, load, inputs_.ball_radius, height, truth_,
                                options_.validation);
  v.report["pose"] = pose_metrics_;
  // Per evaluated probe: contact point (sensor frame, mm) and mean depth error (mm), for error
  // maps outside the HTML report (the daemon's dashboard).
  Json probe_errors = Json::array();
  for (const auto& [point, error] : v.probe_errors) {
    probe_errors.push_back({point.x(), point.y(), point.z(), error});
  }
  v.report["probe_errors"] = probe_errors;
  v.report["coverage_gaps"] = inputs_.coverage_gaps;
  // Captured probes the dataset left out, by reason (the dataset stage's rule).
  int unseen = 0, small = 0;
  for (const ProbeInfo& p : probes_) {
    const auto it = renders_.find(p.plan_index);
    const int pixels = it == renders_.end() ? 0 : it->second.contact_pixels;
    unseen += pixels == 0 ? 1 : 0;
    small += pixels > 0 && pixels < options_.dataset.min_contact_pixels ? 1 : 0;
  }
  v.report["probes_captured"] = probes_.size();
  v.report["probes_dropped"] = {{"no_contact_seen", unseen},
                                {"below_min_contact_pixels", small},
                                {"min_contact_pixels", options_.dataset.min_contact_pixels}};
  v.report["warnings"] = CalibrationWarnings(v.report, curve_, dataset_.probes.size());
  if (inputs_.convergence.is_array() && !inputs_.convergence.empty()) {
    v.report["convergence"] = ConvergencePoints(inputs_.convergence, v.report, probes_.size());
  }
  ReportInputs ri;
  ri.title = "gs360 calibration: run " + std::to_string(run_id_) + " (" + inputs_.sensor + ")";
  ri.validation = v.report;
  Json stages = Json::array();
  for (const StageReport& s : result_.stages) {
    stages.push_back({{"stage", s.stage},
                      {"input_hash", s.input_hash},
                      {"cached", s.cached},
                      {"seconds", s.seconds},
                      {"metrics", s.metrics}});
  }
  ri.stages = stages;
  ri.curve = curve_;
  ri.examples = v.examples;
  ri.probe_errors = v.probe_errors;
  ri.gel_height_mm = height;
  ri.coverage_gaps = inputs_.coverage_gaps;
  return Json{{"validation", v.report}, {"html", RenderReportHtml(ri)}};
}

void Calibration::Export() {
  const std::filesystem::path dir = options_.export_dir.empty()
                                        ? std::filesystem::absolute(db_.path()).parent_path()
                                        : options_.export_dir;
  keys_["export_dir"] = Hasher().Add(dir.string()).Hex();
  const std::string name =
      options_.model_name.empty() ? "run-" + std::to_string(run_id_) : options_.model_name;
  const std::string version =
      options_.model_version.empty() ? keys_.at("train").substr(0, 8) : options_.model_version;
  const std::string stem = name + "-" + version;
  result_.model_path = dir / (stem + ".gs360model");
  result_.onnx_path = dir / (stem + ".onnx");
  result_.report_path = dir / (stem + "-report.html");
  result_.validation_path = dir / (stem + "-validation.json");
  runner_.Run(
      "export", Key("export"),
      [&](Json* metrics) {
        std::filesystem::create_directories(dir);
        *metrics = ExportModel(name, version);
        const std::string text = Json{{"model", result_.model_path.string()}}.dump();
        return std::vector<std::uint8_t>(text.begin(), text.end());
      },
      nullptr,
      // The files are the product: write them again if someone deleted them.
      !std::filesystem::exists(result_.model_path) || !std::filesystem::exists(result_.onnx_path));
  std::filesystem::create_directories(dir);
  WriteTextFile(result_.report_path, html_);
  WriteTextFile(result_.validation_path, result_.validation.dump(2));
}

// Writes the bundle and the ONNX file, records the model; returns the stage's metrics.
Json Calibration::ExportModel(const std::string& name, const std::string& version) {
  ModelBundle bundle;
  bundle.name = name;
  bundle.version = version;
  bundle.gs360_version = std::string(Version());
  bundle.created_at = static_cast<double>(std::chrono::duration_cast<std::chrono::seconds>(
                                              std::chrono::system_clock::now().time_since_epoch())
                                              .count());
  bundle.sensor = inputs_.sensor;
  bundle.intrinsics = result_.intrinsics;
  bundle.cam_from_sensor = result_.cam_from_sensor;
  bundle.gel_mesh = inputs_.gel_mesh;
  bundle.fin_mesh = inputs_.fin_mesh;
  bundle.surface_map = options_.surface_map;
  bundle.reference = reference_;
  bundle.mlp = mlp_;
  bundle.reconstruction = options_.reconstruction;
  bundle.metrics = Json{{"run_id", run_id_},
                        {"validation", result_.validation.value("results", Json::object())}};
  const std::vector<std::uint8_t> bytes = WriteModelBundle(result_.model_path, bundle);
  OnnxExportOptions onnx;
  for (double sigma : options_.reconstruction.difference.context_sigmas_px) {
    onnx.input_description +=
        ", then dR/du, dR/dv, dG/du, dG/dv, dB/du, dB/dv (per px) of the change smoothed by a "
        "Gaussian of sigma " +
        std::to_string(sigma) + " px";
  }
  WriteOnnxFile(result_.onnx_path, mlp_, onnx);
  if (!db_.GetModel(name, version)) {
    db_.PutModel(name, version, bytes, Json{{"file", result_.model_path.string()}}.dump(), run_id_);
  }
  return Json{{"model", result_.model_path.string()},
              {"onnx", result_.onnx_path.string()},
              {"bundle_bytes", bytes.size()},
              {"onnx_bytes", std::filesystem::file_size(result_.onnx_path)}};
}

}  // namespace

CalibrationResult RunCalibration(RunDatabase& db, std::int64_t run_id,
                                 const CalibrationInputs& inputs, const CalibrationOptions& options,
                                 const ValidationTruth* truth, const CalibrationLog& log) {
  options.Check();
  return Calibration(db, run_id, inputs, options, truth, log).Run();
}

}  // namespace gs360
