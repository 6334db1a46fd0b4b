#pragma once
// Content hashing for cache keys (stage artifacts, mesh identity) and blob checksums.
// 64-bit FNV-1a processed 8 bytes per step (a word-wise variant, not byte-compatible with plain
// FNV-1a): fast enough for PNG blobs, deterministic across runs and platforms of the same
// endianness. Not cryptographic: it guards against corruption and stale caches, not adversaries.

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <type_traits>

namespace gs360 {

class Hasher {
 public:
  Hasher& Add(const void* data, std::size_t size);
  Hasher& Add(std::string_view s);
  // Hashes the value's bit pattern; -0.0 and 0.0 are folded together so that equal numbers
  // give equal keys.
  Hasher& AddDouble(double v);
  template <typename T>
  requires std::is_trivially_copyable_v<T> Hasher& AddPod(const T& v) { return Add(&v, sizeof(T)); }

  std::uint64_t Digest() const;
  // 16 lower-case hex digits.
  std::string Hex() const;

 private:
  std::uint64_t state_ = 0xcbf29ce484222325ull;
  std::uint64_t length_ = 0;
};

std::string HashHex(const void* data, std::size_t size);
std::string ToHex64(std::uint64_t v);

}  // namespace gs360
