#include "calib/onnx_export.h"

#include <unistd.h>
#include <algorithm>
#include <catch2/catch.hpp>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iterator>
#include <opencv2/dnn.hpp>
#include <stdexcept>
#include <string>

#include "base/hash.h"
#include "calib/train.h"

namespace gs360 {
namespace {

// A network with calibration-like normalisation (pixels up to 800 px, colour changes ~0.1) and
// non-zero biases everywhere.
Mlp CalibrationLikeMlp(Activation activation, std::uint64_t seed, FourierFeatures fourier = {}) {
  Mlp mlp({5, 16, 12, 8, 2}, activation, seed, fourier);
  int k = 0;
  for (auto& layer : mlp.layers())
    layer.bias = Eigen::VectorXf::LinSpaced(layer.bias.size(), -0.3f, 0.2f + 0.1f * k++);
  Eigen::VectorXf mean(5), scale(5);
  mean << 400.0f, 380.0f, 0.02f, -0.01f, 0.03f;
  scale << 230.0f, 220.0f, 0.11f, 0.09f, 0.13f;
  mlp.SetInputNormalization(mean, scale);
  mlp.SetOutputNormalization(Eigen::Vector2f(0.05f, -0.02f), Eigen::Vector2f(0.6f, 0.55f));
  return mlp;
}

Eigen::MatrixXf RandomFeatures(int n) {
  Eigen::MatrixXf x = Eigen::MatrixXf::Random(5, n);  // [-1, 1]
  x.row(0) = (x.row(0).array() + 1.0f) * 400.0f;
  x.row(1) = (x.row(1).array() + 1.0f) * 400.0f;
  x.bottomRows(3) *= 0.3f;
  return x;
}

// Runs the ONNX model with OpenCV's dnn module; x is [in, n] (Mlp layout), the result [out, n].
Eigen::MatrixXf RunWithOpenCv(const std::vector<std::uint8_t>& bytes, const Eigen::MatrixXf& x) {
  cv::dnn::Net net =
      cv::dnn::readNetFromONNX(reinterpret_cast<const char*>(bytes.data()), bytes.size());
  REQUIRE_FALSE(net.empty());
  cv::Mat input(static_cast<int>(x.cols()), static_cast<int>(x.rows()), CV_32F);
  for (int r = 0; r < input.rows; ++r) {
    for (int c = 0; c < input.cols; ++c) input.at<float>(r, c) = x(c, r);
  }
  net.setInput(input, "input");
  const cv::Mat out = net.forward("slopes");
  REQUIRE(out.dims == 2);
  REQUIRE(out.rows == input.rows);
  Eigen::MatrixXf y(out.cols, out.rows);
  for (int r = 0; r < out.rows; ++r) {
    for (int c = 0; c < out.cols; ++c) y(c, r) = out.at<float>(r, c);
  }
  return y;
}

// The export of `mlp` passes the checker and, read by OpenCV, gives Mlp::Forward's outputs, which
// vary (not a constant network), to float rounding.
void CheckMatchesForward(const Mlp& mlp, const std::vector<std::uint8_t>& bytes,
                         const Eigen::MatrixXf& x) {
  CHECK_NOTHROW(CheckOnnxModel(bytes));
  const Eigen::MatrixXf expected = mlp.Forward(x);
  const Eigen::MatrixXf actual = RunWithOpenCv(bytes, x);
  REQUIRE(actual.rows() == 2);
  REQUIRE(actual.cols() == x.cols());
  CHECK(expected.row(0).maxCoeff() - expected.row(0).minCoeff() > 0.1f);
  CHECK((actual - expected).cwiseAbs().maxCoeff() <= 1e-5f);
}

bool Contains(const std::vector<std::uint8_t>& bytes, const std::string& s) {
  return std::search(bytes.begin(), bytes.end(), s.begin(), s.end()) != bytes.end();
}

std::string RuntimeError(const std::function<void()>& f) {
  try {
    f();
  } catch (const std::runtime_error& e) {
    return e.what();
  }
  return "";
}

}  // namespace

TEST_CASE("ONNX export matches Mlp::Forward through OpenCV dnn", "[onnx]") {
  const Eigen::MatrixXf x = RandomFeatures(500);
  for (Activation activation : {Activation::kTanh, Activation::kRelu, Activation::kSilu}) {
    for (bool fold : {true, false}) {
      INFO("activation " << ToString(activation) << " fold " << fold);
      const Mlp mlp = CalibrationLikeMlp(activation, 3);
      OnnxExportOptions options;
      options.fold_normalization = fold;
      CheckMatchesForward(mlp, ExportMlpToOnnx(mlp, options), x);
    }
  }
}

TEST_CASE("ONNX export with Fourier features matches Mlp::Forward through OpenCV dnn", "[onnx]") {
  const Eigen::MatrixXf x = RandomFeatures(500);
  for (bool fold : {true, false}) {
    INFO("fold " << fold);
    // The calibration's default encoding: 4 frequencies of (u, v), the highest 8 rad per unit.
    const Mlp mlp = CalibrationLikeMlp(Activation::kTanh, 5, FourierFeatures{2, 4, 1.0f});
    OnnxExportOptions options;
    options.fold_normalization = fold;
    const std::vector<std::uint8_t> bytes = ExportMlpToOnnx(mlp, options);
    CHECK(Contains(bytes, "Sin"));
    CHECK(Contains(bytes, "Cos"));
    CHECK(Contains(bytes, "fourier_features"));
    CheckMatchesForward(mlp, bytes, x);
  }
}

TEST_CASE("ONNX export of a trained network", "[onnx]") {
  // Fit y = (sin(u) + v^2, u v) on pixel-scaled inputs, then check the export on new inputs.
  Eigen::MatrixXf x = RandomFeatures(4000);
  Eigen::MatrixXf y(2, x.cols());
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    const float u = x(0, i) / 400.0f - 1.0f, v = x(1, i) / 400.0f - 1.0f;
    y(0, i) = std::sin(u) + v * v + x(2, i);
    y(1, i) = u * v - x(3, i);
  }
  TrainOptions train;
  train.hidden = {16, 16};
  train.max_epochs = 10;
  train.batch_size = 256;
  const TrainResult r =
      Train(x.leftCols(3000), y.leftCols(3000), x.rightCols(1000), y.rightCols(1000), train);
  const std::vector<std::uint8_t> bytes = ExportMlpToOnnx(r.mlp);
  const Eigen::MatrixXf probe = RandomFeatures(300);
  CHECK((RunWithOpenCv(bytes, probe) - r.mlp.Forward(probe)).cwiseAbs().maxCoeff() <= 1e-5f);
}

TEST_CASE("ONNX export carries metadata and is deterministic", "[onnx]") {
  const Mlp mlp = CalibrationLikeMlp(Activation::kTanh, 4);
  OnnxExportOptions options;
  options.model_name = "finger_a";
  options.gs360_version = "9.8.7";
  const std::vector<std::uint8_t> bytes = ExportMlpToOnnx(mlp, options);
  CHECK(bytes == ExportMlpToOnnx(mlp, options));
  const std::vector<std::uint8_t> mlp_bytes = mlp.Serialize();
  for (const std::string s : {"gs360_version", "9.8.7", "model_name", "finger_a",
                              "input_description", "output_description", "slopes", "input",
                              "mlp_checksum", "transB", "Gemm", "Tanh", "folded"}) {
    INFO(s);
    CHECK(Contains(bytes, s));
  }
  CHECK(Contains(bytes, HashHex(mlp_bytes.data(), mlp_bytes.size())));
  CHECK_FALSE(Contains(bytes, "Sigmoid"));
  CHECK(Contains(ExportMlpToOnnx(CalibrationLikeMlp(Activation::kSilu, 4)), "Sigmoid"));
  // Another network, another checksum.
  CHECK(ExportMlpToOnnx(CalibrationLikeMlp(Activation::kTanh, 5), options) != bytes);
}

TEST_CASE("ONNX checker rejects broken models", "[onnx]") {
  const Mlp good = CalibrationLikeMlp(Activation::kTanh, 6);
  std::vector<std::uint8_t> bytes = ExportMlpToOnnx(good);
  SECTION("a declared output shape that does not match the graph") {
    // The graph output's value info: name "slopes" (0x0a 0x06 ...) followed by its type (0x12);
    // its last dimension is dim { dim_value: 2 } = 0x0a 0x02 0x08 0x02. Declare 3 instead.
    const std::vector<std::uint8_t> name = {0x0a, 0x06, 's', 'l', 'o', 'p', 'e', 's', 0x12};
    auto it = std::search(bytes.begin(), bytes.end(), name.begin(), name.end());
    REQUIRE(it != bytes.end());
    const std::vector<std::uint8_t> dim = {0x0a, 0x02, 0x08, 0x02};
    auto d = std::search(it, bytes.end(), dim.begin(), dim.end());
    REQUIRE(d != bytes.end());
    *(d + 3) = 0x03;
    const std::string error = RuntimeError([&] { CheckOnnxModel(bytes); });
    INFO(error);
    CHECK(error.find("ONNX checker rejected the model") != std::string::npos);
    CHECK(error.find("layer3.Gemm") != std::string::npos);
    CHECK(error.find("(2) vs (3)") != std::string::npos);
  }
  SECTION("layer shapes that do not chain are refused before the export") {
    Mlp bad = good;
    // Layer 1 maps 16 -> 12; give it 17 inputs. ONNX's Gemm inference would not notice.
    bad.layers()[1].weight = Eigen::MatrixXf::Random(12, 17);
    CHECK_THROWS_WITH(ExportMlpToOnnx(bad), Catch::Contains("layer 1 has weight [12, 17]"));
  }
  SECTION("a node input that nothing produces") {
    // Node inputs are serialised before the initializers: rename the first reference only.
    const std::string name = "layer1.weight";
    auto it = std::search(bytes.begin(), bytes.end(), name.begin(), name.end());
    REQUIRE(it != bytes.end());
    *(it + static_cast<std::ptrdiff_t>(name.size()) - 1) = 'X';
    const std::string error = RuntimeError([&] { CheckOnnxModel(bytes); });
    INFO(error);
    CHECK(error.find("ONNX checker rejected the model") != std::string::npos);
    CHECK(error.find("layer1.weighX") != std::string::npos);
  }
  SECTION("not a model") {
    const std::vector<std::uint8_t> garbage = {0xff, 0xff, 0xff, 0x07, 0x01};
    CHECK(RuntimeError([&] { CheckOnnxModel(garbage); }).find("cannot parse") != std::string::npos);
  }
  SECTION("first and last layers must fit the normalisation") {
    Mlp bad = good;
    bad.layers()[0].weight = Eigen::MatrixXf::Random(16, 4);
    CHECK_THROWS_AS(ExportMlpToOnnx(bad), std::invalid_argument);
    CHECK_THROWS_AS(ExportMlpToOnnx(Mlp()), std::invalid_argument);
  }
}

TEST_CASE("ONNX export options and file output", "[onnx]") {
  OnnxExportOptions options;
  CHECK_NOTHROW(options.Check());
  options.opset_version = 10;
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("opset_version = 10"));
  options = {};
  options.output_name = "input";
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("output_name"));
  options = {};
  options.model_name.clear();
  CHECK_THROWS_WITH(options.Check(), Catch::Contains("model_name"));

  const Mlp mlp = CalibrationLikeMlp(Activation::kRelu, 7);
  const auto dir =
      std::filesystem::temp_directory_path() / ("gs360_onnx_test_" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  const auto path = dir / "model.onnx";
  WriteOnnxFile(path, mlp);
  std::ifstream file(path, std::ios::binary);
  const std::vector<std::uint8_t> written((std::istreambuf_iterator<char>(file)),
                                          std::istreambuf_iterator<char>());
  CHECK(written == ExportMlpToOnnx(mlp));
  const cv::dnn::Net net = cv::dnn::readNetFromONNX(path.string());
  CHECK_FALSE(net.empty());
  const auto missing = dir / "no_such_dir" / "model.onnx";
  CHECK(RuntimeError([&] { WriteOnnxFile(missing, mlp); }).find(missing.string()) !=
        std::string::npos);
  std::filesystem::remove_all(dir);
}

}  // namespace gs360
