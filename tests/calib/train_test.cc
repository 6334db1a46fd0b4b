#include "calib/train.h"

#include <catch2/catch.hpp>
#include <cmath>
#include <limits>
#include <numbers>
#include <random>
#include <stdexcept>
#include <string>

namespace gs360 {
namespace {

struct Data {
  Eigen::MatrixXf x, y;
};

// y = (sin(u) + v^2, u v) on [-1, 1]^2; inputs shifted and scaled so that the normalisation
// matters.
Data SmoothFunction(int n, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> unit(-1.0f, 1.0f);
  Data d{Eigen::MatrixXf(2, n), Eigen::MatrixXf(2, n)};
  for (int i = 0; i < n; ++i) {
    const float u = unit(rng), v = unit(rng);
    d.x(0, i) = 100.0f + 50.0f * u;
    d.x(1, i) = -3.0f + 0.01f * v;
    d.y(0, i) = std::sin(u) + v * v;
    d.y(1, i) = u * v;
  }
  return d;
}

bool SameWeights(const Mlp& a, const Mlp& b) {
  if (a.layers().size() != b.layers().size()) return false;
  for (std::size_t k = 0; k < a.layers().size(); ++k) {
    if (a.layers()[k].weight != b.layers()[k].weight) return false;
    if (a.layers()[k].bias != b.layers()[k].bias) return false;
  }
  return true;
}

TrainOptions SmallOptions() {
  TrainOptions o;
  o.hidden = {24, 24};
  o.batch_size = 128;
  o.max_epochs = 40;
  o.patience = 0;
  o.seed = 42;
  o.threads = 2;
  return o;
}

template <typename Mutate>
std::string CheckMessage(Mutate mutate) {
  TrainOptions o;
  mutate(o);
  try {
    o.Check();
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "";
}

}  // namespace

TEST_CASE("Train learns a smooth function with every activation", "[train]") {
  const Data train = SmoothFunction(8000, 1);
  const Data val = SmoothFunction(2000, 2);
  for (Activation activation : {Activation::kTanh, Activation::kSilu, Activation::kRelu}) {
    INFO("activation " << ToString(activation));
    TrainOptions o = SmallOptions();
    o.activation = activation;
    const TrainResult r = Train(train.x, train.y, val.x, val.y, o);
    REQUIRE(r.curve.size() == 40u);
    CHECK_FALSE(r.stopped_early);
    CHECK(r.mlp.sizes() == std::vector<int>{2, 24, 24, 2});
    CHECK(r.mlp.activation() == activation);
    // Normalised validation MSE: well below the 1.0 of predicting the mean.
    // (measured: tanh 1.4e-4, silu 1.8e-4, relu 1.0e-3)
    const bool relu = activation == Activation::kRelu;
    CHECK(r.best_val_loss < (relu ? 3e-3 : 5e-4));
    CHECK(r.curve.front().val_loss > 5.0 * r.best_val_loss);
    // The same in output units: RMS error of a few thousandths (outputs span about [-1, 2]).
    const Eigen::MatrixXf pred = r.mlp.Forward(val.x);
    const double rms = std::sqrt((pred - val.y).squaredNorm() / static_cast<double>(pred.size()));
    CHECK(rms < (relu ? 0.03 : 0.012));
    // The normalisation comes from the training set.
    CHECK(r.mlp.input_mean()[0] == Approx(100.0).margin(1.5));
    CHECK(r.mlp.input_scale()[0] == Approx(50.0 / std::sqrt(3.0)).epsilon(0.03));
    CHECK(r.mlp.input_scale()[1] == Approx(0.01 / std::sqrt(3.0)).epsilon(0.03));
    CHECK(r.mlp.output_mean()[1] == Approx(0.0).margin(0.02));
  }
}

TEST_CASE("Loss gradient matches central finite differences", "[train]") {
  for (Activation activation : {Activation::kTanh, Activation::kSilu, Activation::kRelu}) {
    for (const FourierFeatures fourier : {FourierFeatures{}, FourierFeatures{2, 3, 0.8f}}) {
      INFO("activation " << ToString(activation) << " fourier " << fourier.Width());
      Mlp mlp({3, 6, 5, 2}, activation, 17, fourier);
      for (auto& layer : mlp.layers()) layer.bias = Eigen::VectorXf::Random(layer.bias.size());
      mlp.SetInputNormalization(Eigen::Vector3f(1.0f, -2.0f, 0.5f),
                                Eigen::Vector3f(2.0f, 0.5f, 1.0f));
      mlp.SetOutputNormalization(Eigen::Vector2f(0.3f, -0.1f), Eigen::Vector2f(0.7f, 1.3f));
      Eigen::MatrixXf x = Eigen::MatrixXf::Random(3, 20) * 2.0f;
      const Eigen::MatrixXf y = Eigen::MatrixXf::Random(2, 20);
      const LossGradient g = ComputeLossGradient(mlp, x, y);
      CHECK(g.loss == Approx(EvaluateLoss(mlp, x, y)).epsilon(1e-5));
      REQUIRE(g.gradient.size() == 3u);
      const float h = 1e-2f;
      int checked = 0, matched = 0;
      const auto check = [&](float& param, float analytic) {
        const float saved = param;
        param = saved + h;
        const double plus = EvaluateLoss(mlp, x, y);
        param = saved - h;
        const double minus = EvaluateLoss(mlp, x, y);
        param = saved;
        const double numeric = (plus - minus) / (2.0 * h);
        ++checked;
        if (std::abs(numeric - analytic) <= 2e-3 + 0.02 * std::abs(numeric)) ++matched;
      };
      for (std::size_t k = 0; k < 3; ++k) {
        auto& layer = mlp.layers()[k];
        REQUIRE(g.gradient[k].weight.rows() == layer.weight.rows());
        REQUIRE(g.gradient[k].weight.cols() == layer.weight.cols());
        for (Eigen::Index r = 0; r < layer.weight.rows(); ++r) {
          for (Eigen::Index c = 0; c < layer.weight.cols(); ++c) {
            check(layer.weight(r, c), g.gradient[k].weight(r, c));
          }
          check(layer.bias[r], g.gradient[k].bias[r]);
        }
      }
      CHECK(checked == mlp.ParameterCount());
      // relu has kinks that a finite step may cross; the smooth activations must match everywhere.
      if (activation == Activation::kRelu) {
        CHECK(matched >= checked * 9 / 10);
      } else {
        CHECK(matched == checked);
      }
      // A gradient step lowers the loss.
      for (std::size_t k = 0; k < 3; ++k) {
        mlp.layers()[k].weight -= 0.05f * g.gradient[k].weight;
        mlp.layers()[k].bias -= 0.05f * g.gradient[k].bias;
      }
      CHECK(EvaluateLoss(mlp, x, y) < g.loss);
    }
  }
  CHECK_THROWS_AS(ComputeLossGradient(Mlp({3, 2}, Activation::kTanh, 1), Eigen::MatrixXf(2, 4),
                                      Eigen::MatrixXf(2, 4)),
                  std::invalid_argument);
}

TEST_CASE("Fourier features let a small network follow a pattern across the image", "[train]") {
  // A target that oscillates across the image (like the fin shadows and LED fall-off the
  // calibration MLP must follow) plus a smooth dependence on a colour-like input.
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<float> unit(-1.0f, 1.0f);
  const auto make = [&](int n) {
    Data d{Eigen::MatrixXf(3, n), Eigen::MatrixXf(1, n)};
    for (int i = 0; i < n; ++i) {
      const float u = unit(rng), v = unit(rng), c = unit(rng);
      d.x(0, i) = 320.0f + 300.0f * u;
      d.x(1, i) = 240.0f + 220.0f * v;
      d.x(2, i) = 0.1f * c;
      d.y(0, i) = std::sin(9.0f * u) * std::cos(7.0f * v) + c;
    }
    return d;
  };
  const Data train = make(6000), val = make(1000);
  TrainOptions o = SmallOptions();
  o.hidden = {16, 16};
  o.max_epochs = 30;
  o.fourier = {};
  const TrainResult plain = Train(train.x, train.y, val.x, val.y, o);
  o.fourier = FourierFeatures{2, 4, 1.0f};
  const TrainResult fourier = Train(train.x, train.y, val.x, val.y, o);
  CHECK(fourier.mlp.fourier().frequencies == 4);
  CHECK(fourier.mlp.layers()[0].weight.cols() == 3 + 16);
  INFO("val loss plain " << plain.best_val_loss << " fourier " << fourier.best_val_loss);
  CHECK(fourier.best_val_loss < 0.5 * plain.best_val_loss);
  // More encoded inputs than features is a clear error.
  o.fourier = FourierFeatures{4, 2, 1.0f};
  try {
    Train(train.x, train.y, val.x, val.y, o);
    FAIL("no throw");
  } catch (const std::invalid_argument& e) {
    CHECK(std::string(e.what()).find("fourier.inputs = 4") != std::string::npos);
  }
}

TEST_CASE("Train reports a consistent curve and calls progress", "[train]") {
  const Data train = SmoothFunction(3000, 3);
  const Data val = SmoothFunction(800, 4);
  TrainOptions o = SmallOptions();
  o.max_epochs = 6;
  o.schedule = LearningRateSchedule::kCosine;
  o.min_learning_rate = 1e-4;
  std::vector<std::pair<double, double>> seen;
  const TrainResult r =
      Train(train.x, train.y, val.x, val.y, o, [&](int epoch, double t, double v) {
        CHECK(epoch == static_cast<int>(seen.size()));
        seen.emplace_back(t, v);
      });
  REQUIRE(seen.size() == 6u);
  REQUIRE(r.curve.size() == 6u);
  double best = std::numeric_limits<double>::infinity();
  for (int e = 0; e < 6; ++e) {
    const TrainEpoch& ep = r.curve[static_cast<std::size_t>(e)];
    CHECK(ep.epoch == e);
    CHECK(ep.train_loss == seen[static_cast<std::size_t>(e)].first);
    CHECK(ep.val_loss == seen[static_cast<std::size_t>(e)].second);
    CHECK(ep.seconds > 0.0);
    CHECK(ep.seconds <= r.seconds);
    const double cosine = 1e-4 + 0.5 * (3e-3 - 1e-4) * (1.0 + std::cos(std::numbers::pi * e / 6.0));
    CHECK(ep.learning_rate == Approx(cosine).epsilon(1e-12));
    best = std::min(best, ep.val_loss);
  }
  CHECK(r.best_val_loss == best);
  CHECK(r.curve[static_cast<std::size_t>(r.best_epoch)].val_loss == best);
  // The returned weights are the best epoch's: the loss recomputed on them is the same number.
  CHECK(EvaluateLoss(r.mlp, val.x, val.y, o.threads) == r.best_val_loss);
}

TEST_CASE("Train stops early and keeps the best epoch", "[train]") {
  // The validation targets contradict the training targets, so the validation loss gets worse
  // as the network fits the training set: the best epoch is an early one.
  const Data train = SmoothFunction(3000, 5);
  Data val = SmoothFunction(800, 6);
  val.y = -val.y;
  TrainOptions o = SmallOptions();
  o.max_epochs = 100;
  o.patience = 5;
  o.plateau_epochs = 2;
  o.plateau_threshold = 0.0;
  const TrainResult r = Train(train.x, train.y, val.x, val.y, o);
  CHECK(r.stopped_early);
  REQUIRE(r.best_epoch >= 0);
  CHECK(r.curve.size() == static_cast<std::size_t>(r.best_epoch + 1 + o.patience));
  CHECK(r.curve.back().val_loss > r.best_val_loss);
  CHECK(EvaluateLoss(r.mlp, val.x, val.y, o.threads) == r.best_val_loss);
  CHECK(EvaluateLoss(r.mlp, val.x, val.y, o.threads) <
        r.curve.back().val_loss);  // not the last epoch's weights
  // The plateau schedule halved the rate while the validation loss did not improve.
  CHECK(r.curve.back().learning_rate < o.learning_rate * 0.49);
  CHECK(r.curve.front().learning_rate == o.learning_rate);
}

TEST_CASE("Train is reproducible for a seed and thread count", "[train]") {
  const Data train = SmoothFunction(2000, 7);
  const Data val = SmoothFunction(500, 8);
  TrainOptions o = SmallOptions();
  o.max_epochs = 3;
  o.batch_size = 100;  // a last partial batch, uneven chunks
  const TrainResult a = Train(train.x, train.y, val.x, val.y, o);
  const TrainResult b = Train(train.x, train.y, val.x, val.y, o);
  CHECK(SameWeights(a.mlp, b.mlp));
  for (std::size_t e = 0; e < a.curve.size(); ++e) {
    CHECK(a.curve[e].train_loss == b.curve[e].train_loss);
    CHECK(a.curve[e].val_loss == b.curve[e].val_loss);
  }
  o.seed = 43;
  const TrainResult c = Train(train.x, train.y, val.x, val.y, o);
  CHECK_FALSE(SameWeights(a.mlp, c.mlp));
  // Another thread count: the same maths, different rounding, so a close loss.
  o.seed = 42;
  o.threads = 1;
  const TrainResult d = Train(train.x, train.y, val.x, val.y, o);
  CHECK(d.best_val_loss == Approx(a.best_val_loss).epsilon(0.05));
}

TEST_CASE("a killed training resumes from its checkpoint with bit-identical weights", "[train]") {
  const Data train = SmoothFunction(2000, 7);
  const Data val = SmoothFunction(500, 8);
  TrainOptions o = SmallOptions();
  o.max_epochs = 12;
  o.batch_size = 100;
  o.plateau_epochs = 1;  // the rate changes on the way: the schedule's state must survive too
  o.plateau_threshold = 0.3;
  const TrainResult whole = Train(train.x, train.y, val.x, val.y, o);
  REQUIRE(whole.curve.size() == 12);
  REQUIRE(whole.curve.back().learning_rate < o.learning_rate);

  // Killed after epoch 4 (the progress callback throws, as a SIGKILL would end it there).
  std::vector<std::uint8_t> last;
  TrainCheckpointing save;
  save.save = [&](int, const std::vector<std::uint8_t>& state) { last = state; };
  struct Killed {};
  CHECK_THROWS_AS(Train(
                      train.x, train.y, val.x, val.y, o,
                      [](int epoch, double, double) {
                        if (epoch == 5) throw Killed{};
                      },
                      save),
                  Killed);
  REQUIRE(TrainCheckpointEpoch(last) == 4);

  TrainCheckpointing resume;
  resume.resume_from = last;
  std::vector<int> epochs_run;
  const TrainResult resumed = Train(
      train.x, train.y, val.x, val.y, o,
      [&](int epoch, double, double) { epochs_run.push_back(epoch); }, resume);
  CHECK(epochs_run.front() == 5);
  CHECK(epochs_run.size() == 7);
  CHECK(SameWeights(resumed.mlp, whole.mlp));
  CHECK(resumed.best_epoch == whole.best_epoch);
  CHECK(resumed.best_val_loss == whole.best_val_loss);
  REQUIRE(resumed.curve.size() == whole.curve.size());
  for (std::size_t e = 0; e < whole.curve.size(); ++e) {
    CHECK(resumed.curve[e].val_loss == whole.curve[e].val_loss);
    CHECK(resumed.curve[e].learning_rate == whole.curve[e].learning_rate);
  }

  // A checkpoint of another training, a truncated one, foreign bytes: a clear error.
  TrainOptions other = o;
  other.threads = 1;
  CHECK_THROWS_WITH(Train(train.x, train.y, val.x, val.y, other, {}, resume),
                    Catch::Contains("checkpoint is of another training") &&
                        Catch::Contains("threads 2 in the checkpoint, 1 here"));
  TrainCheckpointing truncated;
  truncated.resume_from.assign(last.begin(), last.begin() + static_cast<long>(last.size() / 2));
  CHECK_THROWS_WITH(Train(train.x, train.y, val.x, val.y, o, {}, truncated),
                    Catch::Contains("the checkpoint: truncated input"));
  TrainCheckpointing foreign;
  foreign.resume_from = std::vector<std::uint8_t>(64, 7);
  CHECK_THROWS_WITH(Train(train.x, train.y, val.x, val.y, o, {}, foreign),
                    Catch::Contains("not a training checkpoint"));
}

TEST_CASE("Train handles tiny batches and more threads than samples", "[train]") {
  Data train = SmoothFunction(5, 9);
  const Data val = SmoothFunction(3, 10);
  TrainOptions o = SmallOptions();
  o.max_epochs = 2;
  o.threads = 4;
  o.batch_size = 3;  // chunks of 0 or 1 columns
  const TrainResult r = Train(train.x, train.y, val.x, val.y, o);
  CHECK(r.curve.size() == 2u);
  CHECK(std::isfinite(r.best_val_loss));
  o.batch_size = 1;
  CHECK(std::isfinite(Train(train.x, train.y, val.x, val.y, o).best_val_loss));
  // A constant feature gets scale 1 instead of a division by zero.
  train.x.row(1).setConstant(4.0f);
  const TrainResult c = Train(train.x, train.y, val.x, val.y, o);
  CHECK(c.mlp.input_scale()[1] == 1.0f);
  CHECK(c.mlp.input_mean()[1] == 4.0f);
}

TEST_CASE("TrainOptions::Check names a bad Fourier field", "[train]") {
  CHECK(CheckMessage([](TrainOptions& o) {
          o.fourier.frequencies = 40;
        }).find("fourier: FourierFeatures: frequencies = 40") != std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) { o.fourier.base = -1.0f; }).find("base") !=
        std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) { o.fourier = {}; }).empty());
}

TEST_CASE("TrainOptions::Check names the bad field", "[train]") {
  CHECK(CheckMessage([](TrainOptions&) {}).empty());
  CHECK(CheckMessage([](TrainOptions& o) {
          o.hidden = {32, 0};
        }).find("hidden[1]") != std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) { o.batch_size = 0; }).find("batch_size") !=
        std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) { o.learning_rate = -1; }).find("learning_rate") !=
        std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) { o.beta1 = 1.0; }).find("beta1") != std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) { o.beta2 = -0.1; }).find("beta2") != std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) { o.epsilon = 0; }).find("epsilon") != std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) {
          o.min_learning_rate = 1.0;
        }).find("min_learning_rate") != std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) { o.plateau_factor = 1.0; }).find("plateau_factor") !=
        std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) { o.plateau_epochs = 0; }).find("plateau_epochs") !=
        std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) {
          o.plateau_threshold = 1.5;
        }).find("plateau_threshold") != std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) { o.max_epochs = 0; }).find("max_epochs") !=
        std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) { o.patience = -1; }).find("patience") !=
        std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) {
          o.threads = 0;
        }).find("threads must be in [1, 256], got 0") != std::string::npos);
  CHECK(CheckMessage([](TrainOptions& o) { o.batch_size = -5; }).find("-5") != std::string::npos);

  const Data d = SmoothFunction(10, 1);
  TrainOptions bad;
  bad.threads = 0;
  CHECK_THROWS_AS(Train(d.x, d.y, d.x, d.y, bad), std::invalid_argument);
}

TEST_CASE("Train rejects empty and mismatched data", "[train]") {
  const Data d = SmoothFunction(10, 1);
  TrainOptions o = SmallOptions();
  const auto message = [&](const Eigen::MatrixXf& xt, const Eigen::MatrixXf& yt,
                           const Eigen::MatrixXf& xv, const Eigen::MatrixXf& yv) -> std::string {
    try {
      Train(xt, yt, xv, yv, o);
    } catch (const std::invalid_argument& e) {
      return e.what();
    }
    return "";
  };
  CHECK(message(Eigen::MatrixXf(2, 0), Eigen::MatrixXf(2, 0), d.x, d.y).find("x_train is empty") !=
        std::string::npos);
  CHECK(message(d.x, d.y, Eigen::MatrixXf(2, 0), Eigen::MatrixXf(2, 0)).find("x_val is empty") !=
        std::string::npos);
  CHECK(message(d.x, d.y.leftCols(9), d.x, d.y).find("10 samples but y_train has 9") !=
        std::string::npos);
  CHECK(message(d.x, d.y, d.x.topRows(1), d.y).find("validation rows") != std::string::npos);
  Eigen::MatrixXf nan_x = d.x;
  nan_x(1, 3) = std::numeric_limits<float>::quiet_NaN();
  CHECK(message(nan_x, d.y, d.x, d.y).find("non-finite") != std::string::npos);
  CHECK_THROWS_AS(EvaluateLoss(Mlp({3, 2}, Activation::kTanh, 1), d.x, d.y), std::invalid_argument);
}

TEST_CASE("Learning-rate schedule names", "[train]") {
  for (auto s : {LearningRateSchedule::kConstant, LearningRateSchedule::kPlateau,
                 LearningRateSchedule::kCosine}) {
    CHECK(ParseLearningRateSchedule(ToString(s)) == s);
  }
  CHECK_THROWS_AS(ParseLearningRateSchedule("step"), std::invalid_argument);
}

}  // namespace gs360
