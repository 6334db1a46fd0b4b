#include "storage/frame_codec.h"

#include <stdexcept>
#include <string>

#include <opencv2/imgcodecs.hpp>

#include "base/byte_io.h"
#include "base/hash.h"

namespace gs360 {
namespace {

int OpenCvStrategy(PngStrategy s) {
  switch (s) {
    case PngStrategy::kDefault:
      return cv::IMWRITE_PNG_STRATEGY_DEFAULT;
    case PngStrategy::kFiltered:
      return cv::IMWRITE_PNG_STRATEGY_FILTERED;
    case PngStrategy::kHuffmanOnly:
      return cv::IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY;
    case PngStrategy::kRle:
      return cv::IMWRITE_PNG_STRATEGY_RLE;
    case PngStrategy::kFixed:
      return cv::IMWRITE_PNG_STRATEGY_FIXED;
  }
  throw std::invalid_argument("PngOptions.strategy: unknown value " +
                              std::to_string(static_cast<int>(s)));
}

}  // namespace

void PngOptions::Check() const {
  if (compression_level < -1 || compression_level > 9) {
    throw std::invalid_argument(
        "PngOptions.compression_level must be -1 (fast path) or 0..9, got " +
        std::to_string(compression_level));
  }
  OpenCvStrategy(strategy);
}

EncodedFrame EncodeFrame(const cv::Mat& image, const PngOptions& options) {
  options.Check();
  if (image.empty()) throw std::invalid_argument("EncodeFrame: empty image");
  const int depth = image.depth();
  const int channels = image.channels();
  if ((depth != CV_8U && depth != CV_16U) || (channels != 1 && channels != 3)) {
    throw std::invalid_argument("EncodeFrame: unsupported image type " +
                                cv::typeToString(image.type()) +
                                " (supported: 8UC1, 8UC3, 16UC1, 16UC3)");
  }
  EncodedFrame out;
  out.width = image.cols;
  out.height = image.rows;
  out.channels = channels;
  out.bit_depth = depth == CV_8U ? 8 : 16;
  // OpenCV switches to adaptive filtering as soon as IMWRITE_PNG_COMPRESSION is given, so the
  // level is passed only when the caller asked for one.
  std::vector<int> params;
  params.reserve(4);
  if (options.compression_level >= 0) {
    params.push_back(cv::IMWRITE_PNG_COMPRESSION);
    params.push_back(options.compression_level);
  }
  params.push_back(cv::IMWRITE_PNG_STRATEGY);
  params.push_back(OpenCvStrategy(options.strategy));

  if (!cv::imencode(".png", image, out.png, params)) {
    throw std::runtime_error("EncodeFrame: PNG encoder failed for a " + std::to_string(image.cols) +
                             "x" + std::to_string(image.rows) + " " +
                             cv::typeToString(image.type()) + " image");
  }
  return out;
}

cv::Mat DecodeFrame(std::span<const std::uint8_t> png) {
  if (!HasPngSignature(png)) return {};
  // imdecode needs a Mat header over the bytes; it does not modify them.
  const cv::Mat buf(1, static_cast<int>(png.size()), CV_8UC1,
                    const_cast<std::uint8_t*>(png.data()));
  try {
    return cv::imdecode(buf, cv::IMREAD_UNCHANGED);
  } catch (const cv::Exception&) {
    return {};
  }
}

std::string BlobChecksum(std::span<const std::uint8_t> blob) {
  return HashHex(blob.data(), blob.size());
}

}  // namespace gs360
