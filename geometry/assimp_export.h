#pragma once
// Internal to geometry/: one mesh written through assimp's exporter, shared by the mesh and the
// point-cloud writers. assimp's types stay out of the public headers.

#include <filesystem>
#include <functional>
#include <string>

struct aiMesh;

namespace gs360::geometry_internal {

// Builds a scene of one mesh (one node, one default material), lets `fill` set the mesh's
// primitive types, vertices, normals and faces (arrays allocated with new[]: the scene frees
// them), and exports it to `path` in assimp's `format` ("stlb", "stl", "objnomtl", "ply",
// "plyb"). Returns assimp's error message, empty on success; throws only what `fill` throws.
std::string ExportOneMesh(const std::filesystem::path& path, const char* format,
                          const std::function<void(aiMesh&)>& fill);

}  // namespace gs360::geometry_internal
