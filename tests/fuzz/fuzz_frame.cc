// libFuzzer target: the stored-frame decoder (storage/frame_codec.h). Contract: bytes that are
// not a decodable PNG give an empty image, never an exception or a crash; what decodes is 8- or
// 16-bit with 1, 3 or 4 channels.
#include <cstddef>
#include <cstdint>
#include <span>

#include <opencv2/core.hpp>

#include "storage/frame_codec.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const cv::Mat image = gs360::DecodeFrame(std::span<const std::uint8_t>(data, size));
  if (!image.empty() && (image.channels() < 1 || image.channels() > 4)) __builtin_trap();
  return 0;
}
