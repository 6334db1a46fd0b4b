#pragma once
// A small fully connected network (multi-layer perceptron) on Eigen, float precision: the
// calibration's model from a pixel's position and colour change to the surface slopes.
//
// Layout: sizes = {in, h1, ..., out}. Layer k maps a_k (size sizes[k]) to
// z = W_k a_k + b_k with W_k of shape [sizes[k+1], sizes[k]] ([out, in], as PyTorch and ONNX's
// Gemm with transB = 1 store it); hidden layers apply the activation, the last layer is linear.
// Inputs are normalised first: a = (x - input_mean) ./ input_scale; outputs are scaled back:
// y = z_last .* output_scale + output_mean. The normalisation is part of the model (it is
// exported with it).
//
// Fourier features (optional, FourierFeatures): the first layer sees a_0 = [a; sin(phi); cos(phi)]
// with phi_p = w_j a_i for p = i * frequencies + j (i < inputs, j < frequencies), w_j = base 2^j
// (rad per normalised unit). They let a small network follow how the illumination changes across
// the image (fin shadows, LED fall-off), which it cannot fit from raw (u, v) without many more
// units (chosen by measurement: a lower validation loss for a few more first-layer weights;
// figures in docs/benchmarks.md, "Calibration", session 4). layers()[0].weight then has
// first_layer_input_size() columns.
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

struct FourierFeatures {
  int inputs = 0;       // the leading inputs encoded (0 = no encoding), <= the input size
  int frequencies = 0;  // per input, 0..16
  float base = 1.0f;    // lowest angular frequency, rad per normalised unit, finite and > 0
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("inputs", self.inputs);
    visit("frequencies", self.frequencies);
    visit("base", self.base);
  }
  int Width() const { return 2 * inputs * frequencies; }
  bool Enabled() const { return Width() > 0; }
  // Throws std::invalid_argument naming the field and value (input_size: the network's).
  void Check(int input_size) const;
};

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
  Mlp(std::vector<int> sizes, Activation activation, std::uint64_t seed,
      FourierFeatures fourier = {});

  const std::vector<int>& sizes() const { return sizes_; }
  int input_size() const { return sizes_.empty() ? 0 : sizes_.front(); }
  int output_size() const { return sizes_.empty() ? 0 : sizes_.back(); }
  Activation activation() const { return activation_; }
  const FourierFeatures& fourier() const { return fourier_; }
  // Rows of a_0, the first layer's input: input_size() + fourier().Width().
  int first_layer_input_size() const { return input_size() + fourier_.Width(); }
  // Completes a_0 in place: `a0` is [first_layer_input_size, m] with the normalised inputs in its
  // top input_size() rows; the Fourier rows below them are written (nothing without features).
  // std::invalid_argument for a wrong row count.
  void Encode(Eigen::Ref<Eigen::MatrixXf> a0) const;
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
  FourierFeatures fourier_;
  std::vector<MlpLayer> layers_;
  Eigen::VectorXf input_mean_, input_scale_, output_mean_, output_scale_;
};

}  // namespace gs360
