#pragma once
// Angle constants shared by the tests: test files are compiled in unity batches
// (GS360_UNITY_TESTS), where two files' own copies of one constant would collide.
#include <numbers>

namespace gs360::test {

inline constexpr double kPi = std::numbers::pi;
inline constexpr double kDeg = std::numbers::pi / 180.0;  // radians per degree
inline constexpr double kRadToDeg = 180.0 / std::numbers::pi;

}  // namespace gs360::test
