#include "geometry/point_cloud.h"

#include <assimp/scene.h>

#include <assimp/Exporter.hpp>
#include <string>

namespace gs360 {

void WritePointCloudPly(const std::filesystem::path& path,
                        std::span<const Eigen::Vector3f> points) {
  if (points.empty()) throw PointCloudError(path.string() + ": no points to write");
  // The scene owns its arrays (aiScene's destructor frees them with delete[]).
  aiScene scene;
  scene.mRootNode = new aiNode();
  scene.mRootNode->mNumMeshes = 1;
  scene.mRootNode->mMeshes = new unsigned int[1]{0};
  scene.mNumMaterials = 1;
  scene.mMaterials = new aiMaterial* [1] { new aiMaterial() };
  scene.mNumMeshes = 1;
  scene.mMeshes = new aiMesh* [1] { new aiMesh() };
  aiMesh& mesh = *scene.mMeshes[0];
  mesh.mPrimitiveTypes = aiPrimitiveType_POINT;
  mesh.mNumVertices = static_cast<unsigned int>(points.size());
  mesh.mVertices = new aiVector3D[points.size()];
  // assimp's exporters want every vertex in a primitive: one single-index face per point.
  mesh.mNumFaces = mesh.mNumVertices;
  mesh.mFaces = new aiFace[points.size()];
  for (std::size_t i = 0; i < points.size(); ++i) {
    mesh.mVertices[i] = aiVector3D(points[i].x(), points[i].y(), points[i].z());
    mesh.mFaces[i].mNumIndices = 1;
    mesh.mFaces[i].mIndices = new unsigned int[1]{static_cast<unsigned int>(i)};
  }
  Assimp::Exporter exporter;
  if (exporter.Export(&scene, "plyb", path.string()) != aiReturn_SUCCESS) {
    throw PointCloudError(path.string() +
                          ": cannot write the point cloud: " + exporter.GetErrorString());
  }
}

}  // namespace gs360
