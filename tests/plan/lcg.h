#pragma once
// A tiny seeded generator for the plan tests' random cases (portable, no <random> state).

#include <cstdint>

namespace gs360::test {

struct Lcg {
  std::uint64_t s;
  double Uniform() {  // in [0, 1)
    s = s * 6364136223846793005ull + 1442695040888963407ull;
    return static_cast<double>(s >> 11) * 0x1.0p-53;
  }
};

}  // namespace gs360::test
