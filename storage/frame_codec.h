#pragma once
// Lossless frame encoding for the run database: PNG through OpenCV (libpng + zlib) both ways, and
// blob checksums.
//
// Supported images: CV_8UC1, CV_8UC3, CV_16UC1, CV_16UC3 (channel order as OpenCV holds it,
// BGR for 3 channels; decoding gives back exactly the same pixels and type).
//
// PNG settings: after a row filter, a sensor frame is mostly noise, and string matching cannot
// compress noise. So the default is OpenCV's speed path (the Sub filter on every row, zlib level
// 1) with Huffman-only coding: the fastest zlib setting and within a few percent of the smallest
// (the figures, bench/bench_storage.cc, are in docs/benchmarks.md).

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include <opencv2/core/mat.hpp>

namespace gs360 {

// zlib strategies, as cv::ImwritePNGFlags.
enum class PngStrategy { kDefault, kFiltered, kHuffmanOnly, kRle, kFixed };

// cv::imencode's PNG parameters.
struct PngOptions {
  // -1 is OpenCV's speed path (the Sub filter on every row, zlib level 1); 0..9 is a zlib level
  // with libpng's adaptive per-row filter choice (slower).
  int compression_level = -1;
  // The zlib strategy.
  PngStrategy strategy = PngStrategy::kHuffmanOnly;

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

// A frame encoded as PNG, ready to be committed.
struct EncodedFrame {
  std::vector<std::uint8_t> png;
  int width = 0;
  int height = 0;
  int channels = 0;   // 1 or 3
  int bit_depth = 0;  // 8 or 16
};

// Encodes `image` losslessly. Throws std::invalid_argument for an empty image or an unsupported
// type, std::runtime_error if the encoder fails.
EncodedFrame EncodeFrame(const cv::Mat& image, const PngOptions& options = {});

// Decodes a PNG blob; returns an empty Mat if the bytes are not a decodable PNG.
cv::Mat DecodeFrame(std::span<const std::uint8_t> png);

// Checksum of a stored blob: base/hash.h's 64-bit hash, 16 lower-case hex digits.
std::string BlobChecksum(std::span<const std::uint8_t> blob);

}  // namespace gs360
