// Writes what the Python module's test needs, into the folder given: a model calibrated on the
// virtual rig (model.gs360model) and two raw 640 x 480 BGR frames (press.bgr with a 1 mm press on
// the side, empty.bgr without contact), plus the press's true peak in press.txt.

#include <cstdio>
#include <filesystem>
#include <fstream>

#include "cli/sim_model.h"
#include "sim/tactile_camera.h"

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: make_model DIR\n");
    return 2;
  }
  namespace fs = std::filesystem;
  const fs::path dir = argv[1];
  fs::create_directories(dir);
  gs360::cli::SimModelOptions o;
  o.probes = 150;
  o.hidden = {32, 32};
  o.epochs = 10;
  fs::copy_file(gs360::cli::MakeSimModel(dir / "work", o), dir / "model.gs360model",
                fs::copy_options::overwrite_existing);
  gs360::SimRigOptions so;
  so.seed = o.seed;
  auto rig = std::make_shared<const gs360::SimRig>(so);
  gs360::TactileCamera camera(rig);
  const auto press = gs360::cli::SimPresses(*rig, 1, 1.0, 99).front();
  const auto write = [&](const fs::path& path, const cv::Mat& image) {
    std::ofstream(path, std::ios::binary)
        .write(reinterpret_cast<const char*>(image.data),
               static_cast<std::streamsize>(image.total() * image.elemSize()));
  };
  write(dir / "press.bgr", camera.RenderAtBall(press.ball_sensor, 1000, 10.0));
  write(dir / "empty.bgr", camera.RenderReference(1001, 10.0));
  std::printf("%s\n", dir.c_str());
  return 0;
}
