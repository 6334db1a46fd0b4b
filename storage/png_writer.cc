#include "storage/png_writer.h"

#include <algorithm>
#include <array>
#include <cstdlib>
#include <cstring>
#include <queue>
#include <stdexcept>
#include <string>
#include <utility>

namespace gs360 {
namespace {

// ---- checksums ----

// CRC-32 as PNG uses it (reflected polynomial 0xEDB88320), slicing-by-8.
struct CrcTables {
  std::uint32_t t[8][256];
  CrcTables() {
    for (std::uint32_t i = 0; i < 256; ++i) {
      std::uint32_t c = i;
      for (int k = 0; k < 8; ++k) c = (c & 1) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
      t[0][i] = c;
    }
    for (int k = 1; k < 8; ++k) {
      for (int i = 0; i < 256; ++i) t[k][i] = (t[k - 1][i] >> 8) ^ t[0][t[k - 1][i] & 0xff];
    }
  }
};

std::uint32_t Load32Le(const std::uint8_t* p) {
  return std::uint32_t{p[0]} | std::uint32_t{p[1]} << 8 | std::uint32_t{p[2]} << 16 |
         std::uint32_t{p[3]} << 24;
}

std::uint32_t Crc32(const std::uint8_t* p, std::size_t n) {
  static const CrcTables kTables;
  const auto& t = kTables.t;
  std::uint32_t c = 0xffffffffu;
  for (; n >= 8; p += 8, n -= 8) {
    const std::uint32_t one = Load32Le(p) ^ c;
    const std::uint32_t two = Load32Le(p + 4);
    c = t[7][one & 0xff] ^ t[6][(one >> 8) & 0xff] ^ t[5][(one >> 16) & 0xff] ^ t[4][one >> 24] ^
        t[3][two & 0xff] ^ t[2][(two >> 8) & 0xff] ^ t[1][(two >> 16) & 0xff] ^ t[0][two >> 24];
  }
  for (; n > 0; --n) c = t[0][(c ^ *p++) & 0xff] ^ (c >> 8);
  return c ^ 0xffffffffu;
}

std::uint32_t Adler32(const std::uint8_t* p, std::size_t n) {
  constexpr std::uint32_t kMod = 65521;
  constexpr std::size_t kBlock = 5552;  // largest n with no 32-bit overflow before the modulo
  std::uint32_t a = 1, b = 0;
  while (n > 0) {
    const std::size_t m = std::min(n, kBlock);
    for (std::size_t i = 0; i < m; ++i) {
      a += p[i];
      b += a;
    }
    a %= kMod;
    b %= kMod;
    p += m;
    n -= m;
  }
  return b << 16 | a;
}

// ---- Huffman codes ----

// Code lengths for `freq` (a zero frequency gets length 0), at most `limit` bits, forming a
// complete prefix code (as inflate requires). Frequencies are halved until the tree fits.
template <std::size_t N>
std::array<std::uint8_t, N> HuffmanLengths(std::array<std::uint32_t, N> freq, int limit) {
  std::array<std::uint8_t, N> len{};
  int used = 0;
  for (std::uint32_t f : freq) used += f > 0;
  if (used < 2) {
    // One symbol (or none): pair it with another so that the code is complete.
    std::size_t a = 0;
    while (a < N && freq[a] == 0) ++a;
    if (a == N) a = 0;
    len[a] = 1;
    len[a == 0 ? 1 : 0] = 1;
    return len;
  }
  for (;;) {
    // Nodes 0..N-1 are leaves, N.. internal; parent[] gives the tree.
    std::vector<std::int32_t> parent(2 * N, -1);
    using Item = std::pair<std::uint64_t, std::int32_t>;
    std::priority_queue<Item, std::vector<Item>, std::greater<>> heap;
    for (std::size_t s = 0; s < N; ++s) {
      if (freq[s] > 0) heap.emplace(freq[s], static_cast<std::int32_t>(s));
    }
    std::int32_t next = static_cast<std::int32_t>(N);
    while (heap.size() > 1) {
      const Item x = heap.top();
      heap.pop();
      const Item y = heap.top();
      heap.pop();
      parent[x.second] = next;
      parent[y.second] = next;
      heap.emplace(x.first + y.first, next++);
    }
    int max_len = 0;
    for (std::size_t s = 0; s < N; ++s) {
      if (freq[s] == 0) continue;
      int depth = 0;
      for (std::int32_t v = static_cast<std::int32_t>(s); parent[v] >= 0; v = parent[v]) ++depth;
      len[s] = static_cast<std::uint8_t>(depth);
      max_len = std::max(max_len, depth);
    }
    if (max_len <= limit) return len;
    for (std::uint32_t& f : freq) {
      if (f > 0) f = (f >> 1) | 1;
    }
  }
}

// Canonical codes (RFC 1951 3.2.2), bit-reversed because deflate sends codes MSB first into an
// LSB-first bit stream.
template <std::size_t N>
std::array<std::uint16_t, N> CanonicalCodes(const std::array<std::uint8_t, N>& len) {
  std::array<std::uint16_t, 16> count{}, next{};
  for (std::uint8_t l : len) ++count[l];
  count[0] = 0;
  std::uint16_t code = 0;
  for (int bits = 1; bits < 16; ++bits) {
    code = static_cast<std::uint16_t>((code + count[bits - 1]) << 1);
    next[bits] = code;
  }
  std::array<std::uint16_t, N> codes{};
  for (std::size_t s = 0; s < N; ++s) {
    const int l = len[s];
    if (l == 0) continue;
    std::uint16_t c = next[l]++, r = 0;
    for (int i = 0; i < l; ++i, c >>= 1) r = static_cast<std::uint16_t>((r << 1) | (c & 1));
    codes[s] = r;
  }
  return codes;
}

// LSB-first bit writer into a buffer sized by the caller.
class BitWriter {
 public:
  explicit BitWriter(std::uint8_t* out) : out_(out) {}
  void Put(std::uint32_t bits, int n) {
    acc_ |= std::uint64_t{bits} << n_;
    n_ += n;
    if (n_ >= 32) {
      const auto w = static_cast<std::uint32_t>(acc_);
      out_[0] = static_cast<std::uint8_t>(w);
      out_[1] = static_cast<std::uint8_t>(w >> 8);
      out_[2] = static_cast<std::uint8_t>(w >> 16);
      out_[3] = static_cast<std::uint8_t>(w >> 24);
      out_ += 4;
      acc_ >>= 32;
      n_ -= 32;
    }
  }
  // Pads to a byte boundary; returns the end of the written bytes.
  std::uint8_t* Finish() {
    while (n_ > 0) {
      *out_++ = static_cast<std::uint8_t>(acc_);
      acc_ >>= 8;
      n_ -= 8;
    }
    n_ = 0;
    return out_;
  }

 private:
  std::uint8_t* out_;
  std::uint64_t acc_ = 0;
  int n_ = 0;
};

void Put32Be(std::uint8_t* p, std::uint32_t v) {
  p[0] = static_cast<std::uint8_t>(v >> 24);
  p[1] = static_cast<std::uint8_t>(v >> 16);
  p[2] = static_cast<std::uint8_t>(v >> 8);
  p[3] = static_cast<std::uint8_t>(v);
}

// ---- filtering ----

int Paeth(int a, int b, int c) {
  const int p = a + b - c;
  const int pa = std::abs(p - a), pb = std::abs(p - b), pc = std::abs(p - c);
  if (pa <= pb && pa <= pc) return a;
  return pb <= pc ? b : c;
}

// Filters one row (`cur`, the previous row `prev` or zeros) into out[0..n) after the type byte.
void FilterRow(PngFilter filter, const std::uint8_t* cur, const std::uint8_t* prev, std::size_t n,
               std::size_t bpp, std::uint8_t* out) {
  switch (filter) {
    case PngFilter::kNone:
      std::memcpy(out, cur, n);
      break;
    case PngFilter::kSub:
      for (std::size_t i = 0; i < bpp; ++i) out[i] = cur[i];
      for (std::size_t i = bpp; i < n; ++i)
        out[i] = static_cast<std::uint8_t>(cur[i] - cur[i - bpp]);
      break;
    case PngFilter::kUp:
      for (std::size_t i = 0; i < n; ++i) out[i] = static_cast<std::uint8_t>(cur[i] - prev[i]);
      break;
    case PngFilter::kAverage:
      for (std::size_t i = 0; i < bpp; ++i)
        out[i] = static_cast<std::uint8_t>(cur[i] - (prev[i] >> 1));
      for (std::size_t i = bpp; i < n; ++i) {
        out[i] = static_cast<std::uint8_t>(cur[i] - ((cur[i - bpp] + prev[i]) >> 1));
      }
      break;
    case PngFilter::kPaeth:
      for (std::size_t i = 0; i < bpp; ++i) out[i] = static_cast<std::uint8_t>(cur[i] - prev[i]);
      for (std::size_t i = bpp; i < n; ++i) {
        out[i] = static_cast<std::uint8_t>(cur[i] - Paeth(cur[i - bpp], prev[i], prev[i - bpp]));
      }
      break;
  }
}

// One image row as PNG stores it: RGB order, 16-bit samples big-endian.
void RowBytes(const cv::Mat& image, int y, std::uint8_t* out) {
  const int channels = image.channels();
  const int width = image.cols;
  if (image.depth() == CV_8U) {
    const std::uint8_t* src = image.ptr<std::uint8_t>(y);
    if (channels == 1) {
      std::memcpy(out, src, static_cast<std::size_t>(width));
    } else {
      for (int x = 0; x < width; ++x, src += 3, out += 3) {
        out[0] = src[2];
        out[1] = src[1];
        out[2] = src[0];
      }
    }
  } else {
    const std::uint16_t* src = image.ptr<std::uint16_t>(y);
    for (int x = 0; x < width; ++x, src += channels) {
      for (int c = 0; c < channels; ++c) {
        const std::uint16_t v = src[channels == 3 ? 2 - c : c];
        *out++ = static_cast<std::uint8_t>(v >> 8);
        *out++ = static_cast<std::uint8_t>(v);
      }
    }
  }
}

constexpr std::array<int, 19> kCodeLengthOrder = {16, 17, 18, 0, 8,  7, 9,  6, 10, 5,
                                                  11, 4,  12, 3, 13, 2, 14, 1, 15};

}  // namespace

std::vector<std::uint8_t> WritePng(const cv::Mat& image, PngFilter filter) {
  if (image.empty()) throw std::invalid_argument("WritePng: empty image");
  const int depth = image.depth(), channels = image.channels();
  if ((depth != CV_8U && depth != CV_16U) || (channels != 1 && channels != 3)) {
    throw std::invalid_argument("WritePng: unsupported image type " +
                                cv::typeToString(image.type()));
  }
  const std::size_t width = static_cast<std::size_t>(image.cols);
  const std::size_t height = static_cast<std::size_t>(image.rows);
  const std::size_t bpp = static_cast<std::size_t>(channels) * (depth == CV_16U ? 2 : 1);
  const std::size_t row_bytes = width * bpp;
  const std::size_t stride = row_bytes + 1;
  if (stride * height > (std::size_t{1} << 30)) {
    throw std::invalid_argument("WritePng: image too large for one IDAT chunk (" +
                                std::to_string(width) + "x" + std::to_string(height) + ")");
  }

  // 1. Filtered scanlines (the zlib payload), with their byte histogram.
  std::vector<std::uint8_t> filtered(stride * height);
  std::vector<std::uint8_t> rows(2 * row_bytes, 0);
  std::uint8_t* prev = rows.data();
  std::uint8_t* cur = rows.data() + row_bytes;
  std::array<std::uint32_t, 257> freq{};
  for (std::size_t y = 0; y < height; ++y) {
    RowBytes(image, static_cast<int>(y), cur);
    std::uint8_t* out = filtered.data() + y * stride;
    out[0] = static_cast<std::uint8_t>(filter);
    FilterRow(filter, cur, prev, row_bytes, bpp, out + 1);
    std::swap(prev, cur);
  }
  {
    // Four interleaved histograms avoid stalls on repeated symbols.
    std::array<std::array<std::uint32_t, 256>, 4> h{};
    const std::uint8_t* p = filtered.data();
    const std::size_t n = filtered.size();
    std::size_t i = 0;
    for (; i + 4 <= n; i += 4) {
      ++h[0][p[i]];
      ++h[1][p[i + 1]];
      ++h[2][p[i + 2]];
      ++h[3][p[i + 3]];
    }
    for (; i < n; ++i) ++h[0][p[i]];
    for (int s = 0; s < 256; ++s) freq[s] = h[0][s] + h[1][s] + h[2][s] + h[3][s];
  }
  freq[256] = 1;  // end of block

  // 2. Codes: literals + end of block; two 1-bit distance codes (never used; zlib does the same
  // so that every inflater accepts the block).
  const std::array<std::uint8_t, 257> lit_len = HuffmanLengths(freq, 15);
  const std::array<std::uint16_t, 257> lit_code = CanonicalCodes(lit_len);
  std::array<std::uint8_t, 259> all_lengths{};
  std::copy(lit_len.begin(), lit_len.end(), all_lengths.begin());
  all_lengths[257] = 1;
  all_lengths[258] = 1;
  std::array<std::uint32_t, 19> cl_freq{};
  for (std::uint8_t l : all_lengths) ++cl_freq[l];
  const std::array<std::uint8_t, 19> cl_len = HuffmanLengths(cl_freq, 7);
  const std::array<std::uint16_t, 19> cl_code = CanonicalCodes(cl_len);

  // 3. The PNG: signature, IHDR, one IDAT (zlib header, one deflate block, Adler-32), IEND.
  const std::size_t bound =
      8 + 25 + 12 + 2 + 64 + 259 * 7 / 8 + filtered.size() * 15 / 8 + 4 + 12 + 16;
  std::vector<std::uint8_t> png(bound);
  std::uint8_t* p = png.data();
  static constexpr std::uint8_t kSignature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  std::memcpy(p, kSignature, 8);
  p += 8;
  // IHDR
  Put32Be(p, 13);
  std::memcpy(p + 4, "IHDR", 4);
  Put32Be(p + 8, static_cast<std::uint32_t>(width));
  Put32Be(p + 12, static_cast<std::uint32_t>(height));
  p[16] = depth == CV_16U ? 16 : 8;
  p[17] = channels == 3 ? 2 : 0;  // colour type: truecolour or greyscale
  p[18] = p[19] = p[20] = 0;      // deflate, adaptive filtering, no interlace
  Put32Be(p + 21, Crc32(p + 4, 17));
  p += 25;
  // IDAT
  std::uint8_t* idat = p;
  std::memcpy(p + 4, "IDAT", 4);
  p += 8;
  *p++ = 0x78;  // zlib: deflate, 32K window
  *p++ = 0x01;  // no dictionary, fastest; (0x78 * 256 + 0x01) % 31 == 0
  BitWriter bits(p);
  bits.Put(1, 1);   // BFINAL
  bits.Put(2, 2);   // BTYPE = dynamic Huffman
  bits.Put(0, 5);   // HLIT: 257 literal/length codes
  bits.Put(1, 5);   // HDIST: 2 distance codes
  bits.Put(15, 4);  // HCLEN: 19 code length codes
  for (int s : kCodeLengthOrder) bits.Put(cl_len[s], 3);
  for (std::uint8_t l : all_lengths) bits.Put(cl_code[l], cl_len[l]);
  for (const std::uint8_t b : filtered) bits.Put(lit_code[b], lit_len[b]);
  bits.Put(lit_code[256], lit_len[256]);
  p = bits.Finish();
  Put32Be(p, Adler32(filtered.data(), filtered.size()));
  p += 4;
  const std::size_t idat_len = static_cast<std::size_t>(p - (idat + 8));
  Put32Be(idat, static_cast<std::uint32_t>(idat_len));
  Put32Be(p, Crc32(idat + 4, idat_len + 4));
  p += 4;
  // IEND
  Put32Be(p, 0);
  std::memcpy(p + 4, "IEND", 4);
  Put32Be(p + 8, Crc32(p + 4, 4));
  p += 12;
  png.resize(static_cast<std::size_t>(p - png.data()));
  return png;
}

}  // namespace gs360
