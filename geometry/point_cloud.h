#pragma once
// Point clouds on disk: binary little-endian PLY through assimp's exporter, readable by
// MeshLab, CloudCompare, Open3D and assimp itself.

#include <filesystem>
#include <span>
#include <stdexcept>

#include <Eigen/Core>

namespace gs360 {

class PointCloudError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Writes `points` (any frame; the caller says which, mm) as vertices, each also a one-index
// face (assimp's exporter wants every vertex in a primitive; readers take them as points).
// Throws PointCloudError naming the path for an empty cloud or when assimp cannot write it.
void WritePointCloudPly(const std::filesystem::path& path, std::span<const Eigen::Vector3f> points);

}  // namespace gs360
