// `gs360 bench recon`: run-time reconstruction's speed per stage and its accuracy, on frames of
// the virtual rig through a model calibrated on it (docs/benchmarks.md). Scenes: no contact, one
// contact on the side, on the tip and across a fin, three at once, a dense (deep) one.

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <numbers>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "calib/train.h"
#include "cli/commands.h"
#include "cli/sim_model.h"
#include "recon/contacts.h"
#include "recon/model_bundle.h"
#include "sim/tactile_camera.h"

namespace gs360::cli {
namespace {

using Json = nlohmann::json;
using Clock = std::chrono::steady_clock;

struct BenchReconArgs {
  std::string model;
  std::string cache;
  int train_probes = 300;
  int epochs = 15;
  double seconds = 2.0;  // per scene and thread count
  bool no_screen = false;
  int mlp_stride = 2;
  double mlp_refine_slope = ReconstructionOptions{}.mlp_refine_slope;
  int passes = 0;  // 0: the model's height-field passes
  bool poisson = false;
  std::vector<std::string> scenes;  // empty: all
};

struct Scene {
  std::string name;
  cv::Mat frame;
  std::vector<Eigen::Vector3d> balls;  // sensor frame
};

struct StageTimes {
  double detection = 0, mlp = 0, integration = 0, cloud = 0;
  int frames = 0;
};

double Since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// A ball centre pressing `depth` mm at (t, phi) of the cylinder's profile.
Eigen::Vector3d Ball(const SimRig& rig, double t, double phi, double depth) {
  return rig.profile().SurfacePoint(t, phi) +
         (rig.ball_radius() - depth) * rig.profile().SurfaceNormal(t, phi);
}

// Several contacts at once: each rendered alone, their changes added to one reference.
cv::Mat Composite(TactileCamera& camera, const std::vector<Eigen::Vector3d>& balls,
                  std::uint64_t index) {
  const cv::Mat reference = camera.RenderReference(index, 100.0);
  cv::Mat sum;
  reference.convertTo(sum, CV_32FC3);
  for (const Eigen::Vector3d& b : balls) {
    cv::Mat one, ref32;
    camera.RenderAtBall(b, index, 100.0).convertTo(one, CV_32FC3);
    reference.convertTo(ref32, CV_32FC3);
    sum += one - ref32;
  }
  cv::Mat out;
  sum.convertTo(out, CV_8UC3);
  return out;
}

std::vector<Scene> MakeScenes(const SimRig& rig, TactileCamera& camera) {
  const double q = std::numbers::pi / 4.0;
  std::vector<Scene> s;
  s.push_back({"no contact", camera.RenderReference(5000, 100.0), {}});
  const auto one = [&](const std::string& name, double t, double phi, double depth,
                       std::uint64_t i) {
    const Eigen::Vector3d b = Ball(rig, t, phi, depth);
    s.push_back({name, camera.RenderAtBall(b, i, 100.0), {b}});
  };
  one("side", 0.5, q, 1.0, 5001);
  one("tip", 0.8, q, 1.0, 5002);  // on the cap, 49 deg from the axis (nearer, the fins meet)
  one("across a fin", 0.5, 0.06, 1.0, 5003);
  std::vector<Eigen::Vector3d> three = {Ball(rig, 0.35, q, 1.0), Ball(rig, 0.5, 3 * q, 1.0),
                                        Ball(rig, 0.65, 5 * q, 1.0)};
  s.push_back({"three contacts", Composite(camera, three, 5004), three});
  one("dense", 0.5, 3 * q, 1.5, 5005);
  return s;
}

// One frame through the pieces of Reconstructor::Reconstruct, timing each.
FrameReconstruction TimedFrame(const Reconstructor& r, const cv::Mat& frame, StageTimes* t) {
  auto t0 = Clock::now();
  FrameReconstruction out;
  const DetectedContacts detected = r.Detect(frame, r.reference());
  t->detection += Since(t0);
  for (const ContactRegion& region : detected.regions) {
    if (region.roi.width < 3 || region.roi.height < 3) continue;
    t0 = Clock::now();
    const cv::Mat slopes = r.PredictSlopes(detected.difference, region.roi,
                                           r.SlopesWindow(region, r.options().integration));
    t->mlp += Since(t0);
    t0 = Clock::now();
    out.regions.push_back(r.IntegrateSlopes(slopes, region, r.options().integration));
    t->integration += Since(t0);
  }
  t0 = Clock::now();
  const auto points = r.PointCloud(out);
  t->cloud += Since(t0);
  ++t->frames;
  return out;
}

// Frames per second of whole Reconstruct() calls on `threads` threads for about `seconds`.
double Throughput(const Reconstructor& r, const cv::Mat& frame, int threads, double seconds) {
  std::vector<int> counts(static_cast<std::size_t>(threads), 0);
  const auto t0 = Clock::now();
  std::vector<std::thread> pool;
  for (int i = 0; i < threads; ++i) {
    pool.emplace_back([&, i] {
      while (Since(t0) < seconds) {
        r.Reconstruct(frame);
        ++counts[static_cast<std::size_t>(i)];
      }
    });
  }
  for (auto& t : pool) t.join();
  int total = 0;
  for (int c : counts) total += c;
  return total / Since(t0);
}

// The pixels both paths are judged on: every region either of them reconstructed. A pixel outside
// a path's own regions counts as undeformed gel there, so a smaller region is not flattered by
// leaving out the imprint's edge.
cv::Mat JudgedPixels(const SurfaceMap& map, const FrameReconstruction& a,
                     const FrameReconstruction& b) {
  cv::Mat mask(map.height(), map.width(), CV_8U, cv::Scalar::all(0));
  for (const FrameReconstruction* rec : {&a, &b}) {
    for (const RegionReconstruction& reg : rec->regions) mask(reg.region.roi).setTo(1);
  }
  return mask;
}

// Each pixel's distance along its ray as `rec` gives it: a region's rho, else the undeformed gel.
cv::Mat RhoOf(const SurfaceMap& map, const FrameReconstruction& rec) {
  cv::Mat rho(map.height(), map.width(), CV_64F);
  for (int v = 0; v < map.height(); ++v) {
    for (int u = 0; u < map.width(); ++u) rho.at<double>(v, u) = map.rho0(u, v);
  }
  for (const RegionReconstruction& reg : rec.regions) {
    const cv::Rect& roi = reg.region.roi;
    for (int y = 0; y < roi.height; ++y) {
      for (int x = 0; x < roi.width; ++x) {
        const double r = reg.rho.at<double>(y, x);
        if (std::isfinite(r)) rho.at<double>(roi.y + y, roi.x + x) = r;
      }
    }
  }
  return rho;
}

// Depth error (mm, along the gel's normal) of the judged pixels against the rigid imprint of the
// true balls, as the calibration's validation measures it: along a pixel's ray the surface is the
// nearer of the undeformed gel and the ball's near side.
Json Accuracy(const Reconstructor& r, const FrameReconstruction& rec, const Scene& scene,
              double ball_radius, const cv::Mat& judged) {
  const SurfaceMap& map = r.map();
  std::vector<Eigen::Vector3d> centres;
  double true_peak = 0.0;
  for (const Eigen::Vector3d& b : scene.balls) centres.push_back(map.cam_from_sensor() * b);
  const cv::Mat rho_of = RhoOf(map, rec);
  double sum = 0.0, worst = 0.0;
  std::size_t n = 0;
  for (int v = 0; v < map.height(); ++v) {
    for (int u = 0; u < map.width(); ++u) {
      const double rho = rho_of.at<double>(v, u);
      if (!judged.at<std::uint8_t>(v, u) || !std::isfinite(rho) || !map.visible(u, v)) continue;
      const Eigen::Vector3d d = map.ray(u, v);
      double truth = map.rho0(u, v);
      for (const Eigen::Vector3d& c : centres) {
        const double b = d.dot(c), disc = b * b - (c.squaredNorm() - ball_radius * ball_radius);
        if (disc > 0.0) truth = std::min(truth, b - std::sqrt(disc));
      }
      const double cosine = std::abs(d.dot(map.normal0(u, v)));
      true_peak = std::max(true_peak, (map.rho0(u, v) - truth) * cosine);
      const double error = std::abs(rho - truth) * cosine;
      sum += error;
      worst = std::max(worst, error);
      ++n;
    }
  }
  const auto points = r.PointCloud(rec);
  const auto contacts = SummarizeContacts(r, rec);
  double peak = 0.0;
  bool partial = false;
  for (const ContactSummary& c : contacts) {
    peak = std::max(peak, c.peak_indentation_mm);
    partial = partial || c.partial;
  }
  return Json{{"contacts_found", contacts.size()},
              {"contacts_true", scene.balls.size()},
              {"points", points.size()},
              {"pixels", n},
              {"mean_error_mm", n == 0 ? 0.0 : sum / static_cast<double>(n)},
              {"max_error_mm", worst},
              {"peak_mm", peak},
              {"true_peak_mm", true_peak},
              {"partial", partial}};
}

// Issue 15's targets: frames per second on one thread (a frame without contact, one contact,
// three), two threads over one, and the fast path's error over the full path's.
constexpr double kNoContactFps = 1000.0;
constexpr double kOneContactFps = 100.0;
constexpr double kThreeContactsFps = 50.0;
constexpr double kTwoThreadSpeedup = 1.8;
constexpr double kErrorOverFullPath = 1.05;

double TargetFps(const std::string& scene) {
  return scene == "no contact"       ? kNoContactFps
         : scene == "three contacts" ? kThreeContactsFps
                                     : kOneContactFps;
}

// The targets and whether this scene's figures meet them.
Json Targets(const std::string& scene, double fps, double speedup, double error_ratio) {
  return Json{{"frames_per_s_1_thread", TargetFps(scene)},
              {"two_thread_speedup", kTwoThreadSpeedup},
              {"error_vs_full_path", kErrorOverFullPath},
              {"met",
               {{"frames_per_s_1_thread", fps >= TargetFps(scene)},
                {"two_thread_speedup", speedup >= kTwoThreadSpeedup},
                {"error_vs_full_path", error_ratio <= kErrorOverFullPath}}}};
}

// One scene: the fast path's stages, its frames per second on one and two threads, and its
// accuracy beside the full path's.
Json MeasureScene(const Reconstructor& recon, const Reconstructor& full, const Scene& scene,
                  double seconds, double ball_radius) {
  StageTimes t;
  FrameReconstruction last;
  const auto t0 = Clock::now();
  while (Since(t0) < seconds || t.frames < 3) last = TimedFrame(recon, scene.frame, &t);
  const double n = t.frames;
  const double one = Throughput(recon, scene.frame, 1, seconds);
  const double two = Throughput(recon, scene.frame, 2, seconds);
  const FrameReconstruction reference_rec = full.Reconstruct(scene.frame);
  const cv::Mat judged = JudgedPixels(recon.map(), last, reference_rec);
  const Json fast = Accuracy(recon, last, scene, ball_radius, judged);
  const Json reference = Accuracy(full, reference_rec, scene, ball_radius, judged);
  const double fast_mean = fast["mean_error_mm"], full_mean = reference["mean_error_mm"];
  const double error_ratio = full_mean > 0.0 ? fast_mean / full_mean : 1.0;
  return Json{{"scene", scene.name},
              {"ms",
               {{"detection", 1e3 * t.detection / n},
                {"mlp", 1e3 * t.mlp / n},
                {"integration", 1e3 * t.integration / n},
                {"point_cloud", 1e3 * t.cloud / n},
                {"total", 1e3 * (t.detection + t.mlp + t.integration + t.cloud) / n}}},
              {"frames_per_s_1_thread", one},
              {"frames_per_s_2_threads", two},
              {"two_thread_speedup", two / one},
              {"accuracy", fast},
              {"accuracy_full_path", reference},
              {"error_vs_full_path", error_ratio},
              {"targets", Targets(scene.name, one, two / one, error_ratio)}};
}

// One line per scene that misses a target, or one saying all are met.
void PrintTargets(const Json& rows) {
  int missed = 0;
  for (const Json& row : rows) {
    const Json& t = row["targets"];
    std::string what;
    if (!t["met"]["frames_per_s_1_thread"].get<bool>()) {
      what += " " + std::to_string(std::lround(row["frames_per_s_1_thread"].get<double>())) +
              " f/s (target " +
              std::to_string(std::lround(t["frames_per_s_1_thread"].get<double>())) + ")";
    }
    if (!t["met"]["two_thread_speedup"].get<bool>()) what += " two threads under 1.8x";
    if (!t["met"]["error_vs_full_path"].get<bool>())
      what += " error over 5 % above the full path's";
    if (what.empty()) continue;
    ++missed;
    std::printf("target missed: %s:%s\n", row["scene"].get<std::string>().c_str(), what.c_str());
  }
  if (missed == 0) {
    std::printf(
        "targets: every scene met (1 thread >= 1,000 f/s without contact, 100 with one, "
        "50 with three; 2 threads >= 1.8x; error within 5 %% of the full path's)\n");
  }
}

void PrintRow(const Json& row) {
  const Json& ms = row["ms"];
  std::printf("%-15s %7.2f %7.2f %7.2f %7.2f %7.2f %8.1f %8.1f %5.2f %8.4f %8.4f %7.3f\n",
              row["scene"].get<std::string>().c_str(), ms["detection"].get<double>(),
              ms["mlp"].get<double>(), ms["integration"].get<double>(),
              ms["point_cloud"].get<double>(), ms["total"].get<double>(),
              row["frames_per_s_1_thread"].get<double>(),
              row["frames_per_s_2_threads"].get<double>(), row["two_thread_speedup"].get<double>(),
              row["accuracy"]["mean_error_mm"].get<double>(),
              row["accuracy_full_path"]["mean_error_mm"].get<double>(),
              row["accuracy"]["peak_mm"].get<double>());
}

std::filesystem::path CacheDir(const BenchReconArgs& a) {
  return SimModelCacheDir(a.cache, "bench-recon-model-" + std::to_string(a.train_probes) + "-" +
                                       std::to_string(a.epochs));
}

int RunBenchRecon(const BenchReconArgs& a, const CommandContext& ctx) {
  std::filesystem::path model_path = a.model;
  if (model_path.empty()) {
    SimModelOptions mo;
    mo.probes = a.train_probes;
    mo.hidden = TrainOptions{}.hidden;
    mo.epochs = a.epochs;
    const auto dir = CacheDir(a);
    if (!ctx.json)
      std::fprintf(stderr, "model: calibrating on the virtual rig in %s (cached)\n", dir.c_str());
    model_path = MakeSimModel(dir, mo);
  }
  ModelBundle bundle = ReadModelBundle(model_path);
  // The full path (every pixel, no screen) is the accuracy the fast one must keep.
  bundle.reconstruction.screen = false;
  bundle.reconstruction.mlp_stride = 1;
  const Reconstructor full = bundle.MakeReconstructor(2);
  bundle.reconstruction.screen = !a.no_screen;
  bundle.reconstruction.mlp_stride = a.mlp_stride;
  bundle.reconstruction.mlp_refine_slope = a.mlp_refine_slope;
  if (a.passes > 0) {
    HeightFieldOptions& h = bundle.reconstruction.integration.height_field;
    h.iterations = std::min(h.iterations, a.passes);
    h.oblique_iterations = std::min(h.oblique_iterations, a.passes);
  }
  if (a.poisson) bundle.reconstruction.integration.method = IntegrationMethod::kPoisson;
  const Reconstructor recon = bundle.MakeReconstructor(2);
  SimRigOptions so;
  so.seed = SimModelOptions{}.seed;
  auto rig = std::make_shared<const SimRig>(so);
  TactileCamera camera(rig);
  Json rows = Json::array();
  if (!ctx.json) {
    std::printf("%-15s %7s %7s %7s %7s %7s %8s %8s %5s %8s %8s %7s\n", "scene", "detect", "mlp ms",
                "integr", "cloud", "total", "1thr f/s", "2thr f/s", "x", "mean mm", "full mm",
                "peak mm");
  }
  for (const Scene& scene : MakeScenes(*rig, camera)) {
    if (!a.scenes.empty() &&
        std::find(a.scenes.begin(), a.scenes.end(), scene.name) == a.scenes.end()) {
      continue;
    }
    rows.push_back(MeasureScene(recon, full, scene, a.seconds, rig->ball_radius()));
    if (!ctx.json) PrintRow(rows.back());
  }
  const Json result{{"model", model_path.string()},
                    {"screen", !a.no_screen},
                    {"mlp_stride", a.mlp_stride},
                    {"mlp_refine_slope", a.mlp_refine_slope},
                    {"height_field_passes_at_most", a.passes},
                    {"poisson", a.poisson},
                    {"mlp_sizes", bundle.mlp.sizes()},
                    {"image", {recon.map().width(), recon.map().height()}},
                    {"hardware_threads", std::thread::hardware_concurrency()},
                    {"scenes", rows}};
  if (ctx.json) {
    std::printf("%s\n", result.dump(2).c_str());
  } else {
    PrintTargets(rows);
  }
  return 0;
}

}  // namespace

void RegisterReconBench(CLI::App& bench, CommandContext& ctx) {
  static BenchReconArgs a;
  auto* cmd = bench.add_subcommand(
      "recon", "Reconstruction speed per stage and accuracy on virtual-rig frames");
  cmd->add_option("--model", a.model, "A model bundle; default: one calibrated on the virtual rig");
  cmd->add_option("--cache", a.cache, "Where the default model is kept (~/.cache/gs360)");
  cmd->add_option("--train-probes", a.train_probes, "Presses of the default model")
      ->check(CLI::Range(20, 100000));
  cmd->add_option("--epochs", a.epochs, "Training epochs of the default model")
      ->check(CLI::Range(1, 1000));
  cmd->add_option("--seconds", a.seconds, "Measuring time per scene and thread count")
      ->check(CLI::Range(0.1, 600.0));
  cmd->add_flag("--no-screen", a.no_screen,
                "Without the half-size look for frames without contact");
  cmd->add_option("--mlp-stride", a.mlp_stride, "The fast path's MLP grid (1: every pixel)")
      ->check(CLI::Range(1, 8));
  cmd->add_option("--mlp-refine-slope", a.mlp_refine_slope,
                  "The fast path evaluates every pixel of a grid cell whose nodes' slopes differ "
                  "by more than this (default 0.2)")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--passes", a.passes,
                  "The fast path's height-field passes at most (0: the model's)")
      ->check(CLI::Range(0, 100));
  cmd->add_flag("--poisson", a.poisson, "The fast path integrates by plain Poisson");
  cmd->add_option("--scenes", a.scenes, "Only these scenes (comma-separated names)")
      ->delimiter(',')
      ->check(
          CLI::IsMember({"no contact", "side", "tip", "across a fin", "three contacts", "dense"}));
  cmd->callback([&ctx] { ctx.exit_code = RunBenchRecon(a, ctx); });
}

}  // namespace gs360::cli
