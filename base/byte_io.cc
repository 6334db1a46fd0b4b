#include "base/byte_io.h"

#include <algorithm>
#include <cstring>
#include <iterator>
#include <stdexcept>

namespace gs360 {

bool HasPngSignature(std::span<const std::uint8_t> bytes) {
  static constexpr std::uint8_t kSignature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  return bytes.size() >= sizeof(kSignature) &&
         std::equal(std::begin(kSignature), std::end(kSignature), bytes.begin());
}

void ByteWriter::Bytes(const void* data, std::size_t n) {
  if (n == 0) return;
  const auto* p = static_cast<const std::uint8_t*>(data);
  bytes_.insert(bytes_.end(), p, p + n);
}

void ByteReader::Bytes(void* out, std::size_t n, const char* what) {
  if (n > remaining()) {
    throw std::runtime_error(context_ + ": truncated input: " + what + " needs " +
                             std::to_string(n) + " bytes at offset " + std::to_string(pos_) +
                             ", only " + std::to_string(remaining()) + " left");
  }
  if (n > 0) std::memcpy(out, bytes_.data() + pos_, n);
  pos_ += n;
}

}  // namespace gs360
