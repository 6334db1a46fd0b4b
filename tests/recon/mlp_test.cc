#include "recon/mlp.h"

#include <catch2/catch.hpp>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>

#include "base/hash.h"

namespace gs360 {
namespace {

// 2 -> 2 -> 1 with hand-set weights and normalisation.
Mlp TinyNetwork(Activation activation) {
  Mlp mlp({2, 2, 1}, activation, 7);
  mlp.layers()[0].weight << 0.5f, -1.0f, 2.0f, 0.25f;
  mlp.layers()[0].bias << 0.1f, -0.2f;
  mlp.layers()[1].weight << 1.5f, -0.5f;
  mlp.layers()[1].bias << 0.3f;
  mlp.SetInputNormalization(Eigen::Vector2f(1.0f, 2.0f), Eigen::Vector2f(2.0f, 4.0f));
  mlp.SetOutputNormalization(Eigen::VectorXf::Constant(1, 10.0f),
                             Eigen::VectorXf::Constant(1, 3.0f));
  return mlp;
}

double Act(Activation a, double z) {
  switch (a) {
    case Activation::kTanh:
      return std::tanh(z);
    case Activation::kRelu:
      return z > 0.0 ? z : 0.0;
    case Activation::kSilu:
      return z / (1.0 + std::exp(-z));
  }
  return 0.0;
}

// The same network evaluated by hand in double precision.
double TinyByHand(Activation a, double x0, double x1) {
  const double a0 = (x0 - 1.0) / 2.0;
  const double a1 = (x1 - 2.0) / 4.0;
  const double h0 = Act(a, 0.5 * a0 - 1.0 * a1 + 0.1);
  const double h1 = Act(a, 2.0 * a0 + 0.25 * a1 - 0.2);
  const double z = 1.5 * h0 - 0.5 * h1 + 0.3;
  return z * 3.0 + 10.0;
}

Mlp RandomNetwork(std::uint64_t seed) {
  Mlp mlp({5, 8, 6, 2}, Activation::kSilu, seed);
  for (auto& layer : mlp.layers()) layer.bias.setRandom();
  Eigen::VectorXf mean(5), scale(5);
  mean << 300.0f, 200.0f, 0.1f, -0.2f, 0.3f;
  scale << 150.0f, 100.0f, 0.5f, 0.4f, 0.3f;
  mlp.SetInputNormalization(mean, scale);
  mlp.SetOutputNormalization(Eigen::Vector2f(0.1f, -0.1f), Eigen::Vector2f(0.7f, 0.9f));
  return mlp;
}

void RequireSameNetwork(const Mlp& a, const Mlp& b) {
  REQUIRE(a.sizes() == b.sizes());
  REQUIRE(a.activation() == b.activation());
  REQUIRE(a.input_mean() == b.input_mean());
  REQUIRE(a.input_scale() == b.input_scale());
  REQUIRE(a.output_mean() == b.output_mean());
  REQUIRE(a.output_scale() == b.output_scale());
  REQUIRE(a.layers().size() == b.layers().size());
  for (std::size_t k = 0; k < a.layers().size(); ++k) {
    REQUIRE(a.layers()[k].weight == b.layers()[k].weight);
    REQUIRE(a.layers()[k].bias == b.layers()[k].bias);
  }
}

// 3 -> 4 -> 2 with Fourier features of the first two inputs.
Mlp FourierNetwork(std::uint64_t seed) {
  Mlp mlp({3, 4, 2}, Activation::kTanh, seed, FourierFeatures{2, 3, 0.7f});
  for (auto& layer : mlp.layers()) layer.bias.setRandom();
  mlp.SetInputNormalization(Eigen::Vector3f(300.0f, 200.0f, 0.1f),
                            Eigen::Vector3f(150.0f, 100.0f, 0.5f));
  mlp.SetOutputNormalization(Eigen::Vector2f(0.1f, -0.1f), Eigen::Vector2f(0.7f, 0.9f));
  return mlp;
}

// FourierNetwork evaluated by hand in double precision, following the header's layout.
Eigen::Vector2d FourierByHand(const Mlp& mlp, const Eigen::Vector3d& x) {
  Eigen::Vector3d a;
  for (int i = 0; i < 3; ++i) a[i] = (x[i] - mlp.input_mean()[i]) / mlp.input_scale()[i];
  Eigen::VectorXd a0(3 + 12);
  a0.head<3>() = a;  // fixed size: GCC 12 with AVX warns (falsely) on head(3)
  for (int i = 0; i < 2; ++i) {
    for (int j = 0; j < 3; ++j) {
      const double phase = 0.7 * std::pow(2.0, j) * a[i];
      a0[3 + i * 3 + j] = std::sin(phase);
      a0[3 + 6 + i * 3 + j] = std::cos(phase);
    }
  }
  const auto& l = mlp.layers();
  const Eigen::VectorXd h =
      (l[0].weight.cast<double>() * a0 + l[0].bias.cast<double>()).array().tanh().matrix();
  const Eigen::Vector2d z = l[1].weight.cast<double>() * h + l[1].bias.cast<double>();
  return z.cwiseProduct(mlp.output_scale().cast<double>()) + mlp.output_mean().cast<double>();
}

std::string ErrorOf(std::span<const std::uint8_t> bytes) {
  try {
    Mlp::Deserialize(bytes);
  } catch (const std::runtime_error& e) {
    return e.what();
  }
  return "";
}

}  // namespace

TEST_CASE("Mlp tiny network matches the hand computation", "[mlp]") {
  for (Activation a : {Activation::kTanh, Activation::kRelu, Activation::kSilu}) {
    INFO("activation " << ToString(a));
    const Mlp mlp = TinyNetwork(a);
    Eigen::MatrixXf x(2, 4);
    x << 3.0f, 1.0f, -5.0f, 0.5f,  //
        6.0f, 2.0f, 9.0f, -7.0f;
    const Eigen::MatrixXf y = mlp.Forward(x);
    REQUIRE(y.rows() == 1);
    REQUIRE(y.cols() == 4);
    for (int c = 0; c < 4; ++c) {
      CHECK(y(0, c) == Approx(TinyByHand(a, x(0, c), x(1, c))).margin(1e-5));
    }
  }
  // One value written out: x = (3, 6) -> normalised (1, 1) -> z1 = (-0.4, 2.05).
  const double expected = (1.5 * std::tanh(-0.4) - 0.5 * std::tanh(2.05) + 0.3) * 3.0 + 10.0;
  CHECK(TinyNetwork(Activation::kTanh).Forward(Eigen::Vector2f(3.0f, 6.0f))(0, 0) ==
        Approx(expected).margin(1e-5));
}

TEST_CASE("Mlp with Fourier features matches the hand computation", "[mlp]") {
  const Mlp mlp = FourierNetwork(4);
  REQUIRE(mlp.first_layer_input_size() == 15);
  REQUIRE(mlp.layers()[0].weight.cols() == 15);
  CHECK(mlp.ParameterCount() == 4 * 15 + 4 + 2 * 4 + 2);
  Eigen::MatrixXf x(3, 1500);
  x.setRandom();
  x.row(0) = (x.row(0).array() * 320.0f + 320.0f).matrix();
  x.row(1) = (x.row(1).array() * 240.0f + 240.0f).matrix();
  const Eigen::MatrixXf y = mlp.Forward(x);
  for (int c : {0, 1, 700, 1023, 1024, 1499}) {
    const Eigen::Vector2d expected = FourierByHand(mlp, x.col(c).cast<double>());
    CHECK(y(0, c) == Approx(expected[0]).margin(1e-5));
    CHECK(y(1, c) == Approx(expected[1]).margin(1e-5));
  }
  // The encoding really enters: zeroing the Fourier columns changes the output.
  Mlp plain = mlp;
  plain.layers()[0].weight.rightCols(12).setZero();
  CHECK((plain.Forward(x) - y).cwiseAbs().maxCoeff() > 1e-3f);
  // Encode: the normalised rows on top, then sin, then cos.
  Eigen::MatrixXf a0 = Eigen::MatrixXf::Constant(15, 1, 7.0f);
  a0.topRows(3).setZero();
  a0(0, 0) = 1.0f;
  mlp.Encode(a0);
  CHECK(a0(0, 0) == 1.0f);
  CHECK(a0(3, 0) == Approx(std::sin(0.7)).margin(1e-6));
  CHECK(a0(5, 0) == Approx(std::sin(2.8)).margin(1e-6));
  CHECK(a0(6, 0) == 0.0f);  // sin of input 1's phase 0
  CHECK(a0(9 + 2, 0) == Approx(std::cos(2.8)).margin(1e-6));
  CHECK(a0(12, 0) == 1.0f);  // cos of input 1's phase 0
  Eigen::MatrixXf wrong(14, 1);
  CHECK_THROWS_AS(mlp.Encode(wrong), std::invalid_argument);
}

TEST_CASE("Mlp Fourier options are validated", "[mlp]") {
  CHECK_THROWS_AS(Mlp({3, 4, 2}, Activation::kTanh, 1, FourierFeatures{4, 2, 1.0f}),
                  std::invalid_argument);
  CHECK_THROWS_AS(Mlp({3, 4, 2}, Activation::kTanh, 1, FourierFeatures{2, 17, 1.0f}),
                  std::invalid_argument);
  CHECK_THROWS_AS(Mlp({3, 4, 2}, Activation::kTanh, 1, FourierFeatures{2, 2, 0.0f}),
                  std::invalid_argument);
  CHECK_THROWS_AS(Mlp({3, 4, 2}, Activation::kTanh, 1,
                      FourierFeatures{2, 2, std::numeric_limits<float>::quiet_NaN()}),
                  std::invalid_argument);
  try {
    Mlp({3, 4, 2}, Activation::kTanh, 1, FourierFeatures{-1, 2, 1.0f});
    FAIL("no throw");
  } catch (const std::invalid_argument& e) {
    CHECK(std::string(e.what()).find("inputs = -1") != std::string::npos);
  }
  // Frequencies without inputs (or the reverse) is simply no encoding.
  CHECK(
      Mlp({3, 4, 2}, Activation::kTanh, 1, FourierFeatures{0, 4, 1.0f}).first_layer_input_size() ==
      3);
}

TEST_CASE("Mlp Forward is column independent across blocks", "[mlp]") {
  const Mlp mlp = RandomNetwork(3);
  Eigen::MatrixXf x = Eigen::MatrixXf::Random(5, 2500);
  x.row(0) = x.row(0) * 300.0f;
  x.row(1) = x.row(1) * 200.0f;
  const Eigen::MatrixXf y = mlp.Forward(x);
  REQUIRE(y.rows() == 2);
  REQUIRE(y.cols() == 2500);
  for (int c : {0, 1, 1023, 1024, 1025, 2047, 2048, 2499}) {
    const Eigen::MatrixXf single = mlp.Forward(x.col(c));
    // A single column goes through Eigen's matrix-vector kernel, a block through its
    // matrix-matrix one: the sums round in another order (a few float ulps; clang's build
    // differs by more than 1e-6). A column mixed with another would be off by order one.
    INFO("column " << c << ": " << (single.col(0) - y.col(c)).cwiseAbs().maxCoeff());
    CHECK((single.col(0) - y.col(c)).cwiseAbs().maxCoeff() < 1e-5f);
  }
  CHECK(mlp.Forward(Eigen::MatrixXf(5, 0)).cols() == 0);
  CHECK_THROWS_AS(mlp.Forward(Eigen::MatrixXf::Zero(4, 3)), std::invalid_argument);
  CHECK_THROWS_AS(Mlp().Forward(Eigen::MatrixXf::Zero(1, 1)), std::invalid_argument);
}

TEST_CASE("Mlp construction and initialisation", "[mlp]") {
  const Mlp a({5, 32, 32, 2}, Activation::kTanh, 11);
  const Mlp b({5, 32, 32, 2}, Activation::kTanh, 11);
  const Mlp c({5, 32, 32, 2}, Activation::kTanh, 12);
  RequireSameNetwork(a, b);
  CHECK(a.layers()[0].weight != c.layers()[0].weight);
  CHECK(a.ParameterCount() == 5 * 32 + 32 + 32 * 32 + 32 + 32 * 2 + 2);
  CHECK(a.input_size() == 5);
  CHECK(a.output_size() == 2);
  // Glorot-uniform bound sqrt(6 / (in + out)) and a spread that fills most of it.
  const float glorot = std::sqrt(6.0f / 37.0f);
  CHECK(a.layers()[0].weight.cwiseAbs().maxCoeff() <= glorot);
  CHECK(a.layers()[0].weight.cwiseAbs().maxCoeff() > 0.8f * glorot);
  CHECK(a.layers()[0].bias.isZero());
  CHECK(std::abs(a.layers()[1].weight.mean()) < 0.05f);
  // He-uniform sqrt(6 / in) for relu hidden layers.
  const Mlp r({5, 32, 32, 2}, Activation::kRelu, 11);
  CHECK(r.layers()[1].weight.cwiseAbs().maxCoeff() <= std::sqrt(6.0f / 32.0f));
  CHECK(r.layers()[1].weight.cwiseAbs().maxCoeff() > std::sqrt(6.0f / 64.0f));
  CHECK(a.input_mean().isZero());
  CHECK(a.input_scale().isOnes());

  CHECK_THROWS_AS(Mlp({5}, Activation::kTanh, 1), std::invalid_argument);
  CHECK_THROWS_AS(Mlp({5, 0, 2}, Activation::kTanh, 1), std::invalid_argument);
  CHECK_THROWS_AS(Mlp({5, -3}, Activation::kTanh, 1), std::invalid_argument);
}

TEST_CASE("Mlp normalisation setters validate", "[mlp]") {
  Mlp mlp({3, 4, 2}, Activation::kTanh, 1);
  CHECK_THROWS_AS(mlp.SetInputNormalization(Eigen::VectorXf::Zero(2), Eigen::VectorXf::Ones(2)),
                  std::invalid_argument);
  CHECK_THROWS_AS(mlp.SetInputNormalization(Eigen::VectorXf::Zero(3), Eigen::Vector3f(1, 0, 1)),
                  std::invalid_argument);
  CHECK_THROWS_AS(mlp.SetOutputNormalization(Eigen::Vector2f(0, 0), Eigen::Vector2f(1, -1)),
                  std::invalid_argument);
  CHECK_THROWS_AS(
      mlp.SetOutputNormalization(Eigen::Vector2f(std::numeric_limits<float>::quiet_NaN(), 0),
                                 Eigen::Vector2f(1, 1)),
      std::invalid_argument);
  mlp.SetOutputNormalization(Eigen::Vector2f(1, 2), Eigen::Vector2f(3, 4));
  CHECK(mlp.output_scale() == Eigen::Vector2f(3, 4));
}

TEST_CASE("Mlp activation names", "[mlp]") {
  for (Activation a : {Activation::kTanh, Activation::kRelu, Activation::kSilu}) {
    CHECK(ParseActivation(ToString(a)) == a);
  }
  CHECK(ToString(Activation::kSilu) == "silu");
  CHECK_THROWS_AS(ParseActivation("gelu"), std::invalid_argument);
}

TEST_CASE("Mlp serialisation round trip is exact", "[mlp]") {
  const Mlp mlp = RandomNetwork(5);
  const std::vector<std::uint8_t> bytes = mlp.Serialize();
  REQUIRE(std::memcmp(bytes.data(), "GS360MLP", 8) == 0);
  const Mlp back = Mlp::Deserialize(bytes);
  RequireSameNetwork(mlp, back);
  const Eigen::MatrixXf x = Eigen::MatrixXf::Random(5, 100) * 100.0f;
  CHECK(mlp.Forward(x) == back.Forward(x));
  CHECK(back.Serialize() == bytes);
}

TEST_CASE("Mlp with Fourier features round-trips, and version 1 blobs still load", "[mlp]") {
  const Mlp mlp = FourierNetwork(6);
  const std::vector<std::uint8_t> bytes = mlp.Serialize();
  const Mlp back = Mlp::Deserialize(bytes);
  RequireSameNetwork(mlp, back);
  CHECK(back.fourier().inputs == 2);
  CHECK(back.fourier().frequencies == 3);
  CHECK(back.fourier().base == 0.7f);
  const Eigen::MatrixXf x = Eigen::MatrixXf::Random(3, 50) * 300.0f;
  CHECK(mlp.Forward(x) == back.Forward(x));
  for (std::size_t len = 0; len < bytes.size(); ++len) {
    INFO("length " << len);
    CHECK_FALSE(ErrorOf(std::span(bytes.data(), len)).empty());
  }

  // A version 1 blob (written before the Fourier features existed): the version 2 layout of a
  // network without them, minus the three Fourier fields after the sizes, re-checksummed.
  const Mlp plain = RandomNetwork(6);
  std::vector<std::uint8_t> v1 = plain.Serialize();
  const std::size_t sizes_end = 8 + 4 + 4 + 4 + 4 * plain.sizes().size();
  v1.erase(v1.begin() + static_cast<std::ptrdiff_t>(sizes_end),
           v1.begin() + static_cast<std::ptrdiff_t>(sizes_end + 12));
  v1[8] = 1;
  v1.resize(v1.size() - 8);
  const std::uint64_t checksum = Hasher().Add(v1.data(), v1.size()).Digest();
  for (int b = 0; b < 8; ++b) v1.push_back(static_cast<std::uint8_t>(checksum >> (8 * b)));
  const Mlp old = Mlp::Deserialize(v1);
  RequireSameNetwork(plain, old);
  CHECK_FALSE(old.fourier().Enabled());
  const Eigen::MatrixXf x5 = Eigen::MatrixXf::Random(5, 50) * 100.0f;
  CHECK(old.Forward(x5) == plain.Forward(x5));

  // Fourier fields that do not fit the network are a clear error even with a valid checksum.
  std::vector<std::uint8_t> bad = bytes;
  const std::size_t inputs_at = 8 + 4 + 4 + 4 + 4 * mlp.sizes().size();
  bad[inputs_at] = 7;  // 7 encoded inputs for a 3-input network
  bad.resize(bad.size() - 8);
  const std::uint64_t bad_sum = Hasher().Add(bad.data(), bad.size()).Digest();
  for (int b = 0; b < 8; ++b) bad.push_back(static_cast<std::uint8_t>(bad_sum >> (8 * b)));
  CHECK(ErrorOf(bad).find("inputs = 7") != std::string::npos);
}

TEST_CASE("Mlp deserialisation rejects truncated and corrupt data", "[mlp]") {
  const std::vector<std::uint8_t> bytes = RandomNetwork(9).Serialize();
  SECTION("truncation at every length") {
    for (std::size_t len = 0; len < bytes.size(); ++len) {
      INFO("length " << len);
      CHECK_FALSE(ErrorOf(std::span(bytes.data(), len)).empty());
    }
    CHECK(ErrorOf(std::span(bytes.data(), bytes.size() - 1)).find("truncated") !=
          std::string::npos);
  }
  SECTION("a flipped bit at every offset") {
    for (std::size_t i = 0; i < bytes.size(); ++i) {
      for (std::uint8_t mask : {std::uint8_t{0x01}, std::uint8_t{0x80}}) {
        std::vector<std::uint8_t> bad = bytes;
        bad[i] ^= mask;
        INFO("offset " << i << " mask " << int(mask));
        CHECK_FALSE(ErrorOf(bad).empty());
      }
    }
    std::vector<std::uint8_t> bad = bytes;
    bad[bytes.size() / 2] ^= 0x10;
    CHECK(ErrorOf(bad).find("checksum") != std::string::npos);
  }
  SECTION("messages") {
    std::vector<std::uint8_t> bad = bytes;
    bad[0] = 'X';
    CHECK(ErrorOf(bad).find("magic") != std::string::npos);
    bad = bytes;
    bad[8] = 3;  // version
    CHECK(ErrorOf(bad).find("version 3") != std::string::npos);
    bad = bytes;
    bad.push_back(0);
    CHECK(ErrorOf(bad).find("trailing") != std::string::npos);
  }
  SECTION("non-finite weight with a valid checksum") {
    Mlp mlp = RandomNetwork(9);
    mlp.layers()[1].weight(2, 3) = std::numeric_limits<float>::infinity();
    std::vector<std::uint8_t> bad = mlp.Serialize();
    // Serialize does not validate; Deserialize must refuse even though the checksum matches.
    const std::string error = ErrorOf(bad);
    CHECK(error.find("non-finite") != std::string::npos);
    CHECK(error.find("layer 1 weight") != std::string::npos);
  }
}

}  // namespace gs360
