#include "geometry/point_cloud.h"

#include <assimp/scene.h>

#include <string>

#include "geometry/assimp_export.h"

namespace gs360 {

void WritePointCloudPly(const std::filesystem::path& path,
                        std::span<const Eigen::Vector3f> points) {
  if (points.empty()) throw PointCloudError(path.string() + ": no points to write");
  auto fill = [&](aiMesh& mesh) {
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
  };
  const std::string error = geometry_internal::ExportOneMesh(path, "plyb", fill);
  if (!error.empty()) {
    throw PointCloudError(path.string() + ": cannot write the point cloud: " + error);
  }
}

}  // namespace gs360
