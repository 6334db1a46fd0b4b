#pragma once
// Numbers and durations as text, the same in every module and in every locale.

#include <string>

namespace gs360 {

// Fixed decimals (3 for mm), locale-independent (std::to_chars); "-0.000" is written "0.000".
// Throws std::invalid_argument when the value does not fit (not finite, or beyond 60 digits).
std::string FormatFixed(double value, int decimals);

// A duration for people: "1h 02m", "3m 20s", "12s"; "--" when negative or not finite.
std::string FormatDuration(double seconds);

}  // namespace gs360
