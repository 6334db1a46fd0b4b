#pragma once
// A small fully connected network (multi-layer perceptron) on Eigen, float precision: the
// calibration's model from a pixel's position and colour change to the surface slopes.
//
// Layout: sizes = {in, h1, ..., out}. Layer k maps a_k (size sizes[k]) to
// z = W_k a_k + b_k with W_k of shape [sizes[k+1], sizes[k]] ([out, in], as PyTorch and ONNX's
// Gemm with transB = 1 store it); hidden layers apply the activation, the last layer is linear.
// Inputs are normalised first: a_0 = (x - input_mean) ./ input_scale; outputs are scaled back:
// y = z_last .* output_scale + output_mean. The normalisation is part of the model (it is
// exported with it).
//
// Batches are column-major matrices with one sample per COLUMN ([features, samples]).
//
// Thread safety: const methods may be called concurrently.

#include <Eigen/Core>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

namespace gs360 {

enum class Activation { kTanh, kRelu, kSilu };
std::string_view ToString(Activation a);
// "tanh", "relu", "silu"; std::invalid_argument otherwise.
Activation ParseActivation(std::string_view s);

struct MlpLayer {
  Eigen::MatrixXf weight;  // [out, in]
  Eigen::VectorXf bias;    // [out]
};

class Mlp {
 public:
  Mlp() = default;
  // Random initialisation (Glorot-uniform for tanh, He-uniform for relu/silu; zero biases),
  // deterministic for a seed; identity normalisation. Throws std::invalid_argument for fewer than
  // two sizes or a size < 1.
  Mlp(std::vector<int> sizes, Activation activation, std::uint64_t seed);

  const std::vector<int>& sizes() const { return sizes_; }
  int input_size() const { return sizes_.empty() ? 0 : sizes_.front(); }
  int output_size() const { return sizes_.empty() ? 0 : sizes_.back(); }
  Activation activation() const { return activation_; }
  std::vector<MlpLayer>& layers() { return layers_; }
  const std::vector<MlpLayer>& layers() const { return layers_; }
  int ParameterCount() const;

  // Normalisation (sizes must match input_size / output_size; scales > 0, else
  // std::invalid_argument).
  void SetInputNormalization(const Eigen::VectorXf& mean, const Eigen::VectorXf& scale);
  void SetOutputNormalization(const Eigen::VectorXf& mean, const Eigen::VectorXf& scale);
  const Eigen::VectorXf& input_mean() const { return input_mean_; }
  const Eigen::VectorXf& input_scale() const { return input_scale_; }
  const Eigen::VectorXf& output_mean() const { return output_mean_; }
  const Eigen::VectorXf& output_scale() const { return output_scale_; }

  // x: [input_size, n] -> [output_size, n], normalisation included. std::invalid_argument for a
  // wrong row count.
  Eigen::MatrixXf Forward(const Eigen::MatrixXf& x) const;

  // Binary form (little-endian, versioned, checksummed). Deserialize throws std::runtime_error
  // naming what is wrong (bad magic, unsupported version, truncated, non-finite weight, checksum).
  std::vector<std::uint8_t> Serialize() const;
  static Mlp Deserialize(std::span<const std::uint8_t> bytes);

 private:
  std::vector<int> sizes_;
  Activation activation_ = Activation::kTanh;
  std::vector<MlpLayer> layers_;
  Eigen::VectorXf input_mean_, input_scale_, output_mean_, output_scale_;
};

}  // namespace gs360
