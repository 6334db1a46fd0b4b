// libFuzzer target: the mesh loader (geometry/mesh.h) on STL, OBJ and PLY files. Contract: a
// broken mesh throws MeshError naming the file, also when assimp crashes on it (it runs in a child
// process). The first byte picks the file's extension.
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>

#include "geometry/mesh.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size == 0) return 0;
  static const char* const kExtensions[] = {".stl", ".obj", ".ply"};
  const std::filesystem::path path =
      std::filesystem::temp_directory_path() /
      ("gs360-fuzz-mesh-" + std::to_string(getpid()) + kExtensions[data[0] % 3]);
  {
    std::ofstream out(path, std::ios::binary | std::ios::trunc);
    out.write(reinterpret_cast<const char*>(data + 1), static_cast<std::streamsize>(size - 1));
  }
  gs360::MeshLoadOptions options;
  options.import_timeout_s = 5.0;  // a hang is this target's error, before libFuzzer's -timeout
  try {
    gs360::LoadMesh(path, options);
  } catch (const gs360::MeshError&) {
  }
  std::filesystem::remove(path);
  return 0;
}
