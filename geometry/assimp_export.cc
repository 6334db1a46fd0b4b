#include "geometry/assimp_export.h"

#include <assimp/scene.h>

#include <assimp/Exporter.hpp>

namespace gs360::geometry_internal {

std::string ExportOneMesh(const std::filesystem::path& path, const char* format,
                          const std::function<void(aiMesh&)>& fill) {
  // The scene owns every array it points to (aiScene's destructor frees them with delete[]).
  aiScene scene;
  scene.mRootNode = new aiNode();
  scene.mRootNode->mNumMeshes = 1;
  scene.mRootNode->mMeshes = new unsigned int[1]{0};
  scene.mNumMaterials = 1;
  scene.mMaterials = new aiMaterial* [1] { new aiMaterial() };
  scene.mNumMeshes = 1;
  scene.mMeshes = new aiMesh* [1] { new aiMesh() };
  fill(*scene.mMeshes[0]);
  Assimp::Exporter exporter;
  if (exporter.Export(&scene, format, path.string()) == aiReturn_SUCCESS) return "";
  const std::string error = exporter.GetErrorString();
  return error.empty() ? std::string("assimp's exporter failed") : error;
}

}  // namespace gs360::geometry_internal
