#include <catch2/catch.hpp>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "storage/frame_codec.h"
#include "tests/storage/storage_test_util.h"

namespace gs360 {
namespace {

TEST_CASE("EncodeFrame round-trips every supported image type exactly", "[storage][codec]") {
  for (const int type : {CV_8UC3, CV_8UC1, CV_16UC1, CV_16UC3}) {
    CAPTURE(cv::typeToString(type));
    const cv::Mat image = test::NoisyFrame(3, 97, 61, type);
    const EncodedFrame encoded = EncodeFrame(image);
    CHECK(encoded.width == 97);
    CHECK(encoded.height == 61);
    CHECK(encoded.channels == image.channels());
    CHECK(encoded.bit_depth == (CV_MAT_DEPTH(type) == CV_16U ? 16 : 8));
    const cv::Mat decoded = DecodeFrame(encoded.png);
    CHECK(test::SameImage(decoded, image));
  }
}

TEST_CASE("every OpenCV PNG setting is lossless and compression levels trade size",
          "[storage][codec]") {
  const cv::Mat image = test::NoisyFrame(5, 160, 120);
  std::size_t stored_size = 0, level9_size = 0;
  for (const int level : {-1, 0, 1, 6, 9}) {
    for (const PngStrategy strategy :
         {PngStrategy::kDefault, PngStrategy::kFiltered, PngStrategy::kHuffmanOnly,
          PngStrategy::kRle, PngStrategy::kFixed}) {
      CAPTURE(level, static_cast<int>(strategy));
      const EncodedFrame encoded =
          EncodeFrame(image, {.compression_level = level, .strategy = strategy});
      CHECK(test::SameImage(DecodeFrame(encoded.png), image));
      if (level == 0 && strategy == PngStrategy::kDefault) stored_size = encoded.png.size();
      if (level == 9 && strategy == PngStrategy::kDefault) level9_size = encoded.png.size();
    }
  }
  // Level 0 stores the filtered rows uncompressed: more than the raw pixels.
  CHECK(stored_size >= image.total() * image.elemSize());
  CHECK(level9_size < stored_size * 3 / 4);
}

TEST_CASE("EncodeFrame rejects images it cannot store losslessly", "[storage][codec]") {
  CHECK_THROWS_AS(EncodeFrame(cv::Mat()), std::invalid_argument);
  CHECK_THROWS_AS(EncodeFrame(cv::Mat(4, 4, CV_32FC1, cv::Scalar(0.5))), std::invalid_argument);
  CHECK_THROWS_AS(EncodeFrame(cv::Mat(4, 4, CV_8UC2, cv::Scalar(1, 2))), std::invalid_argument);
  CHECK_THROWS_AS(EncodeFrame(cv::Mat(4, 4, CV_8UC4, cv::Scalar(1, 2, 3, 4))),
                  std::invalid_argument);
}

TEST_CASE("PngOptions::Check names the field and the value", "[storage][codec]") {
  CHECK_NOTHROW(PngOptions{}.Check());
  CHECK_THROWS_WITH(PngOptions{.compression_level = 10}.Check(),
                    Catch::Contains("compression_level") && Catch::Contains("10"));
  CHECK_THROWS_WITH(PngOptions{.compression_level = -2}.Check(), Catch::Contains("-2"));
  CHECK_THROWS_WITH(PngOptions{.strategy = static_cast<PngStrategy>(42)}.Check(),
                    Catch::Contains("strategy") && Catch::Contains("42"));
}

TEST_CASE("DecodeFrame returns an empty image for bytes that are not a PNG", "[storage][codec]") {
  const std::vector<std::uint8_t> garbage(300, 0x5a);
  CHECK(DecodeFrame(garbage).empty());
  CHECK(DecodeFrame({}).empty());
  // A truncated PNG does not decode either.
  EncodedFrame encoded = EncodeFrame(test::NoisyFrame(1, 64, 48));
  encoded.png.resize(encoded.png.size() / 2);
  CHECK(DecodeFrame(encoded.png).empty());
  // Nor does another image format: only PNG bytes reach OpenCV's decoder, whose DICOM reader
  // aborted the process on a fuzzed input (tests/fuzz/corpus/frame).
  std::vector<std::uint8_t> bmp;
  REQUIRE(cv::imencode(".bmp", test::NoisyFrame(3, 16, 12), bmp));
  CHECK(DecodeFrame(bmp).empty());
}

TEST_CASE("BlobChecksum detects a single flipped bit", "[storage][codec]") {
  std::vector<std::uint8_t> blob = EncodeFrame(test::NoisyFrame(2, 64, 48)).png;
  const std::string original = BlobChecksum(blob);
  CHECK(original.size() == 16);
  CHECK(BlobChecksum(blob) == original);
  blob[blob.size() / 2] ^= 0x08;
  CHECK(BlobChecksum(blob) != original);
  blob[blob.size() / 2] ^= 0x08;
  blob.push_back(0);
  CHECK(BlobChecksum(blob) != original);
}

}  // namespace
}  // namespace gs360
