#pragma once
// Small pieces of text handling that the firmwares' reply parsers share (grbl_messages.cc,
// marlin_messages.cc): prefixes, trimming, strict numbers. Internal to gcode/.

#include <charconv>
#include <optional>
#include <string_view>
#include <system_error>
#include <vector>

namespace gs360::reply_text {

inline bool StartsWith(std::string_view s, std::string_view p) {
  return s.substr(0, p.size()) == p;
}

inline bool EndsWith(std::string_view s, std::string_view p) {
  return s.size() >= p.size() && s.substr(s.size() - p.size()) == p;
}

inline std::string_view Trim(std::string_view s) {
  while (!s.empty() && s.front() == ' ') s.remove_prefix(1);
  while (!s.empty() && s.back() == ' ') s.remove_suffix(1);
  return s;
}

// The whole of `s` (spaces around it aside) as a number, or nothing: "12x" is not 12.
template <typename T>
std::optional<T> ParseNumber(std::string_view s) {
  s = Trim(s);
  if (s.empty()) return std::nullopt;
  // from_chars rejects a leading '+'; GRBL never sends one but other firmwares might.
  if (s.front() == '+') s.remove_prefix(1);
  T value{};
  const auto [ptr, ec] = std::from_chars(s.data(), s.data() + s.size(), value);
  if (ec != std::errc() || ptr != s.data() + s.size()) return std::nullopt;
  return value;
}

inline std::vector<std::string_view> Split(std::string_view s, char sep) {
  std::vector<std::string_view> parts;
  std::size_t start = 0;
  while (true) {
    const auto pos = s.find(sep, start);
    if (pos == std::string_view::npos) {
      parts.push_back(s.substr(start));
      return parts;
    }
    parts.push_back(s.substr(start, pos - start));
    start = pos + 1;
  }
}

}  // namespace gs360::reply_text
