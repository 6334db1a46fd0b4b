#pragma once
// Calibration stage "train": fits the MLP (recon/mlp.h) that maps a pixel's features (u, v,
// normalised colour change R, G, B) to its tangent-frame slopes (gx, gy).
//
// Method: Adam on mini-batches of shuffled training samples, a learning-rate schedule, early
// stopping on the validation loss (the best epoch's weights are returned).
//
// Normalisation: the input and output mean / standard deviation are computed from the TRAINING
// set and set on the returned Mlp (a feature with zero spread gets scale 1).
//
// Loss: mean squared error on NORMALISED outputs, averaged over samples and outputs:
//   L = 1 / (n * out) * sum_i sum_j (z_ij - (y_ij - output_mean_j) / output_scale_j)^2
// where z is the network's last (linear) layer. The train loss of an epoch is this loss over all
// training samples as seen during the pass (each with the weights of its mini-batch, i.e. the
// sample-weighted mean of the mini-batch losses); the validation loss is evaluated with the
// epoch's final weights. Both are dimensionless (units of output variance): 1 is what
// predicting the training mean scores.
//
// Reproducibility: the result depends only on the data, the options and the thread count. The
// same seed and thread count give bit-identical weights: the data is shuffled with a seeded
// portable generator, each mini-batch is split into fixed per-thread chunks and the chunk
// gradients are summed in thread order. A different thread count changes the rounding (not the
// maths).
//
// Threads: a pool of `threads` threads (the caller's thread included) lives for the whole call.
// Memory: O(batch_size * widest layer) per thread; the data is not copied.

#include <Eigen/Core>
#include <cstdint>
#include <functional>
#include <span>
#include <vector>

#include "recon/mlp.h"

namespace gs360 {

enum class LearningRateSchedule {
  kConstant,
  // Multiply the rate by plateau_factor when the validation loss has not improved (relatively,
  // by more than plateau_threshold) for plateau_epochs epochs; never below min_learning_rate.
  kPlateau,
  // Cosine annealing from learning_rate to min_learning_rate over max_epochs.
  kCosine,
};
std::string_view ToString(LearningRateSchedule s);
// "constant", "plateau", "cosine"; std::invalid_argument otherwise.
LearningRateSchedule ParseLearningRateSchedule(std::string_view s);

struct TrainOptions {
  // Hidden layer widths (may be empty: linear model). 128 wide: with the context features
  // (recon/features.h) each step from 64 to 96 to 128 wide lowered the depth error, for more
  // training time (chosen by measurement; figures in docs/benchmarks.md, "Calibration").
  std::vector<int> hidden = {128, 128, 128};
  // tanh: on the validation loss tanh and silu tie and relu is worse; tanh is the faster in
  // inference. The plateau schedule did no worse than cosine. (Chosen by measurement with
  // bench/bench_train --compare; figures in docs/benchmarks.md, "Calibration".)
  Activation activation = Activation::kTanh;
  // Fourier features of the first two inputs, the pixel position (recon/mlp.h). Chosen by
  // measurement: 3 or 4 frequencies lower the validation loss, 6 start to fit noise, and wider
  // layers without them only match it at a higher inference cost (figures in
  // docs/benchmarks.md, "Calibration"). {0, 0, 1} turns them off.
  FourierFeatures fourier = {2, 4, 1.0f};
  int batch_size = 1024;
  // Adam.
  double learning_rate = 3e-3;
  double beta1 = 0.9;
  double beta2 = 0.999;
  double epsilon = 1e-8;
  LearningRateSchedule schedule = LearningRateSchedule::kPlateau;
  double min_learning_rate = 1e-5;
  double plateau_factor = 0.5;      // in (0, 1)
  int plateau_epochs = 3;           // >= 1
  double plateau_threshold = 1e-3;  // relative improvement that counts, >= 0
  // Sized so that training fits the whole calibration's time budget of 10 min (training times:
  // bench/bench_train and the calibration runs, docs/benchmarks.md, "Calibration").
  int max_epochs = 60;
  // Early stopping: stop after `patience` epochs in which the validation loss did not improve
  // by more than plateau_threshold (relative) on its best; 0 disables early stopping. Whatever
  // stops the training, the weights of the epoch with the lowest validation loss are returned.
  int patience = 12;
  std::uint64_t seed = 1;
  int threads = 2;  // 1..256

  // Throws std::invalid_argument naming the field and its value.
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("hidden", self.hidden);
    visit("activation", self.activation);
    visit("fourier", self.fourier);
    visit("batch_size", self.batch_size);
    visit("learning_rate", self.learning_rate);
    visit("beta1", self.beta1);
    visit("beta2", self.beta2);
    visit("epsilon", self.epsilon);
    visit("schedule", self.schedule);
    visit("min_learning_rate", self.min_learning_rate);
    visit("plateau_factor", self.plateau_factor);
    visit("plateau_epochs", self.plateau_epochs);
    visit("plateau_threshold", self.plateau_threshold);
    visit("max_epochs", self.max_epochs);
    visit("patience", self.patience);
    visit("seed", self.seed);
    visit("threads", self.threads);
  }
  void Check() const;
};

struct TrainEpoch {
  int epoch = 0;  // 0-based
  double train_loss = 0.0;
  double val_loss = 0.0;
  double seconds = 0.0;        // wall time of this epoch (training + validation)
  double learning_rate = 0.0;  // rate used during this epoch
};

struct TrainResult {
  Mlp mlp;  // the best epoch's weights, with the training set's normalisation
  std::vector<TrainEpoch> curve;
  int best_epoch = -1;
  double best_val_loss = 0.0;
  // True when early stopping ended the training before max_epochs, or when the loss became
  // non-finite (diverged) after a finite epoch.
  bool stopped_early = false;
  double seconds = 0.0;  // total wall time
};

// Called after every epoch on the calling thread.
using TrainProgress = std::function<void(int epoch, double train_loss, double val_loss)>;

// Resuming a training that was killed. After every epoch `save` gets the whole state of the
// training (weights, Adam's moments, the schedule, the best epoch, the curve so far; a few times
// the model's size); Train called again with those bytes in `resume_from` and the same data,
// options and thread count carries on after that epoch and returns bit-identically what an
// uninterrupted run returns (the shuffles of the finished epochs are replayed from the seed).
struct TrainCheckpointing {
  std::function<void(int epoch, const std::vector<std::uint8_t>& state)> save;
  std::vector<std::uint8_t> resume_from;  // empty: from the first epoch
};

// The epoch after which a checkpoint's state was saved; std::invalid_argument for bytes that
// are not a checkpoint of this format version (truncated, foreign).
int TrainCheckpointEpoch(std::span<const std::uint8_t> state);

// x_*: [in, n] features, y_*: [out, n] targets, one sample per column. Throws
// std::invalid_argument for bad options, empty sets, mismatched row/column counts or non-finite
// values in the data, and for a checkpoint that is corrupt or of other data, layer sizes, seed or
// thread count (the message says which); std::runtime_error when the loss is non-finite in the
// first epoch.
TrainResult Train(const Eigen::MatrixXf& x_train, const Eigen::MatrixXf& y_train,
                  const Eigen::MatrixXf& x_val, const Eigen::MatrixXf& y_val,
                  const TrainOptions& options, const TrainProgress& progress = {},
                  const TrainCheckpointing& checkpointing = {});

// Mean squared error of `mlp` on (x, y) in the units of the loss above (normalised by the Mlp's
// output scale). Multi-threaded over `threads`; deterministic for a thread count.
// The loss above on the batch (x, y) (the Mlp's own normalisation) and its gradient with respect
// to every layer's weight and bias (gradient[k] has layer k's shapes), as Train computes them.
// For diagnostics and gradient checks; std::invalid_argument for data that does not fit.
struct LossGradient {
  double loss = 0.0;
  std::vector<MlpLayer> gradient;
};
LossGradient ComputeLossGradient(const Mlp& mlp, const Eigen::MatrixXf& x,
                                 const Eigen::MatrixXf& y);

double EvaluateLoss(const Mlp& mlp, const Eigen::MatrixXf& x, const Eigen::MatrixXf& y,
                    int threads = 1);

}  // namespace gs360
