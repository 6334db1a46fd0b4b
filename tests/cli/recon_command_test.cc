// `gs360 recon` as a user runs it: the real executable on a model calibrated on the virtual rig
// and frames rendered by it; the files it writes open in standard tools (OpenCV, assimp, JSON).

#include <catch2/catch.hpp>

#include <assimp/scene.h>

#include <assimp/Importer.hpp>
#include <filesystem>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "cli/sim_model.h"
#include "recon/contacts.h"
#include "recon/model_bundle.h"
#include "sim/tactile_camera.h"
#include "sim/virtual_rig.h"
#include "tests/cli/run_gs360.h"

using namespace gs360;
using Catch::Contains;
namespace fs = std::filesystem;

namespace {

using Result = test::Gs360Result;
using test::Gs360;

// One model and a few frames for every test case of this file (calibrating takes seconds).
struct Fixture {
  fs::path dir;
  fs::path model;
  fs::path contact;  // a press on the side
  fs::path no_contact;
  Fixture() {
    dir = fs::temp_directory_path() / ("gs360-recon-cmd-" + std::to_string(::getpid()));
    fs::remove_all(dir);
    cli::SimModelOptions o;
    o.probes = 150;
    o.hidden = {32, 32};
    o.epochs = 10;
    model = cli::MakeSimModel(dir / "model", o);
    SimRigOptions so;
    so.seed = 7;
    auto rig = std::make_shared<const SimRig>(so);
    TactileCamera camera(rig);
    const auto press = cli::SimPresses(*rig, 1, 1.0, 99).front();
    fs::create_directories(dir / "frames");
    contact = dir / "frames" / "press.png";
    no_contact = dir / "frames" / "empty.png";
    cv::imwrite(contact.string(), camera.RenderAtBall(press.ball_sensor, 1000, 10.0));
    cv::imwrite(no_contact.string(), camera.RenderReference(1001, 10.0));
  }
  ~Fixture() {
    std::error_code ec;
    fs::remove_all(dir, ec);
  }
};

Fixture& Shared() {
  static Fixture f;
  return f;
}

}  // namespace

TEST_CASE("recon writes a 16-bit depth PNG, its JSON, a preview and a PLY that assimp loads",
          "[cli][recon]") {
  Fixture& f = Shared();
  const fs::path out = f.dir / "out";
  const Result r = Gs360("recon --model " + f.model.string() + " --image " + f.contact.string() +
                         " --out " + out.string());
  INFO(r.out);
  REQUIRE(r.status == 0);
  CHECK_THAT(r.out, Contains("press.png: 1 contact") && Contains("peak"));

  const cv::Mat depth = cv::imread((out / "press-depth.png").string(), cv::IMREAD_UNCHANGED);
  REQUIRE(depth.type() == CV_16U);
  CHECK(depth.cols == 640);
  double max_count = 0;
  cv::minMaxLoc(depth, nullptr, &max_count);
  std::ifstream side_in(out / "press-depth.json");
  const nlohmann::json side = nlohmann::json::parse(side_in);
  const double scale = side.at("scale_mm_per_count");
  // A 1 mm press reconstructs to a peak of about that depth.
  CHECK(max_count * scale > 0.5);
  CHECK(max_count * scale < 1.5);
  REQUIRE(side.at("contacts").size() == 1);
  const auto& c = side["contacts"][0];
  CHECK(c.at("peak_indentation_mm").get<double>() == Approx(max_count * scale).margin(2 * scale));
  CHECK(c.at("area_mm2").get<double>() > 1.0);
  CHECK_FALSE(c.at("partial").get<bool>());  // on the open wall, in full view

  const cv::Mat preview = cv::imread((out / "press-preview.png").string(), cv::IMREAD_COLOR);
  CHECK(preview.cols == 640);
  CHECK(preview.rows == 480);

  Assimp::Importer importer;
  const aiScene* scene = importer.ReadFile((out / "press.ply").string(), 0);
  REQUIRE(scene != nullptr);
  REQUIRE(scene->mNumMeshes == 1);
  CHECK(scene->mMeshes[0]->mNumVertices == side.at("points").get<unsigned>());
  CHECK(scene->mMeshes[0]->mNumVertices > 100);
  // Sensor frame: the points lie on the cylinder's wall, about its 10 mm radius from the axis.
  const aiVector3D v = scene->mMeshes[0]->mVertices[0];
  CHECK(std::hypot(v.x, v.y) == Approx(10.0).margin(1.5));
}

TEST_CASE("recon of a folder: a frame without contact reports none", "[cli][recon]") {
  Fixture& f = Shared();
  const Result r = Gs360("--json recon --model " + f.model.string() + " --images " +
                         (f.dir / "frames").string() + " --out " + (f.dir / "out2").string());
  INFO(r.out);
  REQUIRE(r.status == 0);
  const nlohmann::json all = nlohmann::json::parse(r.out.substr(r.out.find('[')));
  REQUIRE(all.size() == 2);
  CHECK(all[0].at("source").get<std::string>().find("empty.png") != std::string::npos);
  CHECK(all[0].at("contacts").empty());
  CHECK(all[1].at("contacts").size() == 1);
}

TEST_CASE("recon refuses a truncated or foreign model and a corrupt image, naming the file",
          "[cli][recon]") {
  Fixture& f = Shared();
  const fs::path truncated = f.dir / "truncated.gs360model";
  {
    std::ifstream in(f.model, std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), {});
    std::ofstream(truncated, std::ios::binary) << bytes.substr(0, bytes.size() / 2);
  }
  Result r = Gs360("recon --model " + truncated.string() + " --image " + f.contact.string() +
                   " --out " + (f.dir / "x").string());
  CHECK(r.status != 0);
  CHECK_THAT(r.out, Contains(truncated.string()) && Contains("gs360 export"));
  r = Gs360("recon --model " + f.contact.string() + " --image " + f.contact.string() + " --out " +
            (f.dir / "x").string());
  CHECK(r.status != 0);
  CHECK_THAT(r.out, Contains("not a gs360 model bundle"));
  const fs::path broken = f.dir / "broken.png";
  {
    std::ifstream in(f.contact, std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), {});
    std::ofstream(broken, std::ios::binary) << bytes.substr(0, 200);
  }
  r = Gs360("recon --model " + f.model.string() + " --image " + broken.string() + " --out " +
            (f.dir / "x").string());
  CHECK(r.status != 0);
  CHECK_THAT(r.out, Contains(broken.string()) && Contains("not a readable image"));
}

TEST_CASE(
    "no phantom contacts: 1,000 frames without contact, noise, LED drift and slow light change",
    "[cli][recon][phantom]") {
  Fixture& f = Shared();
  ModelBundle bundle = ReadModelBundle(f.model);
  bundle.reconstruction.mlp_stride = 2;  // what `gs360 recon` runs
  const Reconstructor recon = bundle.MakeReconstructor(2);
  SimRigOptions so;
  so.seed = 7;
  TactileCameraOptions co;
  co.sensor.drift_amplitude = 0.04;  // LED drift of up to 4 % per channel over the hours
  TactileCamera camera(std::make_shared<const SimRig>(so), co);
  int contacts = 0, screened = 0;
  double deepest = 0.0;
  for (int i = 0; i < 1000; ++i) {
    const double hours = 8.0 * i / 1000.0;  // an overnight session, one frame every ~29 s
    cv::Mat frame = camera.RenderReference(2000 + i, 3600.0 * hours);
    // Slow illumination change on top: a 3 % gradient across the image that turns with time.
    cv::Mat scale(frame.size(), CV_32FC3);
    const double angle = 0.8 * hours;
    for (int v = 0; v < frame.rows; ++v) {
      for (int u = 0; u < frame.cols; ++u) {
        const double t = (std::cos(angle) * (u - 320.0) + std::sin(angle) * (v - 240.0)) / 400.0;
        const float s = static_cast<float>(1.0 + 0.015 * t);
        scale.at<cv::Vec3f>(v, u) = cv::Vec3f(s, s, s);
      }
    }
    cv::Mat lit;
    frame.convertTo(lit, CV_32FC3);
    lit = lit.mul(scale);
    lit.convertTo(frame, CV_8UC3);
    const FrameReconstruction r = recon.Reconstruct(frame);
    contacts += static_cast<int>(SummarizeContacts(recon, r).size());
    screened += !recon.MayTouch(frame, recon.reference());
    double peak = 0.0;
    cv::minMaxLoc(IndentationImage(recon, r), nullptr, &peak);
    deepest = std::max(deepest, peak);
  }
  INFO(screened << " of 1000 frames stopped at the screen; deepest indentation " << deepest);
  CHECK(contacts == 0);
  CHECK(deepest <= 0.02);  // the contact threshold: no depth beyond the noise floor
}

TEST_CASE("a contact that runs behind a fin is reported as partial, one in full view is not",
          "[cli][recon]") {
  Fixture& f = Shared();
  const Reconstructor recon = ReadModelBundle(f.model).MakeReconstructor(2);
  SimRigOptions so;
  so.seed = 7;
  auto rig = std::make_shared<const SimRig>(so);
  TactileCamera camera(rig);
  const auto press = [&](double phi) {
    const Eigen::Vector3d ball =
        rig->profile().SurfacePoint(0.5, phi) +
        (rig->ball_radius() - 1.0) * rig->profile().SurfaceNormal(0.5, phi);
    return SummarizeContacts(recon, recon.Reconstruct(camera.RenderAtBall(ball, 3000, 0.0)));
  };
  const auto fin = press(0.06);  // the fin at phi = 0 hides part of the imprint
  REQUIRE(fin.size() == 1);
  CHECK(fin[0].partial);
  const auto open = press(0.785);  // halfway between two fins
  REQUIRE(open.size() == 1);
  CHECK_FALSE(open[0].partial);
  CHECK(open[0].area_mm2 > fin[0].area_mm2);
}

TEST_CASE("the screen's window gives the full path's regions and difference inside them",
          "[cli][recon]") {
  Fixture& f = Shared();
  ModelBundle bundle = ReadModelBundle(f.model);
  bundle.reconstruction.screen = false;
  const Reconstructor full = bundle.MakeReconstructor(2);
  bundle.reconstruction.screen = true;
  const Reconstructor fast = bundle.MakeReconstructor(2);
  const cv::Mat frame = cv::imread(f.contact.string(), cv::IMREAD_COLOR);
  const DetectedContacts a = full.Detect(frame, full.reference());
  const DetectedContacts b = fast.Detect(frame, fast.reference());
  CHECK(a.window == cv::Rect(0, 0, 640, 480));
  CHECK(b.window.area() < a.window.area() / 4);  // one contact: a small part of the image
  REQUIRE(a.regions.size() == 1);
  REQUIRE(b.regions.size() == 1);
  CHECK(a.regions[0].roi == b.regions[0].roi);
  CHECK(a.regions[0].area_px == b.regions[0].area_px);
  CHECK(cv::norm(a.difference(a.regions[0].roi), b.difference(b.regions[0].roi), cv::NORM_INF) <
        1e-6);
  // No contact: nothing past the screen.
  const cv::Mat empty = cv::imread(f.no_contact.string(), cv::IMREAD_COLOR);
  CHECK(fast.Detect(empty, fast.reference()).regions.empty());
  CHECK(fast.Detect(empty, fast.reference()).difference.empty());
}

TEST_CASE("the fast path's slopes: only in the height field's window, every pixel at the rim",
          "[cli][recon]") {
  Fixture& f = Shared();
  ModelBundle bundle = ReadModelBundle(f.model);
  bundle.reconstruction.screen = false;
  const Reconstructor every = bundle.MakeReconstructor(2);
  const cv::Mat frame = cv::imread(f.contact.string(), cv::IMREAD_COLOR);
  const DetectedContacts d = every.Detect(frame, every.reference());
  REQUIRE(d.regions.size() == 1);
  const ContactRegion& region = d.regions[0];
  const IntegrationOptions& integration = bundle.reconstruction.integration;
  REQUIRE(integration.method == IntegrationMethod::kHeightField);
  // The window: the blob grown by window_grow_fraction (+ grow_px), inside the region.
  const cv::Rect window = every.SlopesWindow(region, integration);
  const HeightFieldOptions& hf = integration.height_field;
  const int grow = bundle.reconstruction.detection.grow_px +
                   static_cast<int>(std::ceil(hf.window_grow_fraction * region.blob.width));
  CHECK(window.x == std::max(region.blob.x - grow, region.roi.x));
  CHECK((window & region.roi) == window);
  CHECK(window.area() < region.roi.area());
  // Every pixel's slopes: the window's are the region's, none beyond it.
  const cv::Mat all = every.PredictSlopes(d.difference, region.roi);
  const cv::Mat windowed = every.PredictSlopes(d.difference, region.roi, window);
  const cv::Rect inside = window - region.roi.tl();
  CHECK(cv::norm(all(inside), windowed(inside), cv::NORM_INF) < 1e-4);
  cv::Mat outside = windowed.clone();
  outside(inside).setTo(cv::Scalar::all(0));
  CHECK(cv::norm(outside, cv::NORM_INF) == 0.0);
  // A grid of every second pixel: refining every cell whose nodes differ at all gives every
  // pixel's slopes; without refinement, the rim is blurred.
  bundle.reconstruction.mlp_stride = 2;
  bundle.reconstruction.mlp_refine_slope = 0.0;
  const cv::Mat refined =
      bundle.MakeReconstructor(2).PredictSlopes(d.difference, region.roi, window);
  bundle.reconstruction.mlp_refine_slope = 1e9;
  const cv::Mat bilinear =
      bundle.MakeReconstructor(2).PredictSlopes(d.difference, region.roi, window);
  CHECK(cv::norm(refined, windowed, cv::NORM_INF) < 1e-4);
  CHECK(cv::norm(bilinear, windowed, cv::NORM_INF) > 0.05);
  // A window one pixel wide has no cells: every pixel of it is evaluated.
  const cv::Rect column(window.x + window.width / 2, window.y, 1, window.height);
  const cv::Mat thin = bundle.MakeReconstructor(2).PredictSlopes(d.difference, region.roi, column);
  const cv::Rect column_in = column - region.roi.tl();
  // The same pixels through the float MLP in batches of another shape round differently (by
  // 1.3e-4 on one model); the bilinear grid above is off by 0.05 and more.
  CHECK(cv::norm(thin(column_in), all(column_in), cv::NORM_INF) < 1e-3);
  // Past its own grow_fraction the window is the whole region, as before the window existed.
  IntegrationOptions whole = integration;
  whole.height_field.window_grow_fraction = bundle.reconstruction.detection.grow_fraction;
  CHECK(every.SlopesWindow(region, whole) == region.roi);
  whole.method = IntegrationMethod::kPoisson;
  whole.height_field.window_grow_fraction = 0.0;
  CHECK(every.SlopesWindow(region, whole) == region.roi);
  ReconstructionOptions bad;
  bad.mlp_refine_slope = -0.1;
  CHECK_THROWS_WITH(bad.Check(), Contains("mlp_refine_slope"));
}

TEST_CASE("recon --camera runs live from the virtual rig's camera and records depth",
          "[cli][recon]") {
  Fixture& f = Shared();
  VirtualRigOptions options;
  options.rig.seed = 7;
  options.cnc.time_scale = 1.0;
  options.frame_socket = f.dir / "live.sock";
  VirtualRig rig(options);
  const Result r = Gs360("--json recon --model " + f.model.string() + " --camera " +
                         rig.FrameUri() + " --reference-frames 5 --frames 20 --record " +
                         (f.dir / "live").string() + " < /dev/null");
  INFO(r.out);
  REQUIRE(r.status == 0);
  const nlohmann::json summary = nlohmann::json::parse(r.out.substr(r.out.rfind('{')));
  CHECK(summary.at("frames") == 20);
  CHECK(fs::exists(f.dir / "live" / "frame-000020-depth.png"));
  std::ifstream side(f.dir / "live" / "frame-000020-depth.json");
  CHECK(nlohmann::json::parse(side).at("contacts").empty());  // the tool is far from the gel
}
