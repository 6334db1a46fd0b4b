// Capture benchmark: cost of CapturePress's stale filtering, outlier check and K-frame averaging
// (from memory, no camera), and replay throughput (PNG decode) over a temporary folder.
//
// Usage: bench_capture [--width W] [--height H] [--frames N]
// Prints one line per figure.

#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <deque>
#include <filesystem>
#include <sstream>
#include <string>

#include <CLI/CLI.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "capture/capture_press.h"
#include "capture/frame_source.h"
#include "capture/replay_source.h"

namespace {

using Clock = std::chrono::steady_clock;

// Hands out pre-built frames (stale ones first) without copying pixel data.
class MemorySource : public gs360::FrameSource {
 public:
  MemorySource(std::vector<cv::Mat> images, Clock::time_point sync_ok, int stale)
      : images_(std::move(images)), sync_ok_(sync_ok), stale_(stale) {}
  void Start() override {}
  void Stop() override {}
  std::optional<gs360::Frame> Next(std::chrono::milliseconds) override {
    gs360::Frame f;
    f.image = images_[count_ % images_.size()];
    const bool stale = static_cast<int>(count_ % (images_.size() + stale_)) < stale_;
    f.timestamp = stale ? sync_ok_ - std::chrono::milliseconds(1)
                        : sync_ok_ + std::chrono::milliseconds(1 + static_cast<int>(count_));
    f.sequence = count_++;
    return f;
  }
  std::string Describe() const override { return "memory"; }
  bool IsLive() const override { return true; }

 private:
  std::vector<cv::Mat> images_;
  Clock::time_point sync_ok_;
  int stale_;
  std::uint64_t count_ = 0;
};

cv::Mat RandomImage(cv::Size size) {
  // Smooth-ish content so PNG compression is realistic (random noise does not compress).
  cv::Mat small(size.height / 8, size.width / 8, CV_8UC3);
  cv::randu(small, cv::Scalar::all(0), cv::Scalar::all(256));
  cv::Mat big;
  cv::resize(small, big, size, 0, 0, cv::INTER_CUBIC);
  cv::Mat noise(size, CV_8UC3);
  cv::randn(noise, cv::Scalar::all(0), cv::Scalar::all(2));
  return big + noise;
}

}  // namespace

int main(int argc, char** argv) {
  int width = 640, height = 480, frames = 200;
  CLI::App app("bench_capture: CapturePress averaging cost and replay (PNG decode) throughput");
  app.option_defaults()->always_capture_default();
  app.add_option("--width", width, "frame width, pixels")->check(CLI::PositiveNumber);
  app.add_option("--height", height, "frame height, pixels")->check(CLI::PositiveNumber);
  app.add_option("--frames", frames, "frames per CapturePress setting and replayed from disk")
      ->check(CLI::PositiveNumber);
  CLI11_PARSE(app, argc, argv);
  const cv::Size size(width, height);
  cv::theRNG().state = 1;
  // One settled press seen four times: the same scene, fresh sensor noise in each frame (frames
  // of different scenes would be outliers to each other).
  const cv::Mat scene = RandomImage(size);
  std::vector<cv::Mat> images;
  for (int i = 0; i < 4; ++i) {
    cv::Mat noise(size, CV_16SC3);
    cv::randn(noise, cv::Scalar::all(0), cv::Scalar::all(3));
    cv::Mat frame;
    cv::add(scene, noise, frame, cv::noArray(), CV_8UC3);
    images.push_back(frame);
  }

  std::printf("capture bench, %dx%d BGR frames\n", width, height);
  const Clock::time_point sync_ok = Clock::now();
  for (int k : {1, 3, 5, 10}) {
    for (bool outliers : {false, true}) {
      if (k == 1 && outliers) continue;  // nothing to compare
      MemorySource source(images, sync_ok, 2);
      gs360::PressCaptureOptions options;
      options.frames_to_average = k;
      options.reject_outliers = outliers;
      const int presses = std::max(10, frames / k);
      const auto t0 = Clock::now();
      for (int p = 0; p < presses; ++p) {
        const auto result = gs360::CapturePress(source, sync_ok, options);
        if (!result.ok() || result.outliers_rejected != 0) {
          std::fprintf(stderr, "unexpected status: %s\n",
                       std::string(gs360::ToString(result.status)).c_str());
          return 1;
        }
      }
      const double ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
      std::printf("  CapturePress K=%-2d (2 stale + K fresh per press)%s: %8.3f ms/press\n", k,
                  outliers ? ", outlier check" : "", ms / presses);
    }
  }

  namespace fs = std::filesystem;
  const fs::path dir =
      fs::temp_directory_path() / ("gs360_capture_bench_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  std::uintmax_t bytes = 0;
  const auto w0 = Clock::now();
  for (int i = 0; i < frames; ++i) {
    char name[32];
    std::snprintf(name, sizeof(name), "frame_%06d.png", i);
    cv::imwrite((dir / name).string(), images[static_cast<std::size_t>(i) % images.size()]);
    bytes += fs::file_size(dir / name);
  }
  const double write_s = std::chrono::duration<double>(Clock::now() - w0).count();
  {
    auto source = gs360::OpenFrameSource("replay:" + dir.string(), {});
    source->Start();
    const auto t0 = Clock::now();
    int n = 0;
    while (source->Next(std::chrono::milliseconds(1000))) ++n;
    const double s = std::chrono::duration<double>(Clock::now() - t0).count();
    std::printf("  replay (PNG decode, %d frames, %.0f KiB each): %8.1f frames/s (%.2f ms/frame)\n",
                n, static_cast<double>(bytes) / frames / 1024.0, n / s, 1000.0 * s / n);
    std::printf("  (writing them with cv::imwrite PNG defaults: %.2f ms/frame)\n",
                1000.0 * write_s / frames);
  }
  fs::remove_all(dir);
  return 0;
}
