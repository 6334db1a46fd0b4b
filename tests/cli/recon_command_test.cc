// `gs360 recon` as a user runs it: the real executable on a model calibrated on the virtual rig
// and frames rendered by it; the files it writes open in standard tools (OpenCV, assimp, JSON).

#include <catch2/catch.hpp>

#include <assimp/scene.h>
#include <sys/wait.h>

#include <array>
#include <assimp/Importer.hpp>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "cli/sim_model.h"
#include "sim/tactile_camera.h"

using namespace gs360;
using Catch::Contains;
namespace fs = std::filesystem;

namespace {

struct Result {
  int status = -1;
  std::string out;  // stdout and stderr
};

Result Gs360(const std::string& args) {
  const std::string command = std::string(GS360_BINARY_DIR) + "/cli/gs360 " + args + " 2>&1";
  Result r;
  FILE* pipe = ::popen(command.c_str(), "r");
  REQUIRE(pipe != nullptr);
  std::array<char, 4096> buf{};
  while (std::fgets(buf.data(), buf.size(), pipe)) r.out += buf.data();
  const int status = ::pclose(pipe);
  r.status = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

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
