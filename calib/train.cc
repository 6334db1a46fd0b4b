#include "calib/train.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <exception>
#include <limits>
#include <mutex>
#include <numbers>
#include <stdexcept>
#include <string>
#include <thread>

#include "base/byte_io.h"
#include "base/field_error.h"
#include "base/fields.h"

namespace gs360 {
namespace {

using Clock = std::chrono::steady_clock;

double SecondsSince(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// A fixed set of threads running one job at a time: Run(fn) calls fn(t) for every t in
// [0, threads), t = 0 on the caller's thread, and returns when all are done. The first exception
// thrown by any fn is rethrown by Run.
class Pool {
 public:
  explicit Pool(int threads) : threads_(threads) {
    for (int t = 1; t < threads_; ++t) workers_.emplace_back([this, t] { Worker(t); });
  }
  ~Pool() {
    {
      std::lock_guard lock(mutex_);
      stop_ = true;
    }
    start_.notify_all();
    for (std::thread& w : workers_) w.join();
  }
  Pool(const Pool&) = delete;
  Pool& operator=(const Pool&) = delete;

  int threads() const { return threads_; }

  void Run(const std::function<void(int)>& fn) {
    if (threads_ == 1) {
      fn(0);
      return;
    }
    {
      std::lock_guard lock(mutex_);
      job_ = &fn;
      pending_ = threads_ - 1;
      ++generation_;
    }
    start_.notify_all();
    std::exception_ptr mine;
    try {
      fn(0);
    } catch (...) {
      mine = std::current_exception();
    }
    std::unique_lock lock(mutex_);
    done_.wait(lock, [this] { return pending_ == 0; });
    job_ = nullptr;
    std::exception_ptr error = mine ? mine : error_;
    error_ = nullptr;
    lock.unlock();
    if (error) std::rethrow_exception(error);
  }

 private:
  void Worker(int t) {
    std::uint64_t seen = 0;
    for (;;) {
      const std::function<void(int)>* job;
      {
        std::unique_lock lock(mutex_);
        start_.wait(lock, [&] { return stop_ || generation_ != seen; });
        if (stop_) return;
        seen = generation_;
        job = job_;
      }
      std::exception_ptr error;
      try {
        (*job)(t);
      } catch (...) {
        error = std::current_exception();
      }
      {
        std::lock_guard lock(mutex_);
        if (error && !error_) error_ = error;
        if (--pending_ == 0) done_.notify_one();
      }
    }
  }

  int threads_;
  std::vector<std::thread> workers_;
  std::mutex mutex_;
  std::condition_variable start_, done_;
  const std::function<void(int)>* job_ = nullptr;
  std::uint64_t generation_ = 0;
  int pending_ = 0;
  bool stop_ = false;
  std::exception_ptr error_;
};

// xoshiro256** seeded by splitmix64: portable, so the shuffle is the same on every platform.
class Rng {
 public:
  explicit Rng(std::uint64_t seed) {
    std::uint64_t s = seed;
    for (auto& w : state_) {
      std::uint64_t z = (s += 0x9e3779b97f4a7c15ull);
      z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
      z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
      w = z ^ (z >> 31);
    }
  }
  std::uint64_t Next() {
    const std::uint64_t result = Rotl(state_[1] * 5, 7) * 9;
    const std::uint64_t t = state_[1] << 17;
    state_[2] ^= state_[0];
    state_[3] ^= state_[1];
    state_[1] ^= state_[2];
    state_[0] ^= state_[3];
    state_[2] ^= t;
    state_[3] = Rotl(state_[3], 45);
    return result;
  }
  // Unbiased integer in [0, bound) (Lemire's multiply-and-reject on 32-bit bounds).
  std::uint32_t Below(std::uint32_t bound) {
    std::uint64_t m = (Next() >> 32) * bound;
    auto low = static_cast<std::uint32_t>(m);
    if (low < bound) {
      const std::uint32_t threshold = static_cast<std::uint32_t>(-bound) % bound;
      while (low < threshold) {
        m = (Next() >> 32) * bound;
        low = static_cast<std::uint32_t>(m);
      }
    }
    return static_cast<std::uint32_t>(m >> 32);
  }

 private:
  static std::uint64_t Rotl(std::uint64_t x, int k) { return (x << k) | (x >> (64 - k)); }
  std::uint64_t state_[4];
};

void Shuffle(std::vector<std::uint32_t>& perm, Rng& rng) {
  for (std::size_t i = perm.size(); i > 1; --i) {
    const std::uint32_t j = rng.Below(static_cast<std::uint32_t>(i));
    std::swap(perm[i - 1], perm[j]);
  }
}

// Per-thread buffers for one chunk of a mini-batch.
// The checkpoint's layers and matrices; a stored shape must be the network's.
template <typename M>
void PutMatrix(ByteWriter& w, const M& m) {
  w.Put<std::uint32_t>(static_cast<std::uint32_t>(m.rows()));
  w.Put<std::uint32_t>(static_cast<std::uint32_t>(m.cols()));
  w.PutArray(m.data(), static_cast<std::size_t>(m.size()));
}

void PutLayers(ByteWriter& w, const std::vector<MlpLayer>& layers) {
  for (const MlpLayer& l : layers) {
    PutMatrix(w, l.weight);
    PutMatrix(w, l.bias);
  }
}

template <typename M>
void GetMatrix(ByteReader& r, M& m) {
  const auto rows = r.Get<std::uint32_t>("rows"), cols = r.Get<std::uint32_t>("columns");
  if (rows != m.rows() || cols != m.cols()) {
    throw std::invalid_argument("Train: the checkpoint holds a " + std::to_string(rows) + "x" +
                                std::to_string(cols) + " matrix where the network has " +
                                std::to_string(m.rows()) + "x" + std::to_string(m.cols()));
  }
  r.GetArray(m.data(), static_cast<std::size_t>(m.size()), "matrix");
}

void GetLayers(ByteReader& r, std::vector<MlpLayer>& layers) {
  for (MlpLayer& l : layers) {
    GetMatrix(r, l.weight);
    GetMatrix(r, l.bias);
  }
}

constexpr std::uint64_t kCheckpointMagic = 0x31304e5254303633ull;  // "360TRN01"

struct Workspace {
  Eigen::MatrixXf x;                  // [in, chunk] raw inputs
  Eigen::MatrixXf y;                  // [out, chunk] normalised targets
  std::vector<Eigen::MatrixXf> act;   // act[k]: [sizes[k], chunk]; act[L] = linear output
  std::vector<Eigen::MatrixXf> pre;   // silu only: sigmoid of the hidden pre-activations
  Eigen::MatrixXf delta, delta_prev;  // [widest, chunk]
  std::vector<Eigen::MatrixXf> grad_w;
  std::vector<Eigen::VectorXf> grad_b;
  double loss_sum = 0.0;  // sum of squared normalised errors of the chunk
};

// Forward and backward pass on the first m columns of ws.x / ws.y (raw features and targets):
// sets ws.loss_sum (sum of squared normalised errors of these columns) and ws.grad_w / grad_b
// to their share of the gradient of the mean loss of a batch of batch_total samples.
void ChunkGradient(const Mlp& mlp, Workspace& ws, Eigen::Index m, Eigen::Index batch_total) {
  const std::vector<int>& sizes = mlp.sizes();
  const int num_layers = static_cast<int>(sizes.size()) - 1;
  const Activation activation = mlp.activation();
  const Eigen::VectorXf& in_mean = mlp.input_mean();
  const Eigen::VectorXf in_inv_scale = mlp.input_scale().cwiseInverse();
  const Eigen::VectorXf& out_mean = mlp.output_mean();
  const Eigen::VectorXf out_inv_scale = mlp.output_scale().cwiseInverse();
  const Eigen::Index in = mlp.input_size();
  ws.act[0].topLeftCorner(in, m) =
      ((ws.x.leftCols(m).colwise() - in_mean).array().colwise() * in_inv_scale.array()).matrix();
  mlp.Encode(ws.act[0].leftCols(m));
  const auto target =
      ((ws.y.leftCols(m).colwise() - out_mean).array().colwise() * out_inv_scale.array());
  const auto& layers = mlp.layers();
  for (int k = 0; k < num_layers; ++k) {
    auto z = ws.act[k + 1].leftCols(m);
    z.noalias() = layers[k].weight * ws.act[k].leftCols(m);
    z.colwise() += layers[k].bias;
    if (k + 1 < num_layers) {
      switch (activation) {
        case Activation::kTanh:
          z = z.array().tanh().matrix();
          break;
        case Activation::kRelu:
          z = z.array().max(0.0f).matrix();
          break;
        case Activation::kSilu:
          // Keep s = sigmoid(z) = (1 + tanh(z / 2)) / 2 (as in Mlp::Forward) for the backward
          // pass: silu'(z) = s + z s (1 - s) = s + a (1 - s) with a = z s.
          ws.pre[k + 1].leftCols(m) = (0.5f + 0.5f * (0.5f * z.array()).tanh()).matrix();
          z = (z.array() * ws.pre[k + 1].leftCols(m).array()).matrix();
          break;
      }
    }
  }
  const int out = sizes.back();
  auto delta = ws.delta.topLeftCorner(out, m);
  delta = (ws.act[num_layers].leftCols(m).array() - target).matrix();
  ws.loss_sum = static_cast<double>(delta.squaredNorm());
  delta *= static_cast<float>(2.0 / (static_cast<double>(batch_total) * out));
  Eigen::MatrixXf* d = &ws.delta;
  Eigen::MatrixXf* d_prev = &ws.delta_prev;
  for (int k = num_layers - 1; k >= 0; --k) {
    const auto dk = d->topLeftCorner(sizes[k + 1], m);
    ws.grad_w[k].noalias() = dk * ws.act[k].leftCols(m).transpose();
    ws.grad_b[k] = dk.rowwise().sum();
    if (k == 0) break;
    auto dp = d_prev->topLeftCorner(sizes[k], m);
    dp.noalias() = layers[k].weight.transpose() * dk;
    const auto a = ws.act[k].leftCols(m).array();
    switch (activation) {
      case Activation::kTanh:
        dp.array() *= 1.0f - a.square();
        break;
      case Activation::kRelu:
        dp = (a > 0.0f).select(dp, 0.0f);
        break;
      case Activation::kSilu: {
        const auto s = ws.pre[k].leftCols(m).array();
        dp.array() *= s + a * (1.0f - s);
        break;
      }
    }
    std::swap(d, d_prev);
  }
}

// `sizes`: the layer widths as the network sees them (sizes[0] = Mlp::first_layer_input_size()),
// `inputs`: the raw feature count.
Workspace MakeWorkspace(const std::vector<int>& sizes, int inputs, Activation activation,
                        Eigen::Index chunk_max) {
  const int widest = *std::max_element(sizes.begin(), sizes.end());
  Workspace ws;
  ws.x.resize(inputs, chunk_max);
  ws.y.resize(sizes.back(), chunk_max);
  ws.act.resize(sizes.size());
  for (std::size_t k = 0; k < sizes.size(); ++k) ws.act[k].resize(sizes[k], chunk_max);
  if (activation == Activation::kSilu) {
    ws.pre.resize(sizes.size());
    for (std::size_t k = 1; k + 1 < sizes.size(); ++k) ws.pre[k].resize(sizes[k], chunk_max);
  }
  ws.delta.resize(widest, chunk_max);
  ws.delta_prev.resize(widest, chunk_max);
  for (std::size_t k = 0; k + 1 < sizes.size(); ++k) {
    ws.grad_w.push_back(Eigen::MatrixXf::Zero(sizes[k + 1], sizes[k]));
    ws.grad_b.push_back(Eigen::VectorXf::Zero(sizes[k + 1]));
  }
  return ws;
}

// The widths each layer sees: sizes() with the input replaced by the first layer's input.
std::vector<int> LayerSizes(const Mlp& mlp) {
  std::vector<int> sizes = mlp.sizes();
  sizes.front() = mlp.first_layer_input_size();
  return sizes;
}

void CheckData(const char* name_x, const Eigen::MatrixXf& x, const char* name_y,
               const Eigen::MatrixXf& y) {
  if (x.cols() == 0) throw std::invalid_argument(std::string("Train: ") + name_x + " is empty");
  if (x.cols() != y.cols()) {
    throw std::invalid_argument(std::string("Train: ") + name_x + " has " +
                                std::to_string(x.cols()) + " samples but " + name_y + " has " +
                                std::to_string(y.cols()));
  }
  if (x.cols() > static_cast<Eigen::Index>(std::numeric_limits<std::uint32_t>::max())) {
    throw std::invalid_argument(std::string("Train: ") + name_x + " has too many samples (" +
                                std::to_string(x.cols()) + ")");
  }
  if (!x.allFinite()) {
    throw std::invalid_argument(std::string("Train: ") + name_x + " has non-finite values");
  }
  if (!y.allFinite()) {
    throw std::invalid_argument(std::string("Train: ") + name_y + " has non-finite values");
  }
}

// Mean and standard deviation per row (double accumulation); a zero spread gets scale 1.
void RowStats(const Eigen::MatrixXf& m, Eigen::VectorXf& mean, Eigen::VectorXf& scale) {
  const Eigen::Index n = m.cols();
  Eigen::VectorXd sum = Eigen::VectorXd::Zero(m.rows());
  for (Eigen::Index c = 0; c < n; ++c) sum += m.col(c).cast<double>();
  const Eigen::VectorXd mu = sum / static_cast<double>(n);
  Eigen::VectorXd sq = Eigen::VectorXd::Zero(m.rows());
  for (Eigen::Index c = 0; c < n; ++c)
    sq += (m.col(c).cast<double>() - mu).array().square().matrix();
  mean = mu.cast<float>();
  scale.resize(m.rows());
  for (Eigen::Index r = 0; r < m.rows(); ++r) {
    const double sd = std::sqrt(sq[r] / static_cast<double>(n));
    scale[r] = (sd > 1e-12 && std::isfinite(sd)) ? static_cast<float>(sd) : 1.0f;
  }
}

// Sum of squared normalised errors over columns [begin, end) (blocked Forward).
double SquaredErrorSum(const Mlp& mlp, const Eigen::MatrixXf& x, const Eigen::MatrixXf& y,
                       Eigen::Index begin, Eigen::Index end) {
  constexpr Eigen::Index kBlock = 4096;
  const Eigen::ArrayXf inv_scale = mlp.output_scale().array().inverse();
  double sum = 0.0;
  for (Eigen::Index c0 = begin; c0 < end; c0 += kBlock) {
    const Eigen::Index m = std::min(kBlock, end - c0);
    const Eigen::MatrixXf pred = mlp.Forward(x.middleCols(c0, m));
    sum += static_cast<double>(
        ((pred - y.middleCols(c0, m)).array().colwise() * inv_scale).square().sum());
  }
  return sum;
}

double EvaluateLossWithPool(Pool& pool, const Mlp& mlp, const Eigen::MatrixXf& x,
                            const Eigen::MatrixXf& y) {
  const int threads = pool.threads();
  std::vector<double> sums(static_cast<std::size_t>(threads), 0.0);
  const Eigen::Index n = x.cols();
  pool.Run([&](int t) {
    const Eigen::Index begin = n * t / threads;
    const Eigen::Index end = n * (t + 1) / threads;
    sums[static_cast<std::size_t>(t)] = SquaredErrorSum(mlp, x, y, begin, end);
  });
  double total = 0.0;
  for (double s : sums) total += s;
  return total / (static_cast<double>(n) * static_cast<double>(y.rows()));
}

}  // namespace

std::string_view ToString(LearningRateSchedule s) {
  switch (s) {
    case LearningRateSchedule::kConstant:
      return "constant";
    case LearningRateSchedule::kPlateau:
      return "plateau";
    case LearningRateSchedule::kCosine:
      return "cosine";
  }
  return "unknown";
}

LearningRateSchedule ParseLearningRateSchedule(std::string_view s) {
  if (s == "constant") return LearningRateSchedule::kConstant;
  if (s == "plateau") return LearningRateSchedule::kPlateau;
  if (s == "cosine") return LearningRateSchedule::kCosine;
  throw std::invalid_argument("unknown learning-rate schedule '" + std::string(s) +
                              "' (expected constant, plateau or cosine)");
}

void TrainOptions::Check() const {
  for (std::size_t i = 0; i < hidden.size(); ++i) {
    if (hidden[i] < 1 || hidden[i] > 65536) {
      throw std::invalid_argument("TrainOptions.hidden[" + std::to_string(i) +
                                  "] = " + std::to_string(hidden[i]) + " must be in [1, 65536]");
    }
  }
  try {
    // The data's feature count is checked by Train; here only the option's own bounds.
    fourier.Check(std::numeric_limits<int>::max());
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(std::string("TrainOptions.fourier: ") + e.what());
  }
  if (batch_size < 1) ThrowFieldError("TrainOptions.batch_size", batch_size, "must be >= 1");
  if (!std::isfinite(learning_rate) || learning_rate <= 0.0) {
    ThrowFieldError("TrainOptions.learning_rate", learning_rate, "must be > 0");
  }
  if (!(beta1 >= 0.0 && beta1 < 1.0)) {
    ThrowFieldError("TrainOptions.beta1", beta1, "must be in [0, 1)");
  }
  if (!(beta2 >= 0.0 && beta2 < 1.0)) {
    ThrowFieldError("TrainOptions.beta2", beta2, "must be in [0, 1)");
  }
  if (!std::isfinite(epsilon) || epsilon <= 0.0) {
    ThrowFieldError("TrainOptions.epsilon", epsilon, "must be > 0");
  }
  if (!(min_learning_rate >= 0.0 && min_learning_rate <= learning_rate)) {
    ThrowFieldError("TrainOptions.min_learning_rate", min_learning_rate,
                    "must be in [0, learning_rate]");
  }
  if (!(plateau_factor > 0.0 && plateau_factor < 1.0)) {
    ThrowFieldError("TrainOptions.plateau_factor", plateau_factor, "must be in (0, 1)");
  }
  if (plateau_epochs < 1) {
    ThrowFieldError("TrainOptions.plateau_epochs", plateau_epochs, "must be >= 1");
  }
  if (!(plateau_threshold >= 0.0 && plateau_threshold < 1.0)) {
    ThrowFieldError("TrainOptions.plateau_threshold", plateau_threshold, "must be in [0, 1)");
  }
  if (max_epochs < 1) ThrowFieldError("TrainOptions.max_epochs", max_epochs, "must be >= 1");
  if (patience < 0) ThrowFieldError("TrainOptions.patience", patience, "must be >= 0");
  if (threads < 1 || threads > 256) {
    ThrowFieldError("TrainOptions.threads", threads, "must be in [1, 256]");
  }
  switch (schedule) {
    case LearningRateSchedule::kConstant:
    case LearningRateSchedule::kPlateau:
    case LearningRateSchedule::kCosine:
      break;
    default:
      throw std::invalid_argument(
          "TrainOptions.schedule = " + std::to_string(static_cast<int>(schedule)) + " is unknown");
  }
}

LossGradient ComputeLossGradient(const Mlp& mlp, const Eigen::MatrixXf& x,
                                 const Eigen::MatrixXf& y) {
  if (mlp.sizes().empty()) throw std::invalid_argument("ComputeLossGradient: empty network");
  if (x.rows() != mlp.input_size() || y.rows() != mlp.output_size() || x.cols() != y.cols() ||
      x.cols() == 0) {
    throw std::invalid_argument("ComputeLossGradient: data [" + std::to_string(x.rows()) + " x " +
                                std::to_string(x.cols()) + "], [" + std::to_string(y.rows()) +
                                " x " + std::to_string(y.cols()) + "] does not fit the network " +
                                std::to_string(mlp.input_size()) + " -> " +
                                std::to_string(mlp.output_size()));
  }
  Workspace ws = MakeWorkspace(LayerSizes(mlp), mlp.input_size(), mlp.activation(), x.cols());
  ws.x = x;
  ws.y = y;
  ChunkGradient(mlp, ws, x.cols(), x.cols());
  LossGradient result;
  result.loss = ws.loss_sum / (static_cast<double>(x.cols()) * static_cast<double>(y.rows()));
  for (std::size_t k = 0; k < ws.grad_w.size(); ++k) {
    result.gradient.push_back({std::move(ws.grad_w[k]), std::move(ws.grad_b[k])});
  }
  return result;
}

double EvaluateLoss(const Mlp& mlp, const Eigen::MatrixXf& x, const Eigen::MatrixXf& y,
                    int threads) {
  if (threads < 1 || threads > 256) {
    throw std::invalid_argument("EvaluateLoss: threads = " + std::to_string(threads));
  }
  if (x.rows() != mlp.input_size() || y.rows() != mlp.output_size() || x.cols() != y.cols()) {
    throw std::invalid_argument("EvaluateLoss: data [" + std::to_string(x.rows()) + " x " +
                                std::to_string(x.cols()) + "], [" + std::to_string(y.rows()) +
                                " x " + std::to_string(y.cols()) + "] does not fit the network " +
                                std::to_string(mlp.input_size()) + " -> " +
                                std::to_string(mlp.output_size()));
  }
  if (x.cols() == 0) throw std::invalid_argument("EvaluateLoss: empty data");
  Pool pool(threads);
  return EvaluateLossWithPool(pool, mlp, x, y);
}

namespace {

void CheckTrainData(const Eigen::MatrixXf& x_train, const Eigen::MatrixXf& y_train,
                    const Eigen::MatrixXf& x_val, const Eigen::MatrixXf& y_val) {
  CheckData("x_train", x_train, "y_train", y_train);
  CheckData("x_val", x_val, "y_val", y_val);
  if (x_train.rows() < 1 || y_train.rows() < 1) {
    throw std::invalid_argument("Train: x_train has " + std::to_string(x_train.rows()) +
                                " features and y_train " + std::to_string(y_train.rows()) +
                                " outputs; both must be >= 1");
  }
  if (x_val.rows() != x_train.rows() || y_val.rows() != y_train.rows()) {
    throw std::invalid_argument("Train: validation rows (" + std::to_string(x_val.rows()) + ", " +
                                std::to_string(y_val.rows()) + ") differ from training rows (" +
                                std::to_string(x_train.rows()) + ", " +
                                std::to_string(y_train.rows()) + ")");
  }
}

// The seeded initial network, with the training set's normalisation.
Mlp MakeNetwork(const Eigen::MatrixXf& x_train, const Eigen::MatrixXf& y_train,
                const TrainOptions& options) {
  std::vector<int> sizes;
  sizes.push_back(static_cast<int>(x_train.rows()));
  sizes.insert(sizes.end(), options.hidden.begin(), options.hidden.end());
  sizes.push_back(static_cast<int>(y_train.rows()));
  if (options.fourier.inputs > sizes.front()) {
    throw std::invalid_argument(
        "Train: TrainOptions.fourier.inputs = " + std::to_string(options.fourier.inputs) +
        " but the data has " + std::to_string(sizes.front()) + " features");
  }
  Mlp mlp(sizes, options.activation, options.seed, options.fourier);
  Eigen::VectorXf mean, scale;
  RowStats(x_train, mean, scale);
  mlp.SetInputNormalization(mean, scale);
  RowStats(y_train, mean, scale);
  mlp.SetOutputNormalization(mean, scale);
  return mlp;
}

// Mini-batch Adam over the shuffled training set: each batch is split into one chunk per pool
// thread, whose gradients are summed in thread order.
class Trainer {
 public:
  Trainer(Mlp& mlp, const Eigen::MatrixXf& x_train, const Eigen::MatrixXf& y_train,
          const TrainOptions& options)
      : mlp_(mlp),
        x_train_(x_train),
        y_train_(y_train),
        options_(options),
        threads_(options.threads),
        num_layers_(static_cast<int>(mlp.sizes().size()) - 1),
        n_(x_train.cols()),
        batch_(std::min<Eigen::Index>(options.batch_size, n_)),
        perm_(static_cast<std::size_t>(n_)),
        rng_(options.seed ^ 0xd1b54a32d192ed03ull),
        pool_(threads_) {
    const std::vector<int> sizes = LayerSizes(mlp);
    const Eigen::Index chunk_max = (batch_ + threads_ - 1) / threads_;
    for (int t = 0; t < threads_; ++t) {
      spaces_.push_back(MakeWorkspace(sizes, mlp.input_size(), options.activation, chunk_max));
    }
    for (int k = 0; k < num_layers_; ++k) {
      m_w_.push_back(Eigen::MatrixXf::Zero(sizes[k + 1], sizes[k]));
      v_w_.push_back(Eigen::MatrixXf::Zero(sizes[k + 1], sizes[k]));
      m_b_.push_back(Eigen::VectorXf::Zero(sizes[k + 1]));
      v_b_.push_back(Eigen::VectorXf::Zero(sizes[k + 1]));
    }
    for (std::size_t i = 0; i < perm_.size(); ++i) perm_[i] = static_cast<std::uint32_t>(i);
  }

  Pool& pool() { return pool_; }

  // Adam's state (the weights are the Mlp's).
  void Save(ByteWriter& w) const {
    w.Put(b1_power_);
    w.Put(b2_power_);
    for (int k = 0; k < num_layers_; ++k) {
      PutMatrix(w, m_w_[k]);
      PutMatrix(w, v_w_[k]);
      PutMatrix(w, m_b_[k]);
      PutMatrix(w, v_b_[k]);
    }
  }
  // Restores Save's state and the permutation after `epochs` epochs' shuffles.
  void Load(ByteReader& r, int epochs) {
    b1_power_ = r.Get<double>("state");
    b2_power_ = r.Get<double>("state");
    for (int k = 0; k < num_layers_; ++k) {
      GetMatrix(r, m_w_[k]);
      GetMatrix(r, v_w_[k]);
      GetMatrix(r, m_b_[k]);
      GetMatrix(r, v_b_[k]);
    }
    for (int e = 0; e < epochs; ++e) Shuffle(perm_, rng_);
  }

  // One pass over the reshuffled training set at learning rate `lr`; returns the mean loss.
  double Epoch(double lr) {
    Shuffle(perm_, rng_);
    double loss_sum = 0.0;
    for (batch_begin_ = 0; batch_begin_ < n_; batch_begin_ += batch_) {
      batch_size_ = std::min(batch_, n_ - batch_begin_);
      pool_.Run(chunk_fn_);
      AdamStep(lr);
      for (const Workspace& ws : spaces_) loss_sum += ws.loss_sum;
    }
    return loss_sum / (static_cast<double>(n_) * static_cast<double>(y_train_.rows()));
  }

 private:
  // Thread t's chunk of the current batch: its loss and gradient in spaces_[t].
  void ChunkJob(int t) {
    Workspace& ws = spaces_[static_cast<std::size_t>(t)];
    const Eigen::Index c_begin = batch_size_ * t / threads_;
    const Eigen::Index m = batch_size_ * (t + 1) / threads_ - c_begin;
    ws.loss_sum = 0.0;
    if (m == 0) {
      for (int k = 0; k < num_layers_; ++k) {
        ws.grad_w[k].setZero();
        ws.grad_b[k].setZero();
      }
      return;
    }
    const std::uint32_t* idx = perm_.data() + batch_begin_ + c_begin;
    for (Eigen::Index j = 0; j < m; ++j) {
      ws.x.col(j) = x_train_.col(idx[j]);
      ws.y.col(j) = y_train_.col(idx[j]);
    }
    ChunkGradient(mlp_, ws, m, batch_size_);
  }

  // The chunks' gradients summed, then one Adam update of every layer.
  void AdamStep(double lr) {
    b1_power_ *= options_.beta1;
    b2_power_ *= options_.beta2;
    const auto step = static_cast<float>(lr * std::sqrt(1.0 - b2_power_) / (1.0 - b1_power_));
    auto& layers = mlp_.layers();
    for (int k = 0; k < num_layers_; ++k) {
      gw_ = spaces_[0].grad_w[k];
      gb_ = spaces_[0].grad_b[k];
      for (int t = 1; t < threads_; ++t) {
        gw_ += spaces_[static_cast<std::size_t>(t)].grad_w[k];
        gb_ += spaces_[static_cast<std::size_t>(t)].grad_b[k];
      }
      m_w_[k] = b1_ * m_w_[k] + (1.0f - b1_) * gw_;
      v_w_[k] = b2_ * v_w_[k] + (1.0f - b2_) * gw_.cwiseAbs2();
      layers[k].weight.array() -= step * m_w_[k].array() / (v_w_[k].array().sqrt() + eps_);
      m_b_[k] = b1_ * m_b_[k] + (1.0f - b1_) * gb_;
      v_b_[k] = b2_ * v_b_[k] + (1.0f - b2_) * gb_.cwiseAbs2();
      layers[k].bias.array() -= step * m_b_[k].array() / (v_b_[k].array().sqrt() + eps_);
    }
  }

  Mlp& mlp_;
  const Eigen::MatrixXf& x_train_;
  const Eigen::MatrixXf& y_train_;
  const TrainOptions& options_;
  const int threads_;
  const int num_layers_;
  const Eigen::Index n_;
  const Eigen::Index batch_;
  std::vector<Workspace> spaces_;  // one per thread
  // Adam moments.
  std::vector<Eigen::MatrixXf> m_w_, v_w_;
  std::vector<Eigen::VectorXf> m_b_, v_b_;
  const float b1_ = static_cast<float>(options_.beta1);
  const float b2_ = static_cast<float>(options_.beta2);
  const float eps_ = static_cast<float>(options_.epsilon);
  double b1_power_ = 1.0, b2_power_ = 1.0;
  Eigen::MatrixXf gw_;
  Eigen::VectorXf gb_;
  std::vector<std::uint32_t> perm_;
  Rng rng_;
  Pool pool_;
  // The current batch, read by the workers.
  Eigen::Index batch_begin_ = 0;
  Eigen::Index batch_size_ = 0;
  const std::function<void(int)> chunk_fn_ = [this](int t) { ChunkJob(t); };
};

// Keeps the best epoch's weights and runs the plateau schedule and early stopping.
class EpochTracker {
 public:
  EpochTracker(const Mlp& mlp, const TrainOptions& options)
      : options_(options), best_layers_(mlp.layers()) {}

  const std::vector<MlpLayer>& best_layers() const { return best_layers_; }
  double best_val() const { return best_val_; }

  void Save(ByteWriter& w) const {
    PutLayers(w, best_layers_);
    w.Put(best_val_);
    w.Put(significant_best_);
    w.Put(significant_epoch_);
    w.Put(plateau_best_);
    w.Put(plateau_count_);
  }
  void Load(ByteReader& r) {
    GetLayers(r, best_layers_);
    best_val_ = r.Get<double>("state");
    significant_best_ = r.Get<double>("state");
    significant_epoch_ = r.Get<int>("state");
    plateau_best_ = r.Get<double>("state");
    plateau_count_ = r.Get<int>("state");
  }

  // After epoch `epoch`: updates the best weights, *result's best epoch and *lr; returns false
  // when the training stops (early stopping, or a non-finite loss after a finite epoch). Throws
  // std::runtime_error when the very first losses are non-finite.
  bool Continue(int epoch, double train_loss, double val_loss, const Mlp& mlp, double* lr,
                TrainResult* result) {
    if (!std::isfinite(train_loss) || !std::isfinite(val_loss)) {
      // Diverged: keep the best weights so far.
      if (result->best_epoch < 0) {
        throw std::runtime_error("Train: the loss became non-finite in epoch " +
                                 std::to_string(epoch) + " (learning_rate " + std::to_string(*lr) +
                                 " too high?)");
      }
      result->stopped_early = true;
      return false;
    }
    if (val_loss < best_val_) {
      best_val_ = val_loss;
      result->best_epoch = epoch;
      best_layers_ = mlp.layers();
    }
    if (val_loss < significant_best_ * (1.0 - options_.plateau_threshold)) {
      significant_best_ = val_loss;
      significant_epoch_ = epoch;
    }
    if (options_.schedule == LearningRateSchedule::kPlateau) {
      if (val_loss < plateau_best_ * (1.0 - options_.plateau_threshold)) {
        plateau_best_ = val_loss;
        plateau_count_ = 0;
      } else if (++plateau_count_ >= options_.plateau_epochs) {
        *lr = std::max(*lr * options_.plateau_factor, options_.min_learning_rate);
        plateau_count_ = 0;
      }
    }
    if (options_.patience > 0 && epoch - significant_epoch_ >= options_.patience &&
        epoch + 1 < options_.max_epochs) {
      result->stopped_early = true;
      return false;
    }
    return true;
  }

 private:
  const TrainOptions& options_;
  std::vector<MlpLayer> best_layers_;
  double best_val_ = std::numeric_limits<double>::infinity();
  double significant_best_ = std::numeric_limits<double>::infinity();
  int significant_epoch_ = -1;
  double plateau_best_ = std::numeric_limits<double>::infinity();
  int plateau_count_ = 0;
};

}  // namespace

namespace {

// What a checkpoint must match to be resumed: the options (all of them, threads included), the
// data's sizes and the network's layer sizes.
std::string CheckpointIdentity(const TrainOptions& options, const Eigen::MatrixXf& x_train,
                               const Eigen::MatrixXf& x_val, const Mlp& mlp) {
  nlohmann::json id = FieldsToJson(options);
  id["train_samples"] = x_train.cols();
  id["validation_samples"] = x_val.cols();
  id["sizes"] = mlp.sizes();
  return id.dump();
}

// The state after epoch `epoch` (the next one to run: epoch + 1, at rate `lr`).
std::vector<std::uint8_t> SaveCheckpoint(const std::string& identity, int epoch, double lr,
                                         const Mlp& mlp, const Trainer& trainer,
                                         const EpochTracker& tracker, const TrainResult& result) {
  ByteWriter w;
  w.Put(kCheckpointMagic);
  w.Put<std::int32_t>(epoch);
  w.Put<std::uint32_t>(static_cast<std::uint32_t>(identity.size()));
  w.PutArray(identity.data(), identity.size());
  w.Put(lr);
  PutLayers(w, mlp.layers());
  trainer.Save(w);
  tracker.Save(w);
  w.Put<std::int32_t>(result.best_epoch);
  w.Put<std::uint32_t>(static_cast<std::uint32_t>(result.curve.size()));
  for (const TrainEpoch& e : result.curve) {
    w.Put<std::int32_t>(e.epoch);
    w.Put(e.train_loss);
    w.Put(e.val_loss);
    w.Put(e.seconds);
    w.Put(e.learning_rate);
  }
  return std::move(w.bytes());
}

// Restores SaveCheckpoint's state; returns the first epoch still to run.
int ReadCheckpoint(std::span<const std::uint8_t> bytes, const std::string& identity, double* lr,
                   Mlp& mlp, Trainer& trainer, EpochTracker& tracker, TrainResult& result) {
  ByteReader r(bytes, "Train: the checkpoint");
  const int epoch = TrainCheckpointEpoch(bytes);
  r.Get<std::uint64_t>("state");
  r.Get<std::int32_t>("state");
  const auto id_size = r.Get<std::uint32_t>("state");
  if (id_size > r.remaining()) {  // corrupt: do not allocate what is not there
    throw std::invalid_argument("Train: the checkpoint is truncated or corrupt (identity of " +
                                std::to_string(id_size) + " bytes, " +
                                std::to_string(r.remaining()) + " left)");
  }
  std::string stored(id_size, '\0');
  r.Bytes(stored.data(), id_size, "identity");
  if (stored != identity) {
    // Name what differs: "threads 2 in the checkpoint, 1 here".
    const nlohmann::json was = nlohmann::json::parse(stored, nullptr, false);
    const nlohmann::json now = nlohmann::json::parse(identity);
    std::string diff;
    for (const auto& [key, value] : now.items()) {
      if (was.is_object() && was.contains(key) && was[key] == value) continue;
      if (!diff.empty()) diff += "; ";
      diff += key + " " + (was.is_object() && was.contains(key) ? was[key].dump() : "none") +
              " in the checkpoint, " + value.dump() + " here";
    }
    throw std::invalid_argument(
        "Train: the checkpoint is of another training (options, data or layer sizes differ: " +
        diff + ")");
  }
  *lr = r.Get<double>("state");
  GetLayers(r, mlp.layers());
  trainer.Load(r, epoch + 1);
  tracker.Load(r);
  result.best_epoch = r.Get<std::int32_t>("state");
  const auto epochs = r.Get<std::uint32_t>("state");
  if (epochs != static_cast<std::uint32_t>(epoch + 1)) {
    throw std::invalid_argument("Train: the checkpoint after epoch " + std::to_string(epoch) +
                                " holds " + std::to_string(epochs) + " epochs of curve");
  }
  for (std::uint32_t i = 0; i < epochs; ++i) {
    TrainEpoch e;
    e.epoch = r.Get<std::int32_t>("state");
    e.train_loss = r.Get<double>("state");
    e.val_loss = r.Get<double>("state");
    e.seconds = r.Get<double>("state");
    e.learning_rate = r.Get<double>("state");
    result.curve.push_back(e);
  }
  if (r.remaining() != 0)
    throw std::invalid_argument("Train: the checkpoint has bytes after its end");
  return epoch + 1;
}

// ReadCheckpoint with a truncated checkpoint reported as the corrupt input it is.
int LoadCheckpoint(std::span<const std::uint8_t> bytes, const std::string& identity, double* lr,
                   Mlp& mlp, Trainer& trainer, EpochTracker& tracker, TrainResult& result) {
  try {
    return ReadCheckpoint(bytes, identity, lr, mlp, trainer, tracker, result);
  } catch (const std::runtime_error& e) {
    throw std::invalid_argument(e.what());
  }
}

}  // namespace

int TrainCheckpointEpoch(std::span<const std::uint8_t> state) {
  ByteReader r(state, "Train: the checkpoint");
  if (state.size() < sizeof(kCheckpointMagic) + 4 ||
      r.Get<std::uint64_t>("magic") != kCheckpointMagic) {
    throw std::invalid_argument("Train: not a training checkpoint of this version (" +
                                std::to_string(state.size()) + " bytes)");
  }
  return r.Get<std::int32_t>("state");
}

TrainResult Train(const Eigen::MatrixXf& x_train, const Eigen::MatrixXf& y_train,
                  const Eigen::MatrixXf& x_val, const Eigen::MatrixXf& y_val,
                  const TrainOptions& options, const TrainProgress& progress,
                  const TrainCheckpointing& checkpointing) {
  options.Check();
  CheckTrainData(x_train, y_train, x_val, y_val);
  const auto start = Clock::now();
  TrainResult result;
  result.mlp = MakeNetwork(x_train, y_train, options);
  Mlp& mlp = result.mlp;
  Trainer trainer(mlp, x_train, y_train, options);
  EpochTracker tracker(mlp, options);
  double lr = options.learning_rate;
  const std::string identity = CheckpointIdentity(options, x_train, x_val, mlp);
  int first = 0;
  if (!checkpointing.resume_from.empty()) {
    first = LoadCheckpoint(checkpointing.resume_from, identity, &lr, mlp, trainer, tracker, result);
  }
  for (int epoch = first; epoch < options.max_epochs; ++epoch) {
    const auto epoch_start = Clock::now();
    if (options.schedule == LearningRateSchedule::kCosine) {
      lr = options.min_learning_rate +
           0.5 * (options.learning_rate - options.min_learning_rate) *
               (1.0 + std::cos(std::numbers::pi * epoch / options.max_epochs));
    }
    const double train_loss = trainer.Epoch(lr);
    const double val_loss = std::isfinite(train_loss)
                                ? EvaluateLossWithPool(trainer.pool(), mlp, x_val, y_val)
                                : std::numeric_limits<double>::quiet_NaN();
    result.curve.push_back({epoch, train_loss, val_loss, SecondsSince(epoch_start), lr});
    if (progress) progress(epoch, train_loss, val_loss);
    if (!tracker.Continue(epoch, train_loss, val_loss, mlp, &lr, &result)) break;
    if (checkpointing.save) {
      checkpointing.save(epoch, SaveCheckpoint(identity, epoch, lr, mlp, trainer, tracker, result));
    }
  }
  mlp.layers() = tracker.best_layers();
  result.best_val_loss = tracker.best_val();
  result.seconds = SecondsSince(start);
  return result;
}

}  // namespace gs360
