// bench_train: MLP training throughput (samples/s per epoch) on 1 and 2 threads, Forward
// (inference) throughput, and optionally a comparison of activations / schedules by validation
// loss, on synthetic calibration-like data: features (u, v, dR, dG, dB) from a three-light
// shading model of random slopes, targets the slopes (gx, gy).
//
// Usage: bench_train [--samples N] [--epochs E] [--compare] [--compare-samples N]
//                    [--compare-epochs E]
//                    [--compare-seed S]

#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <random>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "calib/train.h"

namespace {

using gs360::Activation;
using gs360::LearningRateSchedule;
using gs360::TrainOptions;

struct Data {
  Eigen::MatrixXf x, y;
};

// 75% contact pixels with random slopes, 25% non-contact (zero slope), 3 coloured lights whose
// direction varies over the image, a little noise.
Data MakeData(int n, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  std::normal_distribution<float> slope(0.0f, 0.6f), noise(0.0f, 0.005f);
  Data d{Eigen::MatrixXf(5, n), Eigen::MatrixXf(2, n)};
  for (int i = 0; i < n; ++i) {
    const float u = unit(rng), v = unit(rng);
    const bool contact = unit(rng) < 0.75f;
    const float gx = contact ? slope(rng) : 0.0f;
    const float gy = contact ? slope(rng) : 0.0f;
    const Eigen::Vector3f normal = Eigen::Vector3f(-gx, -gy, 1.0f).normalized();
    const Eigen::Vector3f n0(0.0f, 0.0f, 1.0f);
    d.x(0, i) = 800.0f * u;
    d.x(1, i) = 800.0f * v;
    for (int c = 0; c < 3; ++c) {
      const float a = 2.0944f * static_cast<float>(c) + 1.5f * (u - 0.5f);
      const Eigen::Vector3f light =
          Eigen::Vector3f(std::cos(a), std::sin(a) + 0.5f * (v - 0.5f), 0.7f).normalized();
      d.x(2 + c, i) =
          std::max(0.0f, normal.dot(light)) - std::max(0.0f, n0.dot(light)) + noise(rng);
    }
    d.y(0, i) = gx;
    d.y(1, i) = gy;
  }
  return d;
}

double Seconds(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace

int main(int argc, char** argv) {
  int samples = 1'000'000;
  int epochs = 3;
  bool compare = false;
  int compare_samples = 200'000;
  int compare_epochs = 60;
  int compare_seed = 1;
  CLI::App app(
      "bench_train: MLP training throughput on 1 and 2 threads, Forward throughput and an "
      "optional comparison of activations / schedules by validation loss");
  app.option_defaults()->always_capture_default();
  app.add_option("--samples", samples, "training samples")->check(CLI::PositiveNumber);
  app.add_option("--epochs", epochs, "epochs per throughput run")->check(CLI::PositiveNumber);
  app.add_flag("--compare", compare, "also compare activations / schedules by validation loss");
  app.add_option("--compare-samples", compare_samples, "training samples of the comparison")
      ->check(CLI::PositiveNumber);
  app.add_option("--compare-epochs", compare_epochs, "epochs of the comparison")
      ->check(CLI::PositiveNumber);
  app.add_option("--compare-seed", compare_seed, "seed of the comparison's data and training");
  CLI11_PARSE(app, argc, argv);

  const Data train = MakeData(samples, 1);
  const Data val = MakeData(std::max(1000, samples / 20), 2);
  {
    const TrainOptions defaults;
    std::string net = "5";
    for (int h : defaults.hidden) net += "-" + std::to_string(h);
    std::printf(
        "bench_train: %d training samples, %d validation, net %s-2, batch %d, Fourier "
        "features %d x %d (the defaults; the real model also takes 18 context features)\n",
        samples, static_cast<int>(val.x.cols()), net.c_str(), defaults.batch_size,
        defaults.fourier.inputs, defaults.fourier.frequencies);
  }

  struct Variant {
    Activation activation;
    bool fourier;
  };
  for (const Variant variant :
       {Variant{Activation::kTanh, true}, Variant{Activation::kTanh, false},
        Variant{Activation::kSilu, true}, Variant{Activation::kRelu, true}}) {
    const Activation act = variant.activation;
    for (int threads : {1, 2}) {
      TrainOptions options;
      if (!variant.fourier) options.fourier = {};
      options.activation = act;
      options.threads = threads;
      options.max_epochs = epochs;
      options.patience = 0;
      const std::clock_t cpu0 = std::clock();
      const gs360::TrainResult r = gs360::Train(train.x, train.y, val.x, val.y, options);
      const double cpu = static_cast<double>(std::clock() - cpu0) / CLOCKS_PER_SEC;
      double best = 1e30;
      for (const auto& e : r.curve) best = std::min(best, e.seconds);
      // Wall-clock rate of the fastest epoch (training + validation pass), and the rate per
      // CPU-second over the whole call (less sensitive to other load on the machine).
      std::printf(
          "  train %-4s %-10s threads %d: %.2f M samples/s wall (best epoch of %d: %.3f s incl. "
          "validation), %.2f M samples per CPU-s, val loss %.4g\n",
          std::string(gs360::ToString(act)).c_str(), variant.fourier ? "fourier" : "no-fourier",
          threads, samples / best / 1e6, epochs, best,
          static_cast<double>(samples) * epochs / cpu / 1e6, r.best_val_loss);
    }
  }

  {
    struct ForwardVariant {
      Activation activation;
      std::vector<int> sizes;
      gs360::FourierFeatures fourier;
      const char* name;
    };
    const std::vector<ForwardVariant> variants = {
        {Activation::kTanh,
         {23, 128, 128, 128, 2},
         {2, 4, 1.0f},
         "23-128-128-128-2 fourier (default)"},
        {Activation::kTanh, {5, 64, 64, 64, 2}, {2, 4, 1.0f}, "5-64-64-64-2 fourier 2x4"},
        {Activation::kTanh, {5, 64, 64, 64, 2}, {}, "5-64-64-64-2"},
        {Activation::kTanh, {5, 128, 128, 128, 2}, {}, "5-128-128-128-2"},
        {Activation::kTanh, {5, 32, 32, 32, 2}, {}, "5-32-32-32-2"},
        {Activation::kSilu, {5, 32, 32, 32, 2}, {}, "5-32-32-32-2"},
        {Activation::kRelu, {5, 32, 32, 32, 2}, {}, "5-32-32-32-2"}};
    for (const ForwardVariant& v : variants) {
      const Activation act = v.activation;
      gs360::Mlp m(v.sizes, act, 1, v.fourier);
      // The synthetic data has 5 features; wider inputs get random context-like rows below them.
      Eigen::MatrixXf x = train.x;
      if (v.sizes.front() > x.rows()) {
        const Eigen::Index extra = v.sizes.front() - x.rows();
        x.conservativeResize(v.sizes.front(), Eigen::NoChange);
        x.bottomRows(extra) = 0.05f * Eigen::MatrixXf::Random(extra, x.cols());
      }
      const int repeats = 3;
      double best = 1e30;
      for (int rep = 0; rep < repeats; ++rep) {
        const auto t0 = std::chrono::steady_clock::now();
        const Eigen::MatrixXf y = m.Forward(x);
        best = std::min(best, Seconds(t0));
        if (!y.allFinite()) std::printf("non-finite output\n");
      }
      std::printf("  Forward %-4s %-26s (1 thread): %.2f M samples/s (%.3f s for %d)\n",
                  std::string(gs360::ToString(act)).c_str(), v.name, samples / best / 1e6, best,
                  samples);
    }
  }

  if (compare) {
    const Data ctrain = MakeData(compare_samples, 3 + 2 * static_cast<std::uint64_t>(compare_seed));
    const Data cval =
        MakeData(compare_samples / 5, 4 + 2 * static_cast<std::uint64_t>(compare_seed));
    std::printf("compare: %d train / %d val samples, up to %d epochs, patience 12, 2 threads\n",
                compare_samples, static_cast<int>(cval.x.cols()), compare_epochs);
    for (LearningRateSchedule schedule :
         {LearningRateSchedule::kPlateau, LearningRateSchedule::kCosine}) {
      for (Activation act : {Activation::kTanh, Activation::kSilu, Activation::kRelu}) {
        TrainOptions options;
        options.activation = act;
        options.schedule = schedule;
        options.max_epochs = compare_epochs;
        options.seed = static_cast<std::uint64_t>(compare_seed);
        const gs360::TrainResult r = gs360::Train(ctrain.x, ctrain.y, cval.x, cval.y, options);
        std::printf("  %-8s %-4s: best val loss %.5f at epoch %d of %zu (%s), rmse %.4f, %.1f s\n",
                    std::string(gs360::ToString(schedule)).c_str(),
                    std::string(gs360::ToString(act)).c_str(), r.best_val_loss, r.best_epoch,
                    r.curve.size(), r.stopped_early ? "stopped early" : "ran out",
                    std::sqrt(r.best_val_loss), r.seconds);
      }
    }
  }
  return 0;
}
