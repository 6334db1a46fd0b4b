// Diagnostics of the pose stage on a stored run of the virtual rig (uses the simulator's truth).
// Usage: bench_pose_db --db RUN.db [--run 1] [--seed 1 | --config RIG.toml] [--cache FILE]
//                      [--simulate] [--csv FILE]
//
// Loads the run's captured probes (as calib/pipeline.cc does: MPos -> ball centre, nearest
// reference frame), finds each impression with FindImpressionRegion on the STORED frames, and
// compares every centroid with the truth: the true projection of the contact point and the hull
// centroid of the rigid imprint rendered through the true camera and pose (what the pose stage's
// bias model predicts at convergence). --simulate also renders each press straight from the
// simulator (TactileCamera::RenderAtBall at the same ball, the reference at run time 0), as
// bench_pose does, to separate the acquisition path from the scene. --cache keeps the per-probe
// measurements (the frame decoding is the slow part). Then runs EstimateCamFromSensor with the
// run's calibrated intrinsics (its intrinsics artifact) and with the true ones, and prints the
// pose errors and residual statistics by height, view angle and distance to the fins. --config: a
// run of a rig file with a [sim] table (`gs360 bench heldout`'s rig-N.toml, `gs360 demo --config`):
// the simulated rig (camera perturbation, lighting, noise) and its seed are read from it.

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <memory>
#include <numbers>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "calib/impression_centroid.h"
#include "calib/pose.h"
#include "calib/render.h"
#include "capture/impression.h"
#include "cli/calibrate_support.h"
#include "cli/heldout_rigs.h"
#include "cli/sim_args.h"
#include "cli/sim_bridge.h"
#include "recon/model_bundle.h"
#include "recon/surface_map.h"
#include "sim/ground_truth.h"
#include "sim/rig_model.h"
#include "sim/tactile_camera.h"
#include "sim/virtual_rig.h"
#include "storage/run_database.h"

namespace {

using namespace gs360;
using Clock = std::chrono::steady_clock;
constexpr double kRadToDeg = 180.0 / std::numbers::pi;

double Seconds(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

struct Row {
  int plan_index = 0;
  Eigen::Vector3d point = Eigen::Vector3d::Zero(), normal = Eigen::Vector3d::Zero();
  Eigen::Vector3d ball = Eigen::Vector3d::Zero();
  double frame_time = 0.0, ref_time = 0.0;
  bool found = false;
  Eigen::Vector2d centroid = Eigen::Vector2d::Zero();  // stored frames, FindImpressionRegion
  double peak = 0.0, area = 0.0;
  int pixels = 0;                                           // region pixels
  Eigen::Vector2d observed_hull = Eigen::Vector2d::Zero();  // the region's hull centroid
  bool near = false;  // the impression's peak lies near where the nominal pose puts the press
  bool sim_found = false;
  Eigen::Vector2d sim_centroid = Eigen::Vector2d::Zero();  // simulator, straight
  // truth
  Eigen::Vector2d proj = Eigen::Vector2d::Zero(), hull = Eigen::Vector2d::Zero();
  bool hull_ok = false;
  double view_deg = 0.0, fin_mm = 0.0, azimuth_deg = 0.0;
};

Eigen::Vector2d HullCentroid(const ProbeRender& pr, bool* ok) {
  std::vector<cv::Point> points, hull;
  for (int y = 0; y < pr.contact.rows; ++y) {
    for (int x = 0; x < pr.contact.cols; ++x) {
      if (pr.contact.at<std::uint8_t>(y, x)) points.emplace_back(pr.roi.x + x, pr.roi.y + y);
    }
  }
  *ok = points.size() >= 3;
  if (!*ok) return Eigen::Vector2d::Zero();
  cv::convexHull(points, hull);
  const cv::Moments m = cv::moments(hull);
  *ok = m.m00 > 0.0;
  return *ok ? Eigen::Vector2d(m.m10 / m.m00, m.m01 / m.m00) : Eigen::Vector2d::Zero();
}

// The cache's first line: what the measurements depend on besides the run (a cache made with
// other settings is measured again).
std::string CacheKey(const ImpressionCentroidOptions& o, bool global_peak) {
  std::ostringstream key;
  key.precision(17);
  key << "# impression";
  auto add = [&key](const char*, const auto& value) { key << ' ' << value; };
  ImpressionCentroidOptions::Fields(o, add);
  key << " global_peak " << global_peak;
  return key.str();
}

void SaveCache(const std::string& path, const std::string& key, const std::vector<Row>& rows) {
  std::ofstream out(path);
  out.precision(17);
  out << key << '\n';
  for (const Row& r : rows) {
    out << r.plan_index << ' ' << r.found << ' ' << r.centroid.x() << ' ' << r.centroid.y() << ' '
        << r.peak << ' ' << r.area << ' ' << r.sim_found << ' ' << r.sim_centroid.x() << ' '
        << r.sim_centroid.y() << ' ' << r.pixels << ' ' << r.observed_hull.x() << ' '
        << r.observed_hull.y() << ' ' << r.near << '\n';
  }
}

bool LoadCache(const std::string& path, const std::string& key, std::vector<Row>* rows,
               bool need_sim) {
  std::ifstream in(path);
  std::string line;
  if (!in || !std::getline(in, line) || line != key) return false;
  std::map<int, Row*> by_index;
  for (Row& r : *rows) by_index[r.plan_index] = &r;
  int n = 0;
  while (std::getline(in, line)) {
    std::istringstream s(line);
    int idx = 0;
    Row tmp;
    s >> idx >> tmp.found >> tmp.centroid.x() >> tmp.centroid.y() >> tmp.peak >> tmp.area >>
        tmp.sim_found >> tmp.sim_centroid.x() >> tmp.sim_centroid.y() >> tmp.pixels >>
        tmp.observed_hull.x() >> tmp.observed_hull.y() >> tmp.near;
    if (!s) return false;
    auto it = by_index.find(idx);
    if (it == by_index.end()) return false;
    Row& r = *it->second;
    r.found = tmp.found;
    r.centroid = tmp.centroid;
    r.peak = tmp.peak;
    r.area = tmp.area;
    r.sim_found = tmp.sim_found;
    r.sim_centroid = tmp.sim_centroid;
    r.pixels = tmp.pixels;
    r.observed_hull = tmp.observed_hull;
    r.near = tmp.near;
    if (need_sim && !tmp.sim_found && tmp.found) return false;
    ++n;
  }
  return n == static_cast<int>(rows->size());
}

struct Stats {
  int n = 0;
  Eigen::Vector2d mean = Eigen::Vector2d::Zero();
  double rms = 0.0;
};

void PrintPose(const char* name, const PoseResult& r, const Rigid3d& truth) {
  std::printf(
      "  %-44s %.4f mm %.4f deg | rms %.3f px, %d in, %d out, %d oblique (> %.1f deg), mean bias "
      "%.2f px, %.1f s\n",
      name, TranslationDifferenceMm(r.cam_from_sensor, truth),
      RotationDifferenceRad(r.cam_from_sensor, truth) * kRadToDeg, r.rms_px, r.inliers, r.outliers,
      r.oblique, r.view_bound_deg, r.mean_bias_px, r.seconds);
}

struct Args {
  std::string db_path, cache, csv, config;
  std::int64_t run_id = 1;
  std::uint64_t seed = 1;
  bool simulate = false;
  bool global_peak = false;  // the impression's peak anywhere in the frame (before issue 33)
  std::vector<int> dump;
  ImpressionCentroidOptions impression;
};

void AddOptions(CLI::App& app, Args& args) {
  app.option_defaults()->always_capture_default();
  app.add_option("--db", args.db_path, "the run database (RUN.db)")
      ->required()
      ->check(CLI::ExistingFile);
  app.add_option("--run", args.run_id, "run id in the database");
  app.add_option("--seed", args.seed, "seed of the simulated rig (as the run was made)");
  app.add_option("--config", args.config,
                 "the rig file the run was made from (its [sim] table and seed; not with --seed)")
      ->check(CLI::ExistingFile);
  app.add_option("--cache", args.cache,
                 "per-probe measurements cache, read if valid, else written");
  app.add_option("--csv", args.csv, "write one row per probe to this CSV file");
  app.add_flag("--global-peak", args.global_peak,
               "look for each impression's peak anywhere in the frame, not near its press");
  app.add_flag("--simulate", args.simulate,
               "also render each press straight from the simulator (TactileCamera::RenderAtBall)");
  ImpressionCentroidOptions& impression = args.impression;
  app.add_option("--fraction", impression.threshold_fraction,
                 "impression region: pixels above this fraction of the peak")
      ->check(CLI::Range(0.0, 1.0));
  app.add_option("--min-dn", impression.min_threshold_dn, "impression noise floor, DN")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--blur", impression.blur_sigma_px, "blur of the difference magnitude, pixels")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--min-peak", impression.min_peak_dn, "weaker impression peaks: none, DN")
      ->check(CLI::PositiveNumber);
  app.add_option("--dump", args.dump,
                 "write pose_dump_PLAN_INDEX.png around this probe's impression (repeatable)");
}

RunDatabaseOptions ReadOnly() {
  RunDatabaseOptions ro;
  ro.read_only = true;
  return ro;
}

// What the reports read: the run, the simulated rig it was made with (its truth) and one row per
// captured probe.
struct Bench {
  const Args& args;
  RunDatabase db;
  CalibrationInputs inputs;
  std::shared_ptr<const SimRig> rig;
  TactileCameraOptions sim_camera;  // the simulator's lighting and noise, for --simulate
  FisheyeCamera true_camera;
  Rigid3d true_pose;
  FisheyeCamera camera;  // the run's calibrated intrinsics, else the nominal ones
  std::vector<Row> rows;
  std::vector<std::int64_t> frame_ids, ref_ids;  // per row: the press and its reference frame
};

// Calibrated intrinsics: the run's latest intrinsics artifact.
std::optional<FisheyeIntrinsics> CalibratedIntrinsics(const RunDatabase& db, std::int64_t run_id) {
  std::optional<FisheyeIntrinsics> calibrated;
  for (const ArtifactRecord& a : db.ListArtifacts(run_id)) {
    if (a.stage != "intrinsics" || calibrated) continue;
    if (a.metrics_json.find("checkerboards") == std::string::npos) continue;
    const auto full = db.GetArtifact(run_id, a.stage, a.input_hash);
    calibrated = IntrinsicsFromJson(
        nlohmann::json::parse(std::string(full->blob.begin(), full->blob.end())));
  }
  return calibrated;
}

Bench LoadBench(const Args& args) {
  RunDatabase db(args.db_path, ReadOnly());
  const RunConfig config = StoredRunConfig(db, args.run_id);
  CalibrationInputs inputs = CalibrationInputsFor(config);
  // The simulated rig as the run was made: --seed's defaults, or the rig file's [sim] table.
  std::uint64_t seed = args.seed;
  cli::SimArgs sim_args;
  if (!args.config.empty()) {
    cli::HeldoutRig file;
    file.config = args.config;
    cli::LoadHeldoutRig(file, &sim_args, &seed);
  }
  VirtualRigOptions sim;
  sim.rig = cli::SimRigOptionsFor(config.rig, seed);
  sim.camera.sensor.seed = seed;
  cli::ApplySimArgs(sim_args, &sim);
  auto rig = std::make_shared<const SimRig>(sim.rig);
  const FisheyeCamera true_camera = SimGroundTruth::TrueCamera(*rig);
  const Rigid3d true_pose = SimGroundTruth::TrueCamFromSensor(*rig);
  const std::optional<FisheyeIntrinsics> calibrated = CalibratedIntrinsics(db, args.run_id);
  const FisheyeCamera camera(calibrated.value_or(inputs.nominal_intrinsics));
  std::printf("bench_pose_db: %s run %lld (%s), intrinsics %s\n", args.db_path.c_str(),
              static_cast<long long>(args.run_id), inputs.sensor.c_str(),
              calibrated ? "calibrated (artifact)" : "nominal");
  return Bench{args,
               std::move(db),
               std::move(inputs),
               std::move(rig),
               sim.camera,
               true_camera,
               true_pose,
               camera,
               {},
               {},
               {}};
}

// One row per captured probe, as calib/pipeline.cc builds them: MPos -> ball centre, nearest
// reference frame.
void LoadRows(Bench& b) {
  const std::int64_t run_id = b.args.run_id;
  const Rigid3d sensor_from_machine = b.inputs.machine_from_sensor.Inverse();
  for (const CapturedProbe& cp : b.db.ListCapturedProbes(run_id)) {
    Row r;
    r.plan_index = cp.probe.plan_index;
    r.point = cp.probe.plan.point_sensor;
    r.normal = cp.probe.plan.normal_sensor;
    const Eigen::Vector3d mpos = cp.probe.machine_position.value_or(cp.probe.plan.press_machine);
    r.ball = sensor_from_machine * (mpos + b.inputs.tool_offset);
    r.frame_time = cp.frame_time;
    const auto ref = b.db.NearestReferenceFrame(run_id, cp.frame_time);
    r.ref_time = ref->timestamp;
    b.rows.push_back(r);
    b.frame_ids.push_back(cp.frame_id);
    b.ref_ids.push_back(ref->id);
  }
  std::printf("  %zu captured probes\n", b.rows.size());
}

// Measures rows t, t + threads, ... on its own database connection (and simulator).
void MeasureStride(Bench& b, int t, int threads) {
  const ImpressionCentroidOptions& impression = b.args.impression;
  const std::size_t n = b.rows.size();
  RunDatabase conn(b.args.db_path, ReadOnly());
  std::map<std::int64_t, cv::Mat> refs;
  std::unique_ptr<TactileCamera> sim;
  cv::Mat sim_ref;
  if (b.args.simulate) {
    TactileCameraOptions to = b.sim_camera;
    to.threads = 1;
    sim = std::make_unique<TactileCamera>(b.rig, to);
    sim_ref = sim->RenderReference(900000 + static_cast<std::uint64_t>(t));
  }
  for (std::size_t k = static_cast<std::size_t>(t); k < n; k += threads) {
    Row& r = b.rows[k];
    const cv::Mat press = conn.LoadFrame(b.frame_ids[k]);
    auto it = refs.find(b.ref_ids[k]);
    if (it == refs.end()) it = refs.emplace(b.ref_ids[k], conn.LoadFrame(b.ref_ids[k])).first;
    std::optional<Eigen::Vector2d> expected;
    if (!b.args.global_peak) {
      expected = b.camera.ProjectUnchecked(b.inputs.nominal_cam_from_sensor * r.point);
    }
    if (const auto region = FindImpressionRegion(press, it->second, impression, {}, expected)) {
      r.found = true;
      r.centroid = region->centroid;
      r.peak = region->peak_dn;
      r.area = region->area_px;
      r.pixels = region->pixels;
      r.observed_hull = region->hull_centroid;
      r.near = region->near_expected;
    }
    if (sim) {
      const cv::Mat p = sim->RenderAtBall(r.ball, 100 + k);
      if (const auto region = FindImpressionRegion(p, sim_ref, impression)) {
        r.sim_found = true;
        r.sim_centroid = region->centroid;
      }
    }
  }
}

// The per-probe measurements, from --cache when it is valid (the frame decoding is the slow part).
void MeasureImpressions(Bench& b) {
  const std::string& cache = b.args.cache;
  const std::string key = CacheKey(b.args.impression, b.args.global_peak);
  if (!cache.empty() && LoadCache(cache, key, &b.rows, b.args.simulate)) return;
  const auto t0 = Clock::now();
  const int threads = 2;
  std::vector<std::thread> pool;
  for (int t = 1; t < threads; ++t) pool.emplace_back([&b, t] { MeasureStride(b, t, threads); });
  MeasureStride(b, 0, threads);
  for (auto& th : pool) th.join();
  const int found = static_cast<int>(
      std::count_if(b.rows.begin(), b.rows.end(), [](const Row& r) { return r.found; }));
  // As the pipeline (calib/pipeline.cc).
  const int far = b.args.global_peak ? 0 : DropFarFromNominal(b.rows, &Row::found, &Row::near);
  std::printf("  impressions in %.1f s, %d found, %d far from the nominal pose's pixel left out\n",
              Seconds(t0), found, far);
  if (!cache.empty()) SaveCache(cache, key, b.rows);
}

// Truth per probe.
void AddTruth(const SurfaceMap& true_map, Bench& b) {
  const FisheyeCamera& true_camera = b.true_camera;
  const Rigid3d& true_pose = b.true_pose;
  for (Row& r : b.rows) {
    r.proj = true_camera.ProjectUnchecked(true_pose * r.point);
    const ProbeRender pr =
        RenderProbe(true_map, true_camera, true_pose * r.ball, b.inputs.ball_radius);
    r.hull = HullCentroid(pr, &r.hull_ok);
    const Eigen::Vector3d c = true_pose * r.point;
    const Eigen::Vector3d n_cam = true_pose.RotateDirection(r.normal);
    r.view_deg = std::acos(std::abs(n_cam.dot(c.normalized()))) * kRadToDeg;
    r.fin_mm = std::min(std::abs(r.point.x()), std::abs(r.point.y()));
    r.azimuth_deg = std::atan2(r.point.y(), r.point.x()) * kRadToDeg;
  }
}

struct Observations {
  std::vector<PoseObservation> stored;  // the stored-frame centroids
  std::vector<const Row*> rows;         // per stored observation
  std::vector<PoseObservation> truth;   // the same probes at their true hull centroids
  std::vector<PoseObservation> sim;     // the same probes at the simulator's centroids
};

// Observations as the pipeline builds them.
Observations BuildObservations(const std::vector<Row>& rows) {
  Observations obs;
  for (const Row& r : rows) {
    if (!r.found) continue;
    PoseObservation o;
    o.probe_index = r.plan_index;
    o.contact_point_sensor = r.point;
    o.contact_normal_sensor = r.normal;
    o.ball_center_sensor = r.ball;
    o.centroid_px = r.centroid;
    o.region_px = r.pixels;
    obs.stored.push_back(o);
    obs.rows.push_back(&r);
    if (r.hull_ok) {
      o.centroid_px = r.hull;
      obs.truth.push_back(o);
    }
    if (r.sim_found) {
      o.centroid_px = r.sim_centroid;
      obs.sim.push_back(o);
    }
  }
  return obs;
}

using RowKey = double (*)(const Row&);
using RowCentroid = Eigen::Vector2d (*)(const Row&);

// Residual of the observed centroid against the true rigid hull centroid, in bins of `key`.
void PrintResidualBins(const Bench& b, const char* what, RowKey key,
                       const std::vector<double>& edges, RowCentroid centroid_of) {
  const FisheyeIntrinsics& intrinsics = b.true_camera.intrinsics();
  std::printf("  observed - true hull centroid, by %s:\n", what);
  for (std::size_t bin = 0; bin + 1 < edges.size(); ++bin) {
    std::vector<double> norms;
    Eigen::Vector2d mean = Eigen::Vector2d::Zero();
    Eigen::Vector2d radial_mean = Eigen::Vector2d::Zero();
    for (const Row& r : b.rows) {
      if (!r.found || !r.hull_ok) continue;
      const double k = key(r);
      if (k < edges[bin] || k >= edges[bin + 1]) continue;
      const Eigen::Vector2d e = centroid_of(r) - r.hull;
      norms.push_back(e.norm());
      mean += e;
      // Component along the image radius (from the principal point) and across it.
      const Eigen::Vector2d rad =
          (r.hull - Eigen::Vector2d(intrinsics.cx, intrinsics.cy)).normalized();
      radial_mean += Eigen::Vector2d(e.dot(rad), rad.x() * e.y() - rad.y() * e.x());
    }
    if (norms.empty()) continue;
    std::sort(norms.begin(), norms.end());
    const double m = static_cast<double>(norms.size());
    std::printf(
        "    [%7.1f, %7.1f): %4zu, median |e| %.2f px, p90 %.2f, mean (%.2f, %.2f), "
        "radial %.2f, tangential %.2f\n",
        edges[bin], edges[bin + 1], norms.size(), norms[norms.size() / 2],
        norms[norms.size() * 9 / 10], mean.x() / m, mean.y() / m, radial_mean.x() / m,
        radial_mean.y() / m);
  }
}

void PrintResiduals(const Bench& b) {
  auto stored = [](const Row& r) { return r.centroid; };
  PrintResidualBins(
      b, "height z (mm)", [](const Row& r) { return r.point.z(); },
      {0, 3, 6, 10, 15, 20, 25, 28, 31}, stored);
  PrintResidualBins(
      b, "view angle (deg)", [](const Row& r) { return r.view_deg; },
      {0, 20, 40, 50, 60, 70, 80, 90}, stored);
  PrintResidualBins(
      b, "distance to a fin plane (mm)", [](const Row& r) { return r.fin_mm; },
      {0, 0.5, 1, 1.5, 2, 3, 5, 100}, stored);
  PrintResidualBins(
      b, "peak (DN)", [](const Row& r) { return r.peak; }, {0, 10, 20, 40, 80, 1000}, stored);
  PrintResidualBins(
      b, "frame time - reference time (s)",
      [](const Row& r) { return std::abs(r.frame_time - r.ref_time); }, {0, 1, 2, 5, 10, 20, 1e9},
      stored);
  if (!b.args.simulate) return;
  auto simc = [](const Row& r) { return r.sim_found ? r.sim_centroid : r.hull; };
  std::printf("  --- simulator straight (same balls) ---\n");
  PrintResidualBins(
      b, "height z (mm)", [](const Row& r) { return r.point.z(); },
      {0, 3, 6, 10, 15, 20, 25, 28, 31}, simc);
  std::vector<double> d;
  for (const Row& r : b.rows) {
    if (r.found && r.sim_found) d.push_back((r.centroid - r.sim_centroid).norm());
  }
  std::sort(d.begin(), d.end());
  if (!d.empty()) {
    std::printf("  |stored - simulated| centroid: median %.3f px, p90 %.3f, max %.3f\n",
                d[d.size() / 2], d[d.size() * 9 / 10], d.back());
  }
}

// --dump PLAN_INDEX: the difference magnitude (x4 scale, 4x zoom) around the impression with the
// observed region (green), its hull centroid (green dot) and the true rigid contact (red) and its
// hull centroid (red dot), as PNG in the working directory.
void DumpProbe(const Bench& b, const SurfaceMap& true_map, int plan_index) {
  const std::size_t n = b.rows.size();
  std::size_t k = 0;
  while (k < n && b.rows[k].plan_index != plan_index) ++k;
  if (k == n) return;
  const Row& r = b.rows[k];
  const cv::Mat press = b.db.LoadFrame(b.frame_ids[k]), ref = b.db.LoadFrame(b.ref_ids[k]);
  const cv::Mat mag = DifferenceMagnitude(press, ref, cv::Mat(), 1.5, "dump");
  const ProbeRender pr =
      RenderProbe(true_map, b.true_camera, b.true_pose * r.ball, b.inputs.ball_radius);
  double peak = 0.0;
  cv::minMaxLoc(mag, nullptr, &peak);
  const int half = 40, zoom = 4;
  const cv::Rect box = cv::Rect(static_cast<int>(r.hull.x()) - half,
                                static_cast<int>(r.hull.y()) - half, 2 * half, 2 * half) &
                       cv::Rect(0, 0, mag.cols, mag.rows);
  cv::Mat grey;
  mag(box).convertTo(grey, CV_8U, 255.0 / peak);
  cv::Mat big;
  cv::resize(grey, big, cv::Size(), zoom, zoom, cv::INTER_NEAREST);
  cv::cvtColor(big, big, cv::COLOR_GRAY2BGR);
  cv::Mat crop_press;
  cv::resize(press(box), crop_press, cv::Size(), zoom, zoom, cv::INTER_NEAREST);
  const float thr = static_cast<float>(std::max(0.2 * peak, 3.0));
  cv::Mat above(box.size(), CV_8U, cv::Scalar(0)), contact(box.size(), CV_8U, cv::Scalar(0));
  for (int v = box.y; v < box.y + box.height; ++v) {
    for (int u = box.x; u < box.x + box.width; ++u) {
      above.at<std::uint8_t>(v - box.y, u - box.x) = mag.at<float>(v, u) > thr ? 255 : 0;
      const int x = u - pr.roi.x, y = v - pr.roi.y;
      if (x >= 0 && y >= 0 && x < pr.roi.width && y < pr.roi.height &&
          pr.contact.at<std::uint8_t>(y, x)) {
        contact.at<std::uint8_t>(v - box.y, u - box.x) = 255;
      }
    }
  }
  for (const auto& [m, col] :
       {std::pair{above, cv::Scalar(0, 255, 0)}, std::pair{contact, cv::Scalar(0, 0, 255)}}) {
    cv::Mat up;
    cv::resize(m, up, cv::Size(), zoom, zoom, cv::INTER_NEAREST);
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(up, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
    cv::drawContours(big, contours, -1, col, 1);
  }
  auto dot = [&](const Eigen::Vector2d& p, cv::Scalar col) {
    cv::circle(big,
               cv::Point(static_cast<int>((p.x() - box.x + 0.5) * zoom),
                         static_cast<int>((p.y() - box.y + 0.5) * zoom)),
               3, col, -1);
  };
  dot(r.centroid, cv::Scalar(0, 255, 0));
  dot(r.hull, cv::Scalar(0, 0, 255));
  cv::Mat both;
  cv::hconcat(big, crop_press, both);
  const std::string name = "pose_dump_" + std::to_string(plan_index) + ".png";
  cv::imwrite(name, both);
  std::printf("  dump %d: z %.2f view %.1f peak %.1f -> %s\n", plan_index, r.point.z(), r.view_deg,
              peak, name.c_str());
}

// The pose stage's settings and scene, shared by every estimate below.
struct PoseSetup {
  PoseOptions options;
  PoseScene scene;
};

// Returns the estimate from the stored frames with the calibrated intrinsics.
PoseResult PrintPoseEstimates(const Bench& b, const Observations& obs, const PoseSetup& setup) {
  const PoseOptions& options = setup.options;
  const PoseScene& scene = setup.scene;
  const Rigid3d& nominal = b.inputs.nominal_cam_from_sensor;
  std::printf("  true pose vs nominal: %.4f mm %.4f deg\n",
              TranslationDifferenceMm(b.true_pose, nominal),
              RotationDifferenceRad(b.true_pose, nominal) * kRadToDeg);
  const PoseResult r_cal = EstimateCamFromSensor(b.camera, obs.stored, nominal, options, scene);
  PrintPose("stored frames, calibrated intrinsics", r_cal, b.true_pose);
  {
    PoseOptions hull = options;
    hull.model_finder = false;
    const PoseResult r_hull = EstimateCamFromSensor(b.camera, obs.stored, nominal, hull, scene);
    PrintPose("  ... the rendered contact's hull centroid", r_hull, b.true_pose);
  }
  for (double bound : {50.0, 55.0, 65.0, 70.0, 80.0}) {
    PoseOptions alt = options;
    alt.max_view_angle_deg = bound;
    const std::string name = "  ... view bound " + std::to_string(static_cast<int>(bound));
    PrintPose(name.c_str(), EstimateCamFromSensor(b.camera, obs.stored, nominal, alt, scene),
              b.true_pose);
  }
  {
    PoseOptions all = options;
    all.max_view_angle_deg = 90.0;
    const PoseResult r_all = EstimateCamFromSensor(b.camera, obs.stored, nominal, all, scene);
    PrintPose("  ... without the view bound (90 deg)", r_all, b.true_pose);
  }
  const PoseResult r_true =
      EstimateCamFromSensor(b.true_camera, obs.stored, nominal, options, scene);
  PrintPose("stored frames, true intrinsics", r_true, b.true_pose);
  PoseOptions hull_model = options;  // the truth is the rendered hull centroid
  hull_model.model_finder = false;
  const PoseResult r_hull = EstimateCamFromSensor(b.camera, obs.truth, nominal, hull_model, scene);
  PrintPose("true hull centroids, calibrated intrinsics", r_hull, b.true_pose);
  if (!obs.sim.empty()) {
    const PoseResult r_sim = EstimateCamFromSensor(b.camera, obs.sim, nominal, options, scene);
    PrintPose("simulated frames, calibrated intrinsics", r_sim, b.true_pose);
  }
  return r_cal;
}

// Subsets chosen by geometry (diagnostics: which probes carry the error).
void PrintSubsets(const Bench& b, const Observations& obs, const PoseSetup& setup) {
  auto estimate = [&](const std::vector<PoseObservation>& sub) {
    return EstimateCamFromSensor(b.camera, sub, b.inputs.nominal_cam_from_sensor, setup.options,
                                 setup.scene);
  };
  auto subset = [&](const char* name, auto keep) {
    std::vector<PoseObservation> sub;
    for (std::size_t i = 0; i < obs.stored.size(); ++i) {
      if (keep(*obs.rows[i])) sub.push_back(obs.stored[i]);
    }
    try {
      PrintPose(name, estimate(sub), b.true_pose);
    } catch (const std::exception& e) {
      std::printf("  %-44s %s\n", name, e.what());
    }
  };
  for (double ratio : {0.0, 3.0}) {
    PoseSetup alt = setup;
    alt.options.max_region_ratio = ratio;
    const std::string name = "max_region_ratio " + std::to_string(ratio);
    try {
      const PoseResult r = EstimateCamFromSensor(
          b.camera, obs.stored, b.inputs.nominal_cam_from_sensor, alt.options, alt.scene);
      PrintPose(name.c_str(), r, b.true_pose);
      std::printf("    left out as spread %d; the paper's estimate %.4f mm %.4f deg\n", r.spread,
                  TranslationDifferenceMm(r.paper_cam_from_sensor, b.true_pose),
                  RotationDifferenceRad(r.paper_cam_from_sensor, b.true_pose) * kRadToDeg);
      alt.options.model_bias = false;
      PrintPose("   ... without the bias model",
                EstimateCamFromSensor(b.camera, obs.stored, b.inputs.nominal_cam_from_sensor,
                                      alt.options, alt.scene),
                b.true_pose);
    } catch (const std::exception& e) {
      std::printf("  %-44s %s\n", name.c_str(), e.what());
    }
  }
  subset("subset z >= 3", [](const Row& r) { return r.point.z() >= 3.0; });
  subset("subset view < 50", [](const Row& r) { return r.view_deg < 50.0; });
  subset("subset z >= 3, view < 50",
         [](const Row& r) { return r.point.z() >= 3.0 && r.view_deg < 50.0; });
  subset("subset fin >= 1.5", [](const Row& r) { return r.fin_mm >= 1.5; });
  subset("subset area < 2000", [](const Row& r) { return r.area < 2000; });
  for (double bound : {40.0, 45.0, 50.0, 55.0, 60.0}) {
    const std::string name = "subset view < " + std::to_string(static_cast<int>(bound));
    subset(name.c_str(), [bound](const Row& r) { return r.view_deg < bound; });
  }
  for (double power : {1.0, 2.0, 4.0}) {
    std::vector<PoseObservation> weighted = obs.stored;
    for (std::size_t i = 0; i < obs.stored.size(); ++i) {
      weighted[i].weight = std::pow(std::cos(obs.rows[i]->view_deg / kRadToDeg), power);
    }
    const std::string name = "weight cos(view)^" + std::to_string(static_cast<int>(power));
    PrintPose(name.c_str(), estimate(weighted), b.true_pose);
  }
  // Observed centroids with the TRUE model error removed where it is below 1 px (truth!).
  subset("only |obs - true hull| <= 1 px (truth)",
         [](const Row& r) { return !(r.hull_ok && (r.centroid - r.hull).norm() > 1.0); });
}

// Where the outliers are.
void PrintOutliers(const std::vector<Row>& rows, const PoseResult& r_cal) {
  std::map<int, const Row*> by_index;
  for (const Row& r : rows) by_index[r.plan_index] = &r;
  std::vector<double> z, fin, view;
  for (int p : r_cal.outlier_probe_indices) {
    const Row& r = *by_index.at(p);
    z.push_back(r.point.z());
    fin.push_back(r.fin_mm);
    view.push_back(r.view_deg);
  }
  auto median = [](std::vector<double> v) {
    if (v.empty()) return 0.0;
    std::sort(v.begin(), v.end());
    return v[v.size() / 2];
  };
  std::printf("  outliers (calibrated): %zu, median z %.1f mm, fin %.2f mm, view %.1f deg\n",
              z.size(), median(z), median(fin), median(view));
}

void WriteCsv(const std::string& path, const std::vector<Row>& rows, const PoseResult& r_cal) {
  std::ofstream out(path);
  out << "plan_index,x,y,z,nx,ny,nz,view_deg,fin_mm,peak,area,u,v,hull_u,hull_v,proj_u,proj_v,"
         "sim_u,sim_v,outlier,observed_hull_u,observed_hull_v\n";
  std::map<int, bool> outlier;
  for (int p : r_cal.outlier_probe_indices) outlier[p] = true;
  for (const Row& r : rows) {
    if (!r.found) continue;
    out << r.plan_index << ',' << r.point.x() << ',' << r.point.y() << ',' << r.point.z() << ','
        << r.normal.x() << ',' << r.normal.y() << ',' << r.normal.z() << ',' << r.view_deg << ','
        << r.fin_mm << ',' << r.peak << ',' << r.area << ',' << r.centroid.x() << ','
        << r.centroid.y() << ',' << r.hull.x() << ',' << r.hull.y() << ',' << r.proj.x() << ','
        << r.proj.y() << ',' << r.sim_centroid.x() << ',' << r.sim_centroid.y() << ','
        << (outlier.count(r.plan_index) ? 1 : 0) << ',' << r.observed_hull.x() << ','
        << r.observed_hull.y() << '\n';
  }
}

int Run(const Args& args) {
  try {
    Bench b = LoadBench(args);
    LoadRows(b);
    MeasureImpressions(b);
    const Bvh gel(b.inputs.gel_mesh), fins(b.inputs.fin_mesh);
    const SurfaceMap true_map = SurfaceMap::Build(b.true_camera, b.true_pose, gel, &fins);
    AddTruth(true_map, b);
    const Observations obs = BuildObservations(b.rows);
    PrintResiduals(b);
    for (int d : args.dump) DumpProbe(b, true_map, d);
    PoseSetup setup{PoseOptions(), PoseScene{&gel, &fins, args.impression}};
    setup.options.ball_radius_mm = b.inputs.ball_radius;
    const PoseResult r_cal = PrintPoseEstimates(b, obs, setup);
    PrintSubsets(b, obs, setup);
    PrintOutliers(b.rows, r_cal);
    if (!args.csv.empty()) WriteCsv(args.csv, b.rows, r_cal);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_pose_db: %s\n", e.what());
    return 1;
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  Args args;
  CLI::App app(
      "bench_pose_db: the pose stage on a stored run of the virtual rig: stored-frame impression "
      "centroids vs the simulator's truth, by height / view angle / fins, and the pose errors");
  AddOptions(app, args);
  CLI11_PARSE(app, argc, argv);
  return Run(args);
}
