// libFuzzer target: the model bundle reader (recon/model_bundle.h), what `gs360 recon` and the
// Python module load. Contract: a truncated, corrupt or foreign file throws ModelBundleError.
// Half the inputs get their checksum appended, so that the fuzzer reaches the chunks behind it.
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "base/hash.h"
#include "recon/model_bundle.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size == 0) return 0;
  std::vector<std::uint8_t> bytes(data + 1, data + size);
  if (data[0] & 1) {
    const std::string sum = gs360::HashHex(bytes.data(), bytes.size());
    bytes.insert(bytes.end(), sum.begin(), sum.end());
  }
  try {
    gs360::DeserializeModelBundle(bytes, "fuzz.gs360model");
  } catch (const gs360::ModelBundleError&) {
  }
  return 0;
}
