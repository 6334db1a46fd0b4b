#include "base/text.h"

#include <cstdint>
#include <cstdio>

namespace gs360 {
namespace {

// One decoded character: its code point and byte length; length 0 for an invalid sequence
// (overlong, surrogate, beyond U+10FFFF, truncated).
struct Decoded {
  std::uint32_t code = 0;
  std::size_t length = 0;
};

Decoded DecodeUtf8(std::string_view s, std::size_t at) {
  const auto byte = [&](std::size_t i) { return static_cast<unsigned char>(s[i]); };
  const unsigned char b0 = byte(at);
  if (b0 < 0x80) return {b0, 1};
  std::size_t n = 0;
  std::uint32_t code = 0, min = 0;
  if ((b0 & 0xE0) == 0xC0) {
    n = 2, code = b0 & 0x1F, min = 0x80;
  } else if ((b0 & 0xF0) == 0xE0) {
    n = 3, code = b0 & 0x0F, min = 0x800;
  } else if ((b0 & 0xF8) == 0xF0) {
    n = 4, code = b0 & 0x07, min = 0x10000;
  } else {
    return {};
  }
  if (at + n > s.size()) return {};
  for (std::size_t i = 1; i < n; ++i) {
    if ((byte(at + i) & 0xC0) != 0x80) return {};
    code = (code << 6) | (byte(at + i) & 0x3F);
  }
  if (code < min || code > 0x10FFFF || (code >= 0xD800 && code <= 0xDFFF)) return {};
  return {code, n};
}

bool IsControl(std::uint32_t c) {
  return c < 0x20 || (c >= 0x7F && c <= 0x9F) || (c >= 0x202A && c <= 0x202E) ||
         (c >= 0x2066 && c <= 0x2069);
}

std::string Hex(const char* format, unsigned value) {
  char buf[16];
  std::snprintf(buf, sizeof buf, format, value);
  return buf;
}

}  // namespace

std::string PrintableTextProblem(std::string_view text, std::size_t max_chars) {
  std::size_t chars = 0;
  for (std::size_t at = 0; at < text.size();) {
    const Decoded d = DecodeUtf8(text, at);
    if (d.length == 0) return "invalid UTF-8 at byte " + std::to_string(at + 1);
    ++chars;
    if (IsControl(d.code)) {
      return "control character " + Hex("U+%04X", d.code) + " at character " +
             std::to_string(chars);
    }
    at += d.length;
  }
  if (chars > max_chars) return std::to_string(chars) + " characters";
  return "";
}

std::string EscapeControlCharacters(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  for (std::size_t at = 0; at < text.size();) {
    const Decoded d = DecodeUtf8(text, at);
    if (d.length == 0) {
      out += Hex("\\x%02x", static_cast<unsigned char>(text[at]));
      ++at;
      continue;
    }
    const std::string_view raw = text.substr(at, d.length);
    at += d.length;
    if (d.code == '\\') {
      out += "\\\\";
    } else if (!IsControl(d.code)) {
      out += raw;
    } else if (d.code == 0x1B) {
      out += "\\e";
    } else if (d.code == '\n') {
      out += "\\n";
    } else if (d.code == '\t') {
      out += "\\t";
    } else if (d.code == '\r') {
      out += "\\r";
    } else if (d.code < 0x80) {
      out += Hex("\\x%02x", d.code);
    } else {
      out += Hex("\\u{%04x}", d.code);
    }
  }
  return out;
}

}  // namespace gs360
