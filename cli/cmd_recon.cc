// `gs360 recon`: an exported model turns tactile frames into depth. One image, a folder of
// images, or a live camera; per frame a 16-bit depth PNG with a JSON side file (its scale and
// frame), a colour-mapped preview and a PLY point cloud in the sensor frame (docs/recon.md).

#include <poll.h>
#include <unistd.h>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <optional>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "base/format.h"
#include "capture/frame_source.h"
#include "cli/commands.h"
#include "cli/progress.h"
#include "geometry/point_cloud.h"
#include "recon/contacts.h"
#include "recon/model_bundle.h"

namespace gs360::cli {
namespace {

using Json = nlohmann::json;
namespace fs = std::filesystem;

// Depth PNG counts: 0.1 um each, so 16 bits reach 6.5535 mm (far beyond any press into the gel).
constexpr double kDepthScaleMm = 1e-4;

struct ReconArgs {
  std::string model;
  std::string image;
  std::string images;
  std::string camera;
  std::string reference;
  std::string out;
  double min_indentation_mm = 0.02;
  int reference_frames = 10;
  int frames = 0;  // camera: stop after this many (0: until Ctrl-C)
  std::string record;
  int threads = 1;
  int mlp_stride = 2;  // measured by `bench recon`: within 5 % of every pixel's accuracy
  double mlp_refine_slope = ReconstructionOptions{}.mlp_refine_slope;
};

cv::Mat ReadFrame(const fs::path& path, const cv::Size& size) {
  if (!fs::exists(path)) throw std::runtime_error(path.string() + ": no such file");
  const cv::Mat image = cv::imread(path.string(), cv::IMREAD_COLOR);
  if (image.empty()) {
    throw std::runtime_error(path.string() +
                             ": not a readable image (corrupt, truncated or not PNG / JPEG)");
  }
  if (image.size() != size) {
    throw std::runtime_error(path.string() + ": the image is " + std::to_string(image.cols) + "x" +
                             std::to_string(image.rows) + " but the model's camera is " +
                             std::to_string(size.width) + "x" + std::to_string(size.height));
  }
  return image;
}

Json ContactJson(const ContactSummary& c) {
  const auto vec = [](const Eigen::Vector3d& v) { return Json::array({v.x(), v.y(), v.z()}); };
  return Json{{"centre_sensor_mm", vec(c.centre_sensor)},
              {"peak_sensor_mm", vec(c.peak_sensor)},
              {"peak_indentation_mm", c.peak_indentation_mm},
              {"area_mm2", c.area_mm2},
              {"pixels", c.pixels},
              {"partial", c.partial},
              {"roi", {c.roi.x, c.roi.y, c.roi.width, c.roi.height}}};
}

// The preview: the frame in grey with the indentation colour-mapped over it (0.5 mm = full scale).
cv::Mat Preview(const cv::Mat& frame, const cv::Mat& indentation) {
  cv::Mat grey, base, scaled, colour;
  cv::cvtColor(frame, grey, cv::COLOR_BGR2GRAY);
  cv::cvtColor(grey, base, cv::COLOR_GRAY2BGR);
  indentation.convertTo(scaled, CV_8U, 255.0 / 0.5);
  cv::applyColorMap(scaled, colour, cv::COLORMAP_TURBO);
  cv::Mat mask = indentation > 0.0f;
  cv::Mat blended;
  cv::addWeighted(base, 0.35, colour, 0.65, 0.0, blended);
  blended.copyTo(base, mask);
  return base;
}

void WriteText(const fs::path& path, const std::string& text) {
  std::ofstream out(path, std::ios::binary);
  out << text;
  if (!out.flush()) throw std::runtime_error(path.string() + ": write failed (disk full?)");
}

void WritePng(const fs::path& path, const cv::Mat& image) {
  if (!cv::imwrite(path.string(), image)) {
    throw std::runtime_error(path.string() + ": cannot write the PNG");
  }
}

// Reconstructs one frame and writes its four files as OUT/STEM-*. Returns the side file's JSON.
Json ReconstructAndWrite(const Reconstructor& recon, const ModelBundle& bundle,
                         const cv::Mat& frame, const cv::Mat& reference, const fs::path& out,
                         const std::string& stem, const std::string& source,
                         double min_indentation_mm) {
  const FrameReconstruction r = recon.Reconstruct(frame, reference);
  const cv::Mat indentation = IndentationImage(recon, r);
  const std::vector<ContactSummary> contacts = SummarizeContacts(recon, r, min_indentation_mm);
  cv::Mat counts;
  indentation.convertTo(counts, CV_16U, 1.0 / kDepthScaleMm);
  WritePng(out / (stem + "-depth.png"), counts);
  WritePng(out / (stem + "-preview.png"), Preview(frame, indentation));
  const std::vector<Eigen::Vector3f> points = recon.PointCloud(r, min_indentation_mm);
  // No contact, no points: no PLY (an old one of the same name would mislead).
  fs::remove(out / (stem + ".ply"));
  if (!points.empty()) WritePointCloudPly(out / (stem + ".ply"), points);
  Json side{
      {"source", source},
      {"model", bundle.name + "-" + bundle.version},
      {"depth_png", stem + "-depth.png"},
      {"quantity", "indentation of the gel along its undeformed outward normal, + into the gel"},
      {"scale_mm_per_count", kDepthScaleMm},
      {"frame", "the camera's pixel grid (u right, v down), one value per pixel; 0 = none"},
      {"width", indentation.cols},
      {"height", indentation.rows},
      {"point_cloud", points.empty() ? Json(nullptr) : Json(stem + ".ply")},
      {"point_cloud_frame", "sensor (mm): origin at the base centre, +z along the finger"},
      {"points", points.size()},
      {"seconds", r.seconds},
      {"problem", r.problem.empty() ? Json(nullptr) : Json(r.problem)},
      {"contacts", Json::array()}};
  for (const ContactSummary& c : contacts) side["contacts"].push_back(ContactJson(c));
  WriteText(out / (stem + "-depth.json"), side.dump(2) + "\n");
  return side;
}

void PrintContacts(const std::string& name, const Json& side) {
  const Json& contacts = side["contacts"];
  std::printf("%s: %zu contact%s (%.1f ms)\n", name.c_str(), contacts.size(),
              contacts.size() == 1 ? "" : "s", side["seconds"].get<double>() * 1e3);
  if (side["problem"].is_string()) {
    std::printf("  not reconstructed: %s\n", side["problem"].get<std::string>().c_str());
  }
  for (const Json& c : contacts) {
    const Json& p = c["centre_sensor_mm"];
    std::printf("  at (%.2f, %.2f, %.2f) mm: peak %.3f mm, area %.2f mm^2%s\n", p[0].get<double>(),
                p[1].get<double>(), p[2].get<double>(), c["peak_indentation_mm"].get<double>(),
                c["area_mm2"].get<double>(),
                c["partial"].get<bool>() ? " (partial: runs out of the camera's view)" : "");
  }
}

ModelBundle LoadModel(const std::string& path) {
  try {
    return ReadModelBundle(path);
  } catch (const ModelBundleError& e) {
    throw std::runtime_error(std::string(e.what()) +
                             ". Export the model again (`gs360 export RUN --out DIR`).");
  }
}

std::vector<fs::path> ImagesIn(const fs::path& dir) {
  if (!fs::is_directory(dir)) throw std::runtime_error(dir.string() + ": not a folder");
  std::vector<fs::path> images;
  for (const auto& e : fs::directory_iterator(dir)) {
    std::string ext = e.path().extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
    if (e.is_regular_file() && (ext == ".png" || ext == ".jpg" || ext == ".jpeg")) {
      images.push_back(e.path());
    }
  }
  std::sort(images.begin(), images.end());
  if (images.empty()) throw std::runtime_error(dir.string() + ": no .png or .jpg images");
  return images;
}

std::atomic<bool> g_stop{false};

// True when the user typed a line starting with 'r' on stdin (non-blocking).
bool ReferenceRequested() {
  pollfd p{STDIN_FILENO, POLLIN, 0};
  if (::poll(&p, 1, 0) <= 0 || !(p.revents & POLLIN)) return false;
  char buf[64];
  const ssize_t n = ::read(STDIN_FILENO, buf, sizeof(buf));
  return n > 0 && (buf[0] == 'r' || buf[0] == 'R');
}

// The mean of `n` frames from `source`: a reference with less noise than one frame.
cv::Mat AverageFrames(FrameSource& source, int n, const cv::Size& size) {
  cv::Mat sum;
  int got = 0;
  while (got < n) {
    const auto frame = source.Next(std::chrono::seconds(5));
    if (!frame) throw std::runtime_error(source.Describe() + ": no frame within 5 s");
    if (frame->image.size() != size) {
      throw std::runtime_error(source.Describe() + " gives " + std::to_string(frame->image.cols) +
                               "x" + std::to_string(frame->image.rows) +
                               " frames; the model's camera is " + std::to_string(size.width) +
                               "x" + std::to_string(size.height));
    }
    if (sum.empty()) sum = cv::Mat::zeros(size, CV_32FC3);
    cv::accumulate(frame->image, sum);
    ++got;
  }
  cv::Mat mean;
  sum.convertTo(mean, CV_8UC3, 1.0 / n);
  return mean;
}

int RunCamera(const ReconArgs& a, const ModelBundle& bundle, const Reconstructor& recon,
              const CommandContext& ctx) {
  const cv::Size size(recon.map().width(), recon.map().height());
  auto source = OpenFrameSource(a.camera, CameraControls{});
  source->Start();
  cv::Mat reference = AverageFrames(*source, a.reference_frames, size);
  std::fprintf(stderr,
               "reference: the mean of %d frames from %s; type r + Enter to take it again, "
               "Ctrl-C to stop\n",
               a.reference_frames, source->Describe().c_str());
  if (!a.record.empty()) fs::create_directories(a.record);
  g_stop = false;
  auto previous = std::signal(SIGINT, [](int) { g_stop = true; });
  int n = 0, contacts_seen = 0;
  auto window_start = std::chrono::steady_clock::now();
  int window_frames = 0;
  double fps = 0.0;
  while (!g_stop && (a.frames == 0 || n < a.frames)) {
    if (ReferenceRequested()) {
      reference = AverageFrames(*source, a.reference_frames, size);
      std::fprintf(stderr, "\nreference taken again (%d frames)\n", a.reference_frames);
    }
    const auto frame = source->Next(std::chrono::seconds(5));
    if (!frame) throw std::runtime_error(source->Describe() + ": no frame within 5 s");
    ++n;
    ++window_frames;
    if (!a.record.empty()) {
      char stem[32];
      std::snprintf(stem, sizeof(stem), "frame-%06d", n);
      ReconstructAndWrite(recon, bundle, frame->image, reference, a.record, stem, a.camera,
                          a.min_indentation_mm);
    } else {
      const FrameReconstruction r = recon.Reconstruct(frame->image, reference);
      contacts_seen = static_cast<int>(SummarizeContacts(recon, r, a.min_indentation_mm).size());
    }
    const double dt =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - window_start).count();
    if (dt >= 1.0) {
      fps = window_frames / dt;
      window_frames = 0;
      window_start = std::chrono::steady_clock::now();
      if (!ctx.json) {
        std::fprintf(stderr, "\r%d frames, %.1f frames/s, %d contact%s   ", n, fps, contacts_seen,
                     contacts_seen == 1 ? "" : "s");
      }
    }
  }
  std::signal(SIGINT, previous);
  source->Stop();
  if (ctx.json) {
    std::printf("%s\n", Json{{"frames", n}, {"frames_per_s", fps}}.dump().c_str());
  } else {
    std::fprintf(stderr, "\n%d frames\n", n);
  }
  return 0;
}

int RunRecon(const ReconArgs& a, const CommandContext& ctx) {
  const int sources = !a.image.empty() + !a.images.empty() + !a.camera.empty();
  if (sources != 1) {
    throw CLI::ValidationError("recon", "give exactly one of --image, --images and --camera");
  }
  if (a.camera.empty() && a.out.empty()) {
    throw CLI::ValidationError("--out", "required with --image and --images");
  }
  ModelBundle bundle = LoadModel(a.model);
  bundle.reconstruction.mlp_stride = a.mlp_stride;
  bundle.reconstruction.mlp_refine_slope = a.mlp_refine_slope;
  const Reconstructor recon = bundle.MakeReconstructor(a.threads);
  const cv::Size size(recon.map().width(), recon.map().height());
  if (!a.camera.empty()) return RunCamera(a, bundle, recon, ctx);
  const cv::Mat reference = a.reference.empty() ? recon.reference() : ReadFrame(a.reference, size);
  fs::create_directories(a.out);
  std::vector<fs::path> inputs =
      a.image.empty() ? ImagesIn(a.images) : std::vector<fs::path>{a.image};
  Json all = Json::array();
  const bool show = !ctx.json && inputs.size() > 1;
  const auto t0 = std::chrono::steady_clock::now();
  for (std::size_t i = 0; i < inputs.size(); ++i) {
    const cv::Mat frame = ReadFrame(inputs[i], size);
    const Json side =
        ReconstructAndWrite(recon, bundle, frame, reference, a.out, inputs[i].stem().string(),
                            inputs[i].string(), a.min_indentation_mm);
    all.push_back(side);
    if (show) {
      const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      const double left =
          s / static_cast<double>(i + 1) * static_cast<double>(inputs.size() - i - 1);
      std::fprintf(stderr, "%s[%zu/%zu] %s, %s left%s", ::isatty(STDERR_FILENO) ? "\r" : "", i + 1,
                   inputs.size(), inputs[i].filename().c_str(), FormatDuration(left).c_str(),
                   ::isatty(STDERR_FILENO) ? "   " : "\n");
    }
    if (!ctx.json && inputs.size() == 1) PrintContacts(inputs[i].filename().string(), side);
  }
  if (show && ::isatty(STDERR_FILENO)) std::fprintf(stderr, "\n");
  if (ctx.json) {
    std::printf("%s\n", (inputs.size() == 1 ? all[0] : all).dump(2).c_str());
  } else if (inputs.size() > 1) {
    std::size_t with = 0;
    for (const Json& s : all) with += !s["contacts"].empty();
    std::printf("%zu images, %zu with contact; files in %s\n", inputs.size(), with, a.out.c_str());
  } else {
    const std::string stem = (fs::path(a.out) / inputs[0].stem()).string();
    std::printf("wrote %s-depth.png, -depth.json, -preview.png%s\n", stem.c_str(),
                all[0]["point_cloud"].is_null() ? " (no contact: no point cloud)"
                                                : (" and " + stem + ".ply").c_str());
  }
  return 0;
}

}  // namespace

void RegisterReconCommand(CLI::App& app, CommandContext& ctx) {
  static ReconArgs a;
  auto* cmd = app.add_subcommand("recon", "Turn tactile frames into depth with an exported model");
  cmd->add_option("--model", a.model, "The model bundle (.gs360model, from `gs360 export`)")
      ->required();
  cmd->add_option("--image", a.image, "One frame (PNG / JPEG)");
  cmd->add_option("--images", a.images, "A folder of frames (*.png, *.jpg), in name order");
  cmd->add_option("--camera", a.camera,
                  "Live frames from a capture URI (libcamera:0, v4l2:/dev/video0, socket:PATH)");
  cmd->add_option("--reference", a.reference,
                  "A no-contact frame taken more recently than the model's");
  cmd->add_option("--out", a.out, "Folder for the depth PNG, its JSON, the preview and the PLY");
  cmd->add_option("--min-indentation", a.min_indentation_mm,
                  "Indentation (mm) below which a pixel is not in contact")
      ->check(CLI::Range(0.0, 5.0));
  cmd->add_option("--reference-frames", a.reference_frames,
                  "Camera: frames averaged into the reference at start and on request")
      ->check(CLI::Range(1, 1000));
  cmd->add_option("--frames", a.frames, "Camera: stop after this many frames (0: at Ctrl-C)")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--record", a.record, "Camera: write every frame's files into this folder");
  cmd->add_option("--mlp-stride", a.mlp_stride,
                  "The MLP on every n-th pixel, interpolated between (1: every pixel)")
      ->check(CLI::Range(1, 8));
  cmd->add_option("--mlp-refine-slope", a.mlp_refine_slope,
                  "With --mlp-stride > 1: every pixel of a grid cell whose nodes' slopes differ by "
                  "more than this (an imprint's rim) gets the MLP too (default 0.2)")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--threads", a.threads, "Threads building the surface map at load")
      ->check(CLI::Range(1, 64));
  cmd->callback([&ctx] { ctx.exit_code = RunRecon(a, ctx); });
}

}  // namespace gs360::cli
