#include "base/field_error.h"

#include <charconv>
#include <cmath>
#include <stdexcept>

namespace gs360 {

std::string FieldErrorMessage(std::string_view field, double value, std::string_view rule) {
  std::string text;
  if (std::isnan(value)) {
    text = "nan";
  } else if (std::isinf(value)) {
    text = value > 0 ? "inf" : "-inf";
  } else {
    char buf[32];
    const auto [end, ec] = std::to_chars(buf, buf + sizeof(buf), value);
    text.assign(buf, ec == std::errc() ? end : buf);
  }
  std::string out(field);
  out.append(" ").append(rule).append(", got ").append(text);
  return out;
}

void ThrowFieldError(std::string_view field, double value, std::string_view rule) {
  throw std::invalid_argument(FieldErrorMessage(field, value, rule));
}

}  // namespace gs360
