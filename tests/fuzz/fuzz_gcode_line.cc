// libFuzzer target: the virtual firmware's G-code line parser (sim/grbl_gcode.h), GRBL's own
// steps 1-3. Contract: any line gives a status code (0 or a GRBL error), never a crash.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "sim/grbl_gcode.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view line(reinterpret_cast<const char*>(data), size);
  const gs360::GcodeState state;
  const gs360::CoordinateData coords;
  gs360::GcodeBlock block;
  gs360::ParseGcodeLine(line, state, coords, &block);
  std::size_t pos = 0;
  double value = 0.0;
  gs360::ReadGrblFloat(line, pos, value);
  return 0;
}
