#pragma once
// Base64 (RFC 4648, the standard alphabet, with padding): PNG frames in HTML reports and in
// JSON notifications.

#include <cstdint>
#include <span>
#include <string>

namespace gs360 {

std::string Base64Encode(std::span<const std::uint8_t> data);

}  // namespace gs360
