// The MLP at its edges: float against a double-precision evaluation of the same weights, inputs
// far outside the training range, and training that diverges or is given NaN.

#include <cmath>
#include <limits>
#include <random>
#include <stdexcept>
#include <string>

#include "calib/train.h"
#include "recon/features.h"
#include "recon/mlp.h"
#include "recon/model_bundle.h"
#include "stress/stress_cases.h"

namespace gs360::stress {
namespace {

// The network of recon/mlp.h evaluated in double from its float weights: normalisation, Fourier
// features (the phase as the float product the model defines, then sin/cos in double), layers.
Eigen::MatrixXd ForwardDouble(const Mlp& mlp, const Eigen::MatrixXf& x) {
  const Eigen::MatrixXf a_float =
      ((x.colwise() - mlp.input_mean()).array().colwise() / mlp.input_scale().array()).matrix();
  const FourierFeatures& f = mlp.fourier();
  const int count = f.inputs * f.frequencies;
  Eigen::MatrixXd a(mlp.first_layer_input_size(), x.cols());
  a.topRows(mlp.input_size()) = a_float.cast<double>();
  for (int i = 0; i < f.inputs; ++i) {
    float w = f.base;
    for (int j = 0; j < f.frequencies; ++j, w *= 2.0f) {
      const Eigen::ArrayXd phase = (w * a_float.row(i)).cast<double>().transpose().array();
      a.row(mlp.input_size() + i * f.frequencies + j) = phase.sin().transpose();
      a.row(mlp.input_size() + count + i * f.frequencies + j) = phase.cos().transpose();
    }
  }
  for (std::size_t k = 0; k < mlp.layers().size(); ++k) {
    const MlpLayer& layer = mlp.layers()[k];
    Eigen::MatrixXd z = layer.weight.cast<double>() * a;
    z.colwise() += layer.bias.cast<double>();
    if (k + 1 < mlp.layers().size()) {
      switch (mlp.activation()) {
        case Activation::kTanh:
          z = z.array().tanh();
          break;
        case Activation::kRelu:
          z = z.array().max(0.0);
          break;
        case Activation::kSilu:
          z = z.array() / (1.0 + (-z.array()).exp());
          break;
      }
    }
    a = std::move(z);
  }
  return ((a.array().colwise() * mlp.output_scale().cast<double>().array()).colwise() +
          mlp.output_mean().cast<double>().array())
      .matrix();
}

// Inputs drawn around the network's normalisation: mean + scale * N(0, spread).
Eigen::MatrixXf Inputs(const Mlp& mlp, int n, double spread, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> normal(0.0f, static_cast<float>(spread));
  Eigen::MatrixXf x(mlp.input_size(), n);
  for (int c = 0; c < n; ++c) {
    for (int r = 0; r < mlp.input_size(); ++r) {
      x(r, c) = mlp.input_mean()[r] + mlp.input_scale()[r] * normal(rng);
    }
  }
  return x;
}

// Largest |float - double| over the outputs, in units of each output's scale.
double RelativeGap(const Mlp& mlp, const Eigen::MatrixXf& x) {
  const Eigen::MatrixXd exact = ForwardDouble(mlp, x);
  const Eigen::MatrixXd gap = (mlp.Forward(x).cast<double>() - exact).cwiseAbs();
  return (gap.array().colwise() / mlp.output_scale().cast<double>().array()).maxCoeff();
}

Mlp DefaultSizedNetwork(std::uint64_t seed) {
  const TrainOptions t;
  std::vector<int> sizes = {kFeatureCount};
  sizes.insert(sizes.end(), t.hidden.begin(), t.hidden.end());
  sizes.push_back(2);
  return Mlp(sizes, t.activation, seed, t.fourier);
}

StressCase FloatAgainstDouble(bool trained) {
  const std::string name = trained ? "float against double: the calibrated model, 100,000 inputs"
                                   : "float against double: the default 128 x 128 x 128 network "
                                     "(random weights), 100,000 inputs";
  return {"mlp", name, "outputs agree within 1e-4 of each output's scale",
          [trained](const StressContext& c, std::string* observed) {
            if (trained && !c.model) throw std::invalid_argument("no model given");
            const Mlp mlp = trained ? c.model->mlp : DefaultSizedNetwork(c.seed);
            const double gap = RelativeGap(mlp, Inputs(mlp, 100000, 1.0, c.seed));
            *observed = Format("largest gap %.2g of the output scale", gap);
            return gap <= 1e-4;
          }};
}

StressCase FarInputs() {
  return {"mlp", "inputs 1e6 normalisation units away (saturated colours, pixels off the image)",
          "finite outputs, float within 1e-3 of double",
          [](const StressContext& c, std::string* observed) {
            const Mlp mlp = DefaultSizedNetwork(c.seed);
            const Eigen::MatrixXf x = Inputs(mlp, 1000, 1e6, c.seed);
            const Eigen::MatrixXf y = mlp.Forward(x);
            const double gap = RelativeGap(mlp, x);
            *observed = Format("%s outputs; largest gap %.2g of the output scale",
                               y.allFinite() ? "finite" : "NON-FINITE", gap);
            return y.allFinite() && gap <= 1e-3;
          }};
}

// A small regression problem (slopes of a smooth field) for the training cases.
void Problem(std::uint64_t seed, Eigen::MatrixXf* x, Eigen::MatrixXf* y) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  *x = Eigen::MatrixXf(kFeatureCount, 2000);
  *y = Eigen::MatrixXf(2, 2000);
  for (int c = 0; c < 2000; ++c) {
    for (int r = 0; r < kFeatureCount; ++r) (*x)(r, c) = u(rng);
    (*y)(0, c) = std::sin(3.0f * (*x)(0, c)) + (*x)(2, c);
    (*y)(1, c) = std::cos(2.0f * (*x)(1, c)) - (*x)(3, c);
  }
}

StressCase Diverging() {
  return {"mlp", "training at a learning rate of 1e4 (diverges)",
          "an error, or a model whose every weight is finite",
          [](const StressContext& c, std::string* observed) {
            Eigen::MatrixXf x, y;
            Problem(c.seed, &x, &y);
            TrainOptions o;
            o.hidden = {32, 32};
            o.learning_rate = 1e4;
            o.max_epochs = 5;
            o.threads = 1;
            try {
              const TrainResult r = Train(x, y, x, y, o);
              bool finite = true;
              for (const MlpLayer& l : r.mlp.layers()) {
                finite = finite && l.weight.allFinite() && l.bias.allFinite();
              }
              *observed =
                  Format("trained %zu epochs, best %d (val loss %.3g); weights %s", r.curve.size(),
                         r.best_epoch, r.best_val_loss, finite ? "finite" : "NOT FINITE");
              return finite && std::isfinite(r.best_val_loss);
            } catch (const std::runtime_error& e) {
              *observed = std::string("std::runtime_error: ") + e.what();
              return true;
            }
          }};
}

StressCase NaNTarget() {
  return {"mlp", "training data with one NaN target", "std::invalid_argument naming the value",
          [](const StressContext& c, std::string* observed) {
            Eigen::MatrixXf x, y;
            Problem(c.seed, &x, &y);
            y(1, 1234) = std::numeric_limits<float>::quiet_NaN();
            TrainOptions o;
            o.hidden = {8};
            o.max_epochs = 1;
            o.threads = 1;
            try {
              Train(x, y, x, y, o);
              *observed = "trained";
              return false;
            } catch (const std::invalid_argument& e) {
              *observed = e.what();
              return true;
            }
          }};
}

}  // namespace

std::vector<StressCase> MlpCases() {
  return {FloatAgainstDouble(true), FloatAgainstDouble(false), FarInputs(), Diverging(),
          NaNTarget()};
}

}  // namespace gs360::stress
