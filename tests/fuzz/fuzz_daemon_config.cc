// libFuzzer target: gs360d's TOML configuration loader (daemon/daemon_config.h), with the run,
// rig and plan sections it contains. Contract: bad text throws ConfigError (naming the file,
// line and key); anything else escaping, or a crash, is a bug.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "base/json_reader.h"
#include "daemon/daemon_config.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  try {
    const gs360::DaemonConfig config =
        gs360::DaemonConfigFromToml(text, "fuzz.toml", "/nonexistent");
    // What loads must write back and load again.
    gs360::DaemonConfigFromToml(gs360::DaemonConfigToToml(config), "fuzz-again.toml",
                                "/nonexistent");
  } catch (const gs360::ConfigError&) {
  }
  return 0;
}
