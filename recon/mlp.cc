#include "recon/mlp.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>

#include "base/byte_io.h"
#include "base/hash.h"

namespace gs360 {
namespace {

static_assert(std::endian::native == std::endian::little,
              "the MLP binary form is written with the host byte order: little-endian only");

constexpr char kMagic[8] = {'G', 'S', '3', '6', '0', 'M', 'L', 'P'};
// Version 2 added the Fourier features (after the sizes); version 1 blobs still load.
constexpr std::uint32_t kFormatVersion = 2;
constexpr int kMaxFourierFrequencies = 16;
// Sanity bounds used by Deserialize before allocating anything.
constexpr std::uint32_t kMaxSizesCount = 64;
constexpr std::int32_t kMaxLayerWidth = 1 << 16;
// Columns per block in Forward: keeps the intermediate activations in cache.
constexpr Eigen::Index kForwardBlock = 1024;

// splitmix64: a tiny, well-mixed, portable generator (no std distributions, so the
// initialisation is identical on every platform).
std::uint64_t SplitMix64(std::uint64_t& state) {
  std::uint64_t z = (state += 0x9e3779b97f4a7c15ull);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

// Uniform in [-1, 1).
float UniformSigned(std::uint64_t& state) {
  const double u = static_cast<double>(SplitMix64(state) >> 11) * 0x1.0p-53;  // [0, 1)
  return static_cast<float>(2.0 * u - 1.0);
}

// The Fourier rows of a_0 (recon/mlp.h): out row p = sin(w_j a_i), row P + p = cos(w_j a_i),
// p = i * frequencies + j. The phase is a float product, as the ONNX graph computes it (a Gemm
// whose only non-zero weight per phase is w_j), so both give the same bits before the sine. The
// phases go into one contiguous block first so that Eigen's vectorised sin / cos run over it.
void EncodeFeatures(const FourierFeatures& f, const Eigen::Ref<const Eigen::MatrixXf>& a,
                    Eigen::Ref<Eigen::MatrixXf> out) {
  const int count = f.inputs * f.frequencies;
  Eigen::MatrixXf phase(count, a.cols());
  for (int i = 0; i < f.inputs; ++i) {
    float w = f.base;
    for (int j = 0; j < f.frequencies; ++j, w *= 2.0f) {
      phase.row(i * f.frequencies + j) = w * a.row(i);
    }
  }
  out.topRows(count) = phase.array().sin().matrix();
  out.bottomRows(count) = phase.array().cos().matrix();
}

std::uint32_t ActivationCode(Activation a) {
  switch (a) {
    case Activation::kTanh:
      return 0;
    case Activation::kRelu:
      return 1;
    case Activation::kSilu:
      return 2;
  }
  throw std::invalid_argument("Mlp: unknown activation");
}

void CheckNormalization(const char* what, const Eigen::VectorXf& mean, const Eigen::VectorXf& scale,
                        int expected) {
  if (mean.size() != expected || scale.size() != expected) {
    throw std::invalid_argument(std::string("Mlp::Set") + what + "Normalization: sizes " +
                                std::to_string(mean.size()) + " / " + std::to_string(scale.size()) +
                                ", expected " + std::to_string(expected));
  }
  for (Eigen::Index i = 0; i < expected; ++i) {
    if (!std::isfinite(mean[i])) {
      throw std::invalid_argument(std::string("Mlp::Set") + what + "Normalization: mean[" +
                                  std::to_string(i) + "] = " + std::to_string(mean[i]) +
                                  " is not finite");
    }
    if (!std::isfinite(scale[i]) || !(scale[i] > 0.0f)) {
      throw std::invalid_argument(std::string("Mlp::Set") + what + "Normalization: scale[" +
                                  std::to_string(i) + "] = " + std::to_string(scale[i]) +
                                  " must be finite and > 0");
    }
  }
}

// In-place activation on a block (vectorised by Eigen).
template <typename Block>
void ApplyActivation(Activation activation, Block&& a) {
  switch (activation) {
    case Activation::kTanh:
      a = a.array().tanh();
      break;
    case Activation::kRelu:
      a = a.array().max(0.0f);
      break;
    case Activation::kSilu:
      // x * sigmoid(x) with sigmoid(x) = (1 + tanh(x / 2)) / 2: Eigen's float tanh is a
      // vectorised rational approximation, several times faster than its exp on SSE2.
      a = a.array() * (0.5f + 0.5f * (0.5f * a.array()).tanh());
      break;
  }
}

// Floats that must all be finite (weights, normalisation): a NaN in a model is corruption.
void GetFiniteFloats(ByteReader& r, float* out, std::size_t n, const std::string& what) {
  r.GetArray(out, n, what.c_str());
  for (std::size_t i = 0; i < n; ++i) {
    if (!std::isfinite(out[i])) {
      throw std::runtime_error("Mlp::Deserialize: non-finite value " + std::to_string(out[i]) +
                               " in " + what + " at index " + std::to_string(i));
    }
  }
}

void PutVector(ByteWriter& w, const Eigen::VectorXf& v) {
  w.PutArray(v.data(), static_cast<std::size_t>(v.size()));
}

// Scales read from a blob: each must be > 0 (a model divides by them).
void CheckPositiveScales(const Eigen::VectorXf& scale, const char* what) {
  for (Eigen::Index i = 0; i < scale.size(); ++i) {
    if (!(scale[i] > 0.0f)) {
      throw std::runtime_error("Mlp::Deserialize: " + std::string(what) + "[" + std::to_string(i) +
                               "] = " + std::to_string(scale[i]) + " is not > 0");
    }
  }
}

Activation ActivationFromCode(std::uint32_t code) {
  switch (code) {
    case 0:
      return Activation::kTanh;
    case 1:
      return Activation::kRelu;
    case 2:
      return Activation::kSilu;
    default:
      throw std::runtime_error("Mlp::Deserialize: unknown activation code " + std::to_string(code));
  }
}

// The blob is exactly `expected` bytes long and its last 8 are the checksum of the rest.
void CheckLengthAndChecksum(std::span<const std::uint8_t> bytes, std::size_t expected) {
  if (bytes.size() < expected) {
    throw std::runtime_error("Mlp::Deserialize: truncated data: " + std::to_string(bytes.size()) +
                             " bytes, the header announces " + std::to_string(expected));
  }
  if (bytes.size() > expected) {
    throw std::runtime_error("Mlp::Deserialize: " + std::to_string(bytes.size() - expected) +
                             " trailing bytes after the model");
  }
  std::uint64_t stored = 0;
  std::memcpy(&stored, bytes.data() + expected - sizeof(stored), sizeof(stored));
  const std::uint64_t actual = Hasher().Add(bytes.data(), expected - sizeof(stored)).Digest();
  if (stored != actual) {
    throw std::runtime_error("Mlp::Deserialize: checksum mismatch (stored " + ToHex64(stored) +
                             ", computed " + ToHex64(actual) + "): corrupt data");
  }
}

// The layer sizes after the header's count: each in [1, kMaxLayerWidth].
std::vector<int> ReadLayerSizes(ByteReader& r) {
  const auto count = r.Get<std::uint32_t>("layer count");
  if (count < 2 || count > kMaxSizesCount) {
    throw std::runtime_error("Mlp::Deserialize: bad size count " + std::to_string(count));
  }
  std::vector<int> sizes(count);
  for (std::uint32_t i = 0; i < count; ++i) {
    const auto s = r.Get<std::int32_t>("sizes");
    if (s < 1 || s > kMaxLayerWidth) {
      throw std::runtime_error("Mlp::Deserialize: bad size[" + std::to_string(i) +
                               "] = " + std::to_string(s));
    }
    sizes[i] = s;
  }
  return sizes;
}

}  // namespace

std::string_view ToString(Activation a) {
  switch (a) {
    case Activation::kTanh:
      return "tanh";
    case Activation::kRelu:
      return "relu";
    case Activation::kSilu:
      return "silu";
  }
  return "unknown";
}

Activation ParseActivation(std::string_view s) {
  if (s == "tanh") return Activation::kTanh;
  if (s == "relu") return Activation::kRelu;
  if (s == "silu") return Activation::kSilu;
  throw std::invalid_argument("unknown activation '" + std::string(s) +
                              "' (expected tanh, relu or silu)");
}

void FourierFeatures::Check(int input_size) const {
  if (inputs < 0 || inputs > input_size) {
    throw std::invalid_argument("FourierFeatures: inputs = " + std::to_string(inputs) +
                                " must be in [0, " + std::to_string(input_size) + "]");
  }
  if (frequencies < 0 || frequencies > kMaxFourierFrequencies) {
    throw std::invalid_argument("FourierFeatures: frequencies = " + std::to_string(frequencies) +
                                " must be in [0, " + std::to_string(kMaxFourierFrequencies) + "]");
  }
  if (!std::isfinite(base) || !(base > 0.0f)) {
    throw std::invalid_argument("FourierFeatures: base = " + std::to_string(base) +
                                " must be finite and > 0");
  }
}

Mlp::Mlp(std::vector<int> sizes, Activation activation, std::uint64_t seed, FourierFeatures fourier)
    : sizes_(std::move(sizes)), activation_(activation), fourier_(fourier) {
  if (sizes_.size() < 2) {
    throw std::invalid_argument("Mlp: need at least two sizes (input and output), got " +
                                std::to_string(sizes_.size()));
  }
  for (std::size_t i = 0; i < sizes_.size(); ++i) {
    if (sizes_[i] < 1 || sizes_[i] > kMaxLayerWidth) {
      throw std::invalid_argument("Mlp: sizes[" + std::to_string(i) +
                                  "] = " + std::to_string(sizes_[i]) + " must be in [1, " +
                                  std::to_string(kMaxLayerWidth) + "]");
    }
  }
  ActivationCode(activation);  // validates
  fourier_.Check(sizes_.front());
  std::uint64_t state = seed ^ 0x6a09e667f3bcc909ull;
  layers_.resize(sizes_.size() - 1);
  for (std::size_t k = 0; k + 1 < sizes_.size(); ++k) {
    const int in = k == 0 ? first_layer_input_size() : sizes_[k];
    const int out = sizes_[k + 1];
    const bool last = k + 2 == sizes_.size();
    // Glorot-uniform for tanh (and for the linear output layer), He-uniform before relu/silu.
    const double limit = (activation == Activation::kTanh || last)
                             ? std::sqrt(6.0 / static_cast<double>(in + out))
                             : std::sqrt(6.0 / static_cast<double>(in));
    MlpLayer& layer = layers_[k];
    layer.weight.resize(out, in);
    for (int r = 0; r < out; ++r) {
      for (int c = 0; c < in; ++c) {
        layer.weight(r, c) = static_cast<float>(limit) * UniformSigned(state);
      }
    }
    layer.bias = Eigen::VectorXf::Zero(out);
  }
  input_mean_ = Eigen::VectorXf::Zero(sizes_.front());
  input_scale_ = Eigen::VectorXf::Ones(sizes_.front());
  output_mean_ = Eigen::VectorXf::Zero(sizes_.back());
  output_scale_ = Eigen::VectorXf::Ones(sizes_.back());
}

int Mlp::ParameterCount() const {
  int count = 0;
  for (const MlpLayer& layer : layers_) {
    count += static_cast<int>(layer.weight.size() + layer.bias.size());
  }
  return count;
}

void Mlp::SetInputNormalization(const Eigen::VectorXf& mean, const Eigen::VectorXf& scale) {
  CheckNormalization("Input", mean, scale, input_size());
  input_mean_ = mean;
  input_scale_ = scale;
}

void Mlp::SetOutputNormalization(const Eigen::VectorXf& mean, const Eigen::VectorXf& scale) {
  CheckNormalization("Output", mean, scale, output_size());
  output_mean_ = mean;
  output_scale_ = scale;
}

Eigen::MatrixXf Mlp::Forward(const Eigen::MatrixXf& x) const {
  if (sizes_.empty()) throw std::invalid_argument("Mlp::Forward: empty network");
  if (x.rows() != input_size()) {
    throw std::invalid_argument("Mlp::Forward: input has " + std::to_string(x.rows()) +
                                " rows, the network expects " + std::to_string(input_size()));
  }
  const Eigen::Index n = x.cols();
  Eigen::MatrixXf y(output_size(), n);
  if (n == 0) return y;
  const int max_width =
      std::max(first_layer_input_size(), *std::max_element(sizes_.begin(), sizes_.end()));
  const Eigen::Index block = std::min(n, kForwardBlock);
  // Two ping-pong buffers, one column block at a time.
  Eigen::MatrixXf buf_a(max_width, block), buf_b(max_width, block);
  const Eigen::ArrayXf inv_in_scale = input_scale_.array().inverse();
  for (Eigen::Index c0 = 0; c0 < n; c0 += block) {
    const Eigen::Index m = std::min(block, n - c0);
    auto a0 = buf_a.topLeftCorner(input_size(), m);
    a0 = ((x.middleCols(c0, m).colwise() - input_mean_).array().colwise() * inv_in_scale).matrix();
    Encode(buf_a.topLeftCorner(first_layer_input_size(), m));
    Eigen::MatrixXf* cur = &buf_a;
    Eigen::MatrixXf* next = &buf_b;
    for (std::size_t k = 0; k < layers_.size(); ++k) {
      const MlpLayer& layer = layers_[k];
      const auto in_rows = layer.weight.cols();
      const auto out_rows = layer.weight.rows();
      auto z = next->topLeftCorner(out_rows, m);
      z.noalias() = layer.weight * cur->topLeftCorner(in_rows, m);
      z.colwise() += layer.bias;
      if (k + 1 < layers_.size()) ApplyActivation(activation_, z);
      std::swap(cur, next);
    }
    y.middleCols(c0, m) =
        ((cur->topLeftCorner(output_size(), m).array().colwise() * output_scale_.array())
             .colwise() +
         output_mean_.array())
            .matrix();
  }
  return y;
}

void Mlp::Encode(Eigen::Ref<Eigen::MatrixXf> a0) const {
  if (a0.rows() != first_layer_input_size()) {
    throw std::invalid_argument("Mlp::Encode: a_0 has " + std::to_string(a0.rows()) +
                                " rows, the first layer takes " +
                                std::to_string(first_layer_input_size()));
  }
  if (fourier_.Enabled()) {
    EncodeFeatures(fourier_, a0.topRows(input_size()), a0.bottomRows(fourier_.Width()));
  }
}

std::vector<std::uint8_t> Mlp::Serialize() const {
  if (sizes_.empty()) throw std::invalid_argument("Mlp::Serialize: empty network");
  ByteWriter w;
  for (char c : kMagic) w.Put(c);
  w.Put(kFormatVersion);
  w.Put(ActivationCode(activation_));
  w.Put(static_cast<std::uint32_t>(sizes_.size()));
  for (int s : sizes_) w.Put(static_cast<std::int32_t>(s));
  w.Put(static_cast<std::int32_t>(fourier_.inputs));
  w.Put(static_cast<std::int32_t>(fourier_.frequencies));
  w.Put(fourier_.base);
  PutVector(w, input_mean_);
  PutVector(w, input_scale_);
  PutVector(w, output_mean_);
  PutVector(w, output_scale_);
  for (const MlpLayer& layer : layers_) {
    // Row-major [out, in], as ONNX / PyTorch store Gemm weights.
    const Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> rm = layer.weight;
    w.PutArray(rm.data(), static_cast<std::size_t>(rm.size()));
    PutVector(w, layer.bias);
  }
  const std::uint64_t checksum = Hasher().Add(w.bytes().data(), w.bytes().size()).Digest();
  w.Put(checksum);
  return std::move(w.bytes());
}

Mlp Mlp::Deserialize(std::span<const std::uint8_t> bytes) {
  ByteReader r(bytes, "Mlp::Deserialize");
  if (bytes.size() < sizeof(kMagic) || std::memcmp(bytes.data(), kMagic, sizeof(kMagic)) != 0) {
    throw std::runtime_error("Mlp::Deserialize: bad magic (not a GS360MLP blob)");
  }
  for (std::size_t i = 0; i < sizeof(kMagic); ++i) r.Get<char>("magic");
  const auto version = r.Get<std::uint32_t>("version");
  if (version != 1 && version != kFormatVersion) {
    throw std::runtime_error("Mlp::Deserialize: unsupported version " + std::to_string(version) +
                             " (supported: 1, " + std::to_string(kFormatVersion) + ")");
  }
  const auto activation_code = r.Get<std::uint32_t>("activation");
  const std::vector<int> sizes = ReadLayerSizes(r);
  const auto count = static_cast<std::uint32_t>(sizes.size());
  std::size_t floats = 0;
  FourierFeatures fourier;
  if (version >= 2) {
    fourier.inputs = r.Get<std::int32_t>("fourier inputs");
    fourier.frequencies = r.Get<std::int32_t>("fourier frequencies");
    fourier.base = r.Get<float>("fourier base");
    try {
      fourier.Check(sizes.front());
    } catch (const std::invalid_argument& e) {
      throw std::runtime_error(std::string("Mlp::Deserialize: ") + e.what());
    }
  }
  const int first_in = sizes.front() + fourier.Width();
  floats +=
      2 * static_cast<std::size_t>(sizes.front()) + 2 * static_cast<std::size_t>(sizes.back());
  for (std::uint32_t i = 0; i + 1 < count; ++i) {
    const int layer_in = i == 0 ? first_in : sizes[i];
    floats += static_cast<std::size_t>(sizes[i + 1]) * (static_cast<std::size_t>(layer_in) + 1);
  }
  const std::size_t expected = r.pos() + floats * sizeof(float) + sizeof(std::uint64_t);
  CheckLengthAndChecksum(bytes, expected);
  const Activation activation = ActivationFromCode(activation_code);
  Mlp mlp;
  mlp.sizes_ = sizes;
  mlp.activation_ = activation;
  mlp.fourier_ = fourier;
  const int in = sizes.front();
  const int out = sizes.back();
  mlp.input_mean_.resize(in);
  mlp.input_scale_.resize(in);
  mlp.output_mean_.resize(out);
  mlp.output_scale_.resize(out);
  GetFiniteFloats(r, mlp.input_mean_.data(), in, "input mean");
  GetFiniteFloats(r, mlp.input_scale_.data(), in, "input scale");
  GetFiniteFloats(r, mlp.output_mean_.data(), out, "output mean");
  GetFiniteFloats(r, mlp.output_scale_.data(), out, "output scale");
  CheckPositiveScales(mlp.input_scale_, "input scale");
  CheckPositiveScales(mlp.output_scale_, "output scale");
  mlp.layers_.resize(count - 1);
  for (std::uint32_t k = 0; k + 1 < count; ++k) {
    const std::string name = "layer " + std::to_string(k);
    Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> rm(
        sizes[k + 1], k == 0 ? first_in : sizes[k]);
    GetFiniteFloats(r, rm.data(), static_cast<std::size_t>(rm.size()), name + " weight");
    mlp.layers_[k].weight = rm;
    mlp.layers_[k].bias.resize(sizes[k + 1]);
    GetFiniteFloats(r, mlp.layers_[k].bias.data(), static_cast<std::size_t>(sizes[k + 1]),
                    name + " bias");
  }
  return mlp;
}

}  // namespace gs360
