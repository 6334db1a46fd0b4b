#pragma once
// A fast, standard PNG writer for sensor frames (used by EncodeFrame's built-in encoder).
//
// Sensor frames are smooth fields plus noise: after a PNG row filter what remains is mostly
// noise, which string matching cannot compress. So this writer applies one filter to every row
// and codes the filtered bytes with a single dynamic-Huffman deflate block, literals only (what
// zlib's Z_HUFFMAN_ONLY does, without libpng's and zlib's per-byte overheads). The output is an
// ordinary PNG (IHDR, one IDAT, IEND; CRC-32 and Adler-32 checked by every decoder). On images
// with large flat areas it compresses worse than zlib (at best 1 bit per byte).

#include <cstdint>
#include <vector>

#include <opencv2/core/mat.hpp>

namespace gs360 {

// PNG row filters (PNG spec section 9.2); one is applied to every row.
enum class PngFilter { kNone = 0, kSub = 1, kUp = 2, kAverage = 3, kPaeth = 4 };

// Encodes `image` (CV_8UC1, CV_8UC3, CV_16UC1 or CV_16UC3; 3 channels in OpenCV's BGR order,
// written as PNG RGB). Throws std::invalid_argument for an empty image or another type.
std::vector<std::uint8_t> WritePng(const cv::Mat& image, PngFilter filter);

}  // namespace gs360
