#include "base/format.h"

#include <charconv>
#include <cmath>
#include <cstdio>
#include <stdexcept>

namespace gs360 {

std::string FormatFixed(double value, int decimals) {
  char buf[64];
  const auto [ptr, ec] =
      std::to_chars(buf, buf + sizeof(buf), value, std::chars_format::fixed, decimals);
  if (ec != std::errc()) throw std::invalid_argument("FormatFixed: value out of range");
  std::string s(buf, ptr);
  if (s[0] == '-' && s.find_first_not_of("-0.") == std::string::npos) s.erase(0, 1);
  return s;
}

std::string FormatDuration(double s) {
  if (!(s >= 0.0) || !std::isfinite(s)) return "--";
  const long long t = std::llround(s);
  char buf[32];
  if (t >= 3600) {
    std::snprintf(buf, sizeof buf, "%lldh %02lldm", t / 3600, (t / 60) % 60);
  } else if (t >= 60) {
    std::snprintf(buf, sizeof buf, "%lldm %02llds", t / 60, t % 60);
  } else {
    std::snprintf(buf, sizeof buf, "%llds", t);
  }
  return buf;
}

}  // namespace gs360
