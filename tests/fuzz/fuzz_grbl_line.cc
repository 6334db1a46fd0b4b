// libFuzzer target: the GRBL response and status-report parser (gcode/grbl_messages.h), which
// reads whatever the serial line delivers. Contract: never throws, never crashes; the sanitised
// line is printable ASCII.
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "gcode/grbl_messages.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  const std::string clean = gs360::SanitizeGrblLine(bytes);
  for (char c : clean) {
    if (c < 0x20 || c > 0x7e) __builtin_trap();
  }
  gs360::ParseGrblLine(bytes);
  const gs360::GrblMessage m = gs360::ParseGrblLine(clean);
  gs360::GrblMessageKindName(m.kind);
  return 0;
}
