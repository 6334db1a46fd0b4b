// bench_storage: what committing press frames costs, on one core.
//
// Frames look like the sensor's: 640x480 colour, a smooth lit-gel colour field (side LEDs in red
// and green, a blue ring from the base, vignetting) plus Gaussian sensor noise and 8-bit
// quantisation. Reports PNG encode speed and size for several settings, then encode + commit
// through RunDatabase::CommitCapture (one transaction per frame, as the run engine does) in
// both synchronous modes, the database size per 1,000 frames, and checksum-verified load speed.
//
//   bench_storage [--frames N] [--sigma S] [--dir DIR]
// Pin it to one core for the "one core" figure: taskset -c 0 bench_storage

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

#include <time.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <opencv2/core.hpp>

#include "storage/run_database.h"

namespace {

using Clock = std::chrono::steady_clock;
namespace fs = std::filesystem;

double Seconds(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double>(b - a).count();
}

// CPU time of this thread: what one core spends, whatever else the machine is doing.
double ThreadCpuSeconds() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

// A lit gel seen by the camera: smooth colour field, vignetting, noise, quantisation.
cv::Mat GelFrame(int seed, double sigma) {
  constexpr int kW = 640, kH = 480;
  std::mt19937 rng(static_cast<unsigned>(seed));
  std::normal_distribution<double> noise(0.0, sigma);
  std::uniform_real_distribution<double> jitter(-0.05, 0.05);
  const double dx = jitter(rng), dy = jitter(rng);
  cv::Mat out(kH, kW, CV_8UC3);
  for (int y = 0; y < kH; ++y) {
    auto* row = out.ptr<cv::Vec3b>(y);
    for (int x = 0; x < kW; ++x) {
      const double u = (x - 0.5 * kW) / (0.5 * kH) + dx, v = (y - 0.5 * kH) / (0.5 * kH) + dy;
      const double r2 = u * u + v * v;
      const double vignette = 1.0 / (1.0 + 0.35 * r2);
      const double blue = 150.0 * std::exp(-1.5 * r2) + 25.0;                 // ring at the base
      const double green = 60.0 + 55.0 * std::max(0.0, v) + 15.0 * u * u;     // yz board
      const double red = 55.0 + 60.0 * std::abs(u) * std::exp(-0.5 * v * v);  // xz board
      const double bgr[3] = {blue, green, red};
      for (int c = 0; c < 3; ++c) {
        row[x][c] = cv::saturate_cast<uchar>(std::lround(bgr[c] * vignette + noise(rng)));
      }
    }
  }
  return out;
}

struct Setting {
  const char* name;
  gs360::PngOptions png;
  int reps;
};

// The database file plus whatever WAL is left beside it.
std::uintmax_t DatabaseSize(const fs::path& path) {
  std::uintmax_t total = fs::file_size(path);
  for (const char* suffix : {"-wal", "-shm"}) {
    fs::path extra = path;
    extra += suffix;
    if (fs::exists(extra)) total += fs::file_size(extra);
  }
  return total;
}

}  // namespace

int main(int argc, char** argv) {
  using namespace gs360;
  int frames = 1000;
  double sigma = 1.7;
  std::string dir_arg;
  CLI::App app("bench_storage: PNG encode + commit throughput of the run database");
  app.add_option("--frames", frames, "frames committed per synchronous mode")
      ->check(CLI::PositiveNumber);
  app.add_option("--sigma", sigma, "sensor noise, grey levels");
  app.add_option("--dir", dir_arg, "where to put the benchmark databases (default: temp dir)");
  CLI11_PARSE(app, argc, argv);

  cv::setNumThreads(1);
  const fs::path dir = dir_arg.empty() ? fs::temp_directory_path() /
                                             ("gs360_bench_storage_" + std::to_string(::getpid()))
                                       : fs::path(dir_arg);
  fs::create_directories(dir);

  constexpr int kPool = 16;
  std::vector<cv::Mat> pool;
  for (int i = 0; i < kPool; ++i) pool.push_back(GelFrame(i, sigma));
  std::printf(
      "frames: 640x480 8UC3, smooth lit-gel field + Gaussian noise sigma=%.2f, %d distinct\n",
      sigma, kPool);
  std::printf("single thread (cv::setNumThreads(1)); pin with taskset -c 0 for one core\n\n");

  // ---- PNG encoding alone ----
  const std::vector<Setting> settings = {
      {"fast path (Sub, zlib 1) + huffman-only [default]", {}, 32},
      {"fast path (Sub, zlib 1) + RLE [OpenCV default]", {.strategy = PngStrategy::kRle}, 32},
      {"zlib 1, adaptive filters, huffman-only",
       {.compression_level = 1, .strategy = PngStrategy::kHuffmanOnly},
       16},
      {"zlib 1, adaptive filters, default strategy",
       {.compression_level = 1, .strategy = PngStrategy::kDefault},
       16},
      {"zlib 6, adaptive filters, default strategy",
       {.compression_level = 6, .strategy = PngStrategy::kDefault},
       4},
  };

  std::printf("PNG encode only%41s %8s %8s %9s %9s %7s\n", "", "cpu ms", "wall ms", "fps(cpu)",
              "kB/frame", "ratio");
  for (const Setting& s : settings) {
    std::size_t bytes = 0;
    const auto t0 = Clock::now();
    const double c0 = ThreadCpuSeconds();
    for (int i = 0; i < s.reps; ++i) bytes += EncodeFrame(pool[i % kPool], s.png).png.size();
    const double cpu = (ThreadCpuSeconds() - c0) / s.reps;
    const double wall = Seconds(t0, Clock::now()) / s.reps;
    const double kb = bytes / 1000.0 / s.reps;
    std::printf("  %-54s %8.2f %8.2f %9.1f %9.1f %7.3f\n", s.name, cpu * 1e3, wall * 1e3, 1.0 / cpu,
                kb, kb * 1000.0 / (640 * 480 * 3));
  }

  // ---- encode + commit, one transaction per frame ----
  std::printf("\nencode + commit via RunDatabase::CommitCapture, %d frames, default PNG settings\n",
              frames);
  std::printf("  %-7s %9s %9s %9s %10s %10s %11s %10s\n", "sync", "fps wall", "fps cpu", "ms/frame",
              "encode ms", "commit ms", "MB/1000 fr", "load fps");
  for (const SyncMode mode : {SyncMode::kFull, SyncMode::kNormal}) {
    const char* name = mode == SyncMode::kFull ? "FULL" : "NORMAL";
    const fs::path path = dir / (std::string("bench_") + name + ".gs360db");
    fs::remove(path);
    double encode_s = 0, total_s = 0, total_cpu = 0, load_s = 0;
    std::int64_t run = 0;
    std::vector<std::int64_t> frame_ids;
    {
      RunDatabaseOptions options;
      options.synchronous = mode;
      RunDatabase db(path, options);
      run = db.CreateRun(R"({"bench": true})", "bench");
      const std::vector<std::int64_t> ids =
          db.InsertPlan(run, std::vector<ProbePlanEntry>(static_cast<std::size_t>(frames)));
      db.SetRunState(run, RunState::kRunning);
      const auto t0 = Clock::now();
      const double c0 = ThreadCpuSeconds();
      for (int i = 0; i < frames; ++i) {
        const auto e0 = Clock::now();
        const EncodedFrame encoded = EncodeFrame(pool[i % kPool], options.png);
        encode_s += Seconds(e0, Clock::now());
        const double t = 1.7e9 + 4.0 * i;
        frame_ids.push_back(
            db.CommitCapture(ids[static_cast<std::size_t>(i)], encoded, {{1, 2, 3}, t, t + 0.1}));
      }
      total_s = Seconds(t0, Clock::now());
      total_cpu = ThreadCpuSeconds() - c0;
      db.SetRunState(run, RunState::kDone);
    }  // closing checkpoints the WAL into the main file
    const double mb_per_1000 = static_cast<double>(DatabaseSize(path)) / 1e6 * 1000.0 / frames;
    {
      RunDatabase db(path, {.read_only = true});
      const int loads = std::min(frames, 200);
      const auto t0 = Clock::now();
      for (int i = 0; i < loads; ++i) {
        if (db.LoadFrame(frame_ids[static_cast<std::size_t>(i)]).empty()) return 1;
      }
      load_s = Seconds(t0, Clock::now()) / loads;
    }
    std::printf("  %-7s %9.1f %9.1f %9.2f %10.2f %10.2f %11.1f %10.1f\n", name, frames / total_s,
                frames / total_cpu, total_s / frames * 1e3, encode_s / frames * 1e3,
                (total_s - encode_s) / frames * 1e3, mb_per_1000, 1.0 / load_s);
    fs::remove(path);
  }
  std::printf(
      "\nfps wall: frames / elapsed time; fps cpu: frames / CPU time of this thread (excludes\n"
      "waiting for fsync and other processes); encode/commit ms: wall time per frame;\n"
      "MB/1000 fr: database size after close, per 1,000 frames; load fps: LoadFrame with\n"
      "checksum check and PNG decode.\n");
  if (dir_arg.empty()) fs::remove_all(dir);
  return 0;
}
