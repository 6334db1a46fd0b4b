#pragma once
// Small, portable, seeded random numbers for the simulated tactile camera (no std distributions,
// whose output differs between standard libraries): SplitMix64 for integers, 53-bit uniforms,
// Box-Muller normals. Identical sequences on every platform for a given seed.

#include <cmath>
#include <cstdint>
#include <numbers>

namespace gs360 {

// SplitMix64 (Steele, Lea, Flood 2014): passes BigCrush, one 64-bit state, any seed is fine.
class SimRandom {
 public:
  explicit SimRandom(std::uint64_t seed) : state_(seed) {}

  std::uint64_t NextU64() {
    std::uint64_t z = (state_ += 0x9e3779b97f4a7c15ull);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
  }
  // Uniform in [0, 1).
  double Uniform() { return static_cast<double>(NextU64() >> 11) * 0x1.0p-53; }
  // Uniform in [lo, hi).
  double Uniform(double lo, double hi) { return lo + (hi - lo) * Uniform(); }
  // +1 or -1 with equal probability.
  double Sign() { return (NextU64() >> 63) != 0 ? 1.0 : -1.0; }
  // Standard normal (Box-Muller; the second value of each pair is kept for the next call).
  double Normal() {
    if (has_spare_) {
      has_spare_ = false;
      return spare_;
    }
    double u1 = Uniform();
    while (u1 <= 0.0) u1 = Uniform();
    const double u2 = Uniform();
    const double radius = std::sqrt(-2.0 * std::log(u1));
    const double angle = 2.0 * std::numbers::pi * u2;
    spare_ = radius * std::sin(angle);
    has_spare_ = true;
    return radius * std::cos(angle);
  }

 private:
  std::uint64_t state_;
  double spare_ = 0.0;
  bool has_spare_ = false;
};

// Stateless 64-bit mix of two values (for per-frame and per-pixel seeds).
inline std::uint64_t MixSeed(std::uint64_t a, std::uint64_t b) {
  SimRandom r(a ^ (b * 0xd1b54a32d192ed03ull + 0x8cb92ba72f3d8dd7ull));
  r.NextU64();
  return r.NextU64();
}

}  // namespace gs360
