#include "base/hash.h"

#include <cstring>

namespace gs360 {
namespace {
constexpr std::uint64_t kPrime = 0x100000001b3ull;

// Final avalanche (splitmix64) so that nearby inputs give unrelated digests.
std::uint64_t Mix(std::uint64_t z) {
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}
}  // namespace

Hasher& Hasher::Add(const void* data, std::size_t size) {
  const auto* p = static_cast<const unsigned char*>(data);
  std::size_t i = 0;
  std::uint64_t h = state_;
  for (; i + 8 <= size; i += 8) {
    std::uint64_t w;
    std::memcpy(&w, p + i, 8);
    h = (h ^ w) * kPrime;
    h ^= h >> 29;
  }
  for (; i < size; ++i) h = (h ^ p[i]) * kPrime;
  state_ = h;
  length_ += size;
  return *this;
}

Hasher& Hasher::Add(std::string_view s) {
  // Length first, so that ("ab","c") and ("a","bc") differ.
  const std::uint64_t n = s.size();
  Add(&n, sizeof(n));
  return Add(s.data(), s.size());
}

Hasher& Hasher::AddDouble(double v) {
  if (v == 0.0) v = 0.0;
  return Add(&v, sizeof(v));
}

std::uint64_t Hasher::Digest() const {
  return Mix(state_ ^ length_);
}

std::string Hasher::Hex() const {
  return ToHex64(Digest());
}

std::string ToHex64(std::uint64_t v) {
  static constexpr char kDigits[] = "0123456789abcdef";
  std::string s(16, '0');
  for (int i = 15; i >= 0; --i, v >>= 4) s[i] = kDigits[v & 0xf];
  return s;
}

std::string HashHex(const void* data, std::size_t size) {
  return Hasher().Add(data, size).Hex();
}

}  // namespace gs360
