#include <catch2/catch.hpp>

#include <random>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "storage/frame_codec.h"
#include "storage/png_writer.h"
#include "tests/storage/storage_test_util.h"

namespace gs360 {
namespace {

constexpr PngFilter kFilters[] = {PngFilter::kNone, PngFilter::kSub, PngFilter::kUp,
                                  PngFilter::kAverage, PngFilter::kPaeth};

// Decoded by OpenCV's libpng + zlib, which check every CRC-32 and the Adler-32.
cv::Mat Decode(const std::vector<std::uint8_t>& png) {
  return cv::imdecode(png, cv::IMREAD_UNCHANGED);
}

TEST_CASE("WritePng output decodes exactly, for every filter, type and odd size",
          "[storage][png]") {
  for (const PngFilter filter : kFilters) {
    for (const int type : {CV_8UC3, CV_8UC1, CV_16UC1, CV_16UC3}) {
      for (const cv::Size size :
           {cv::Size(1, 1), cv::Size(7, 1), cv::Size(1, 9), cv::Size(33, 17), cv::Size(160, 120)}) {
        CAPTURE(static_cast<int>(filter), cv::typeToString(type), size.width, size.height);
        const cv::Mat image = test::NoisyFrame(size.area(), size.width, size.height, type);
        REQUIRE(test::SameImage(Decode(WritePng(image, filter)), image));
      }
    }
  }
}

TEST_CASE("WritePng handles extreme symbol statistics", "[storage][png]") {
  SECTION("a constant image: one symbol") {
    for (const PngFilter filter : kFilters) {
      const cv::Mat black(50, 40, CV_8UC3, cv::Scalar(0, 0, 0));
      const cv::Mat grey(50, 40, CV_8UC1, cv::Scalar(77));
      CHECK(test::SameImage(Decode(WritePng(black, filter)), black));
      CHECK(test::SameImage(Decode(WritePng(grey, filter)), grey));
    }
  }
  SECTION("uniform random bytes: every symbol") {
    cv::Mat noise(64, 64, CV_8UC3);
    cv::randu(noise, cv::Scalar::all(0), cv::Scalar::all(256));
    for (const PngFilter filter : kFilters) {
      CHECK(test::SameImage(Decode(WritePng(noise, filter)), noise));
    }
  }
  SECTION("Fibonacci frequencies: Huffman depth above 15 must be limited") {
    // Byte value k appears Fib(k+1) times: an unlimited Huffman tree would be 24 levels deep.
    std::vector<std::uint8_t> bytes;
    std::uint64_t a = 1, b = 1;
    for (int k = 0; k < 25; ++k) {
      bytes.insert(bytes.end(), a, static_cast<std::uint8_t>(k));
      const std::uint64_t c = a + b;
      a = b;
      b = c;
    }
    std::shuffle(bytes.begin(), bytes.end(), std::mt19937(7));
    const int width = 1000;
    bytes.resize(bytes.size() / width * width);
    const cv::Mat image = cv::Mat(bytes, true).reshape(1, static_cast<int>(bytes.size() / width));
    REQUIRE(image.cols == width);
    CHECK(test::SameImage(Decode(WritePng(image, PngFilter::kNone)), image));
  }
}

TEST_CASE("WritePng output is checked by decoders: a flipped byte is caught", "[storage][png]") {
  const cv::Mat image = test::NoisyFrame(9, 64, 48);
  std::vector<std::uint8_t> png = WritePng(image, PngFilter::kAverage);
  REQUIRE(test::SameImage(Decode(png), image));
  png[png.size() / 2] ^= 0x10;  // inside the IDAT data
  CHECK(DecodeFrame(png).empty());
}

TEST_CASE("the built-in writer beats OpenCV's fastest setting on size for noisy frames",
          "[storage][png]") {
  const cv::Mat image = test::NoisyFrame(21, 640, 480);
  const std::size_t builtin = EncodeFrame(image).png.size();
  const std::size_t opencv =
      EncodeFrame(image, {.encoder = PngEncoder::kOpenCv, .compression_level = -1}).png.size();
  const std::size_t raw = image.total() * image.elemSize();
  CAPTURE(builtin, opencv, raw);
  CHECK(builtin < opencv);
  CHECK(builtin < raw * 6 / 10);
  CHECK_THROWS_AS(WritePng(cv::Mat(), PngFilter::kSub), std::invalid_argument);
  CHECK_THROWS_AS(WritePng(cv::Mat(3, 3, CV_16SC1), PngFilter::kSub), std::invalid_argument);
}

}  // namespace
}  // namespace gs360
