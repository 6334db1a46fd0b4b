#pragma once
// The exported depth model: everything run-time reconstruction needs, in one versioned,
// checksummed file (".gs360model"), independent of the run database.
//
// Contents: the fisheye intrinsics and cam_from_sensor found by calibration, the gel and fin
// meshes (sensor frame, mm) from which the surface map is rebuilt at load time (a few hundred
// kB instead of ~25 MB of per-pixel data), the surface-map options, the no-contact reference
// frame (PNG), the MLP (recon/mlp.h) and the reconstruction options, plus provenance metadata
// and the validation summary (JSON).
//
// File layout (little-endian): "GS360BDL" | u32 format version | u32 chunk count |
// chunks (u32 name length, name, u64 size, bytes) | 16 hex digits: FNV-1a 64 of everything
// before. Chunks: "meta.json", "gel_mesh", "fin_mesh", "reference.png", "mlp".
// A reader refuses a newer format version, a truncated file, a checksum mismatch or a missing
// chunk with ModelBundleError naming the file and the problem.

#include <cstdint>
#include <filesystem>
#include <memory>
#include <span>
#include <stdexcept>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core/mat.hpp>

#include "geometry/fisheye.h"
#include "geometry/mesh.h"
#include "geometry/rigid3.h"
#include "recon/mlp.h"
#include "recon/reconstructor.h"
#include "recon/surface_map.h"

namespace gs360 {

constexpr std::uint32_t kModelBundleFormat = 1;

class ModelBundleError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct ModelBundle {
  std::string name;     // e.g. the run's name
  std::string version;  // model version chosen by the user (e.g. "1")
  std::string gs360_version;
  double created_at = 0.0;  // Unix seconds
  std::string sensor;       // description: "cylinder", a mesh path...
  FisheyeIntrinsics intrinsics;
  Rigid3d cam_from_sensor;
  TriangleMesh gel_mesh;  // sensor frame
  TriangleMesh fin_mesh;  // sensor frame (may be empty)
  SurfaceMapOptions surface_map;
  cv::Mat reference;  // CV_8UC3, intrinsics.width x intrinsics.height
  Mlp mlp;
  ReconstructionOptions reconstruction;
  nlohmann::json metrics = nlohmann::json::object();  // validation summary, provenance

  // Rebuilds the surface map (BVHs over the meshes) and returns a ready reconstructor.
  Reconstructor MakeReconstructor(int threads = 2) const;
};

// The JSON forms the bundle's meta.json uses (also the calibration artifacts'). FromJson throws
// nlohmann::json exceptions for missing keys or wrong types.
nlohmann::json IntrinsicsToJson(const FisheyeIntrinsics& intrinsics);
FisheyeIntrinsics IntrinsicsFromJson(const nlohmann::json& json);
nlohmann::json PoseToJson(const Rigid3d& pose);  // quaternion qw qx qy qz, translation t (mm)
Rigid3d PoseFromJson(const nlohmann::json& json);

std::vector<std::uint8_t> SerializeModelBundle(const ModelBundle& bundle);
// `where` names the source (a file path) in error messages.
ModelBundle DeserializeModelBundle(std::span<const std::uint8_t> bytes, const std::string& where);
// Writes atomically (temporary file + rename) and returns the bytes written. Throws
// ModelBundleError naming the path.
std::vector<std::uint8_t> WriteModelBundle(const std::filesystem::path& path,
                                           const ModelBundle& bundle);
ModelBundle ReadModelBundle(const std::filesystem::path& path);

}  // namespace gs360
