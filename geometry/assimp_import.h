#pragma once
// Internal to geometry/: a mesh file read through assimp's importer in a child process.
//
// Debian's assimp 5.2 crashes (a bus error in its post-processing) or never returns on some
// malformed files (found by tests/fuzz). A broken mesh from a user's configuration must be an
// error, not the end of gs360d: the child reads the file and sends back the triangles; a crash or
// a hang in it becomes a MeshError.

#include <filesystem>

#include "geometry/mesh.h"

namespace gs360::geometry_internal {

// Every face mesh of the file in one TriangleMesh, with the nodes' transforms applied; points and
// lines dropped, polygons split into fans, no normals, no validation. Throws MeshError naming the
// file when assimp cannot parse it, a face uses a vertex past its mesh's, the importer crashes,
// or it has not finished after `timeout_s` seconds (the child is then killed).
TriangleMesh ImportMeshFile(const std::filesystem::path& path, double timeout_s);

}  // namespace gs360::geometry_internal
