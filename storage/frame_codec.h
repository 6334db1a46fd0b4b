#pragma once
// Lossless frame encoding for the run database: PNG (a built-in writer, or OpenCV's), decoding
// through OpenCV, and blob checksums.
//
// Supported images: CV_8UC1, CV_8UC3, CV_16UC1, CV_16UC3 (channel order as OpenCV holds it,
// BGR for 3 channels; decoding gives back exactly the same pixels and type).
//
// PNG settings (measured on 640x480 colour frames with sensor noise by bench/bench_storage.cc):
// after a row filter, noise is what remains, and string matching cannot compress noise. The
// default, the built-in writer (storage/png_writer.h) with the Average filter and literal-only
// Huffman coding, takes ~2.5 ms of CPU per frame, ~3x less than OpenCV/libpng's fastest
// setting (SUB + zlib 1), and is ~5% smaller (~370 kB per frame at noise sigma 1.7). zlib levels
// 1-9 with adaptive filters are 6-50x slower for at best the same size. Averaging K frames lowers
// the noise and the size.

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "storage/png_writer.h"

namespace gs360 {

// zlib strategies, as cv::ImwritePNGFlags.
enum class PngStrategy { kDefault, kFiltered, kHuffmanOnly, kRle, kFixed };

enum class PngEncoder {
  kBuiltin,  // storage/png_writer.h: one filter for every row, literal-only Huffman deflate
  kOpenCv,   // cv::imencode (libpng + zlib) with compression_level and strategy below
};

struct PngOptions {
  PngEncoder encoder = PngEncoder::kBuiltin;
  // kBuiltin: the row filter.
  PngFilter filter = PngFilter::kAverage;
  // kOpenCv: -1 is OpenCV's speed path (the SUB filter on every row, zlib level 1); 0..9 is a
  // zlib level with libpng's adaptive per-row filter choice (slower).
  int compression_level = -1;
  // kOpenCv: the zlib strategy.
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

// Checksum of a stored blob: geometry/hash.h's 64-bit hash, 16 lower-case hex digits.
std::string BlobChecksum(std::span<const std::uint8_t> blob);

}  // namespace gs360
