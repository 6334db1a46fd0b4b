#include "rig/rig_shape.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <string>

#include "geometry/bvh.h"

namespace gs360 {
namespace {

// A fingertip is millimetres to centimetres across. A mesh far outside that is almost always in
// other units (CAD exports in metres or inches); say so before the planner or the fins fail on it
// with a message about geometry.
void CheckFingerSize(const TriangleMesh& gel, const RigConfig& rig) {
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d hi = -lo;
  for (const Eigen::Vector3d& v : gel.vertices) {
    lo = lo.cwiseMin(v);
    hi = hi.cwiseMax(v);
  }
  const double extent = (hi - lo).maxCoeff();
  constexpr double kMinMm = 2.0, kMaxMm = 1000.0;
  if (extent >= kMinMm && extent <= kMaxMm) return;
  char buf[64], scale[64];
  std::snprintf(buf, sizeof buf, "%.4g", extent);
  std::snprintf(scale, sizeof scale, "%.6g", rig.mesh_scale);
  std::string hint = extent < kMinMm ? " (a file in metres needs mesh_scale = 1000)"
                                     : " (a file in micrometres needs mesh_scale = 0.001)";
  throw MeshError(
      rig.mesh_path + ": the sensor mesh spans " + buf + " mm after rig.mesh_scale = " + scale +
      "; a fingertip spans 2 to 1000 mm: set rig.mesh_scale to the file's unit in mm" + hint);
}

}  // namespace

RigShape BuildRigShape(const RigConfig& rig, const MeshLoadOptions& load) {
  rig.Check();
  RigShape out;
  if (rig.mesh_path.empty()) {
    out.profile = MakeProfile(rig.shape);
    out.profile_is_exact = true;
    out.gel = MakeRevolutionMesh(*out.profile, rig.shape.tessellation);
  } else {
    MeshLoadOptions scaled = load;
    scaled.scale *= rig.mesh_scale;
    out.gel = LoadMesh(rig.mesh_path, scaled);
    CheckFingerSize(out.gel, rig);
    out.base_faces_removed = RemoveBaseFaces(out.gel);
    if (out.gel.Empty()) {
      throw MeshError(rig.mesh_path +
                      ": the sensor mesh is only a flat base on the plane z = 0, with no finger "
                      "above it (+z must point along the finger)");
    }
    if (!out.gel.HasNormals()) out.gel.ComputeVertexNormals();
    // The fins follow the inner wall; for a mesh, a profile inscribed in it.
    const Bvh bvh(out.gel);
    out.profile = MakeSplineProfile(FitInscribedProfile(bvh, 24));
  }
  out.fin_options = rig.fins;
  if (!out.profile_is_exact && out.fin_options.enabled) {
    // A profile inscribed in a finger that is not round (a bent tip) narrows faster than any
    // board could follow: the boards end a millimetre below where their outline would fold.
    const double fold_z = FinFoldZ(out.fin_options, *out.profile);
    if (std::isfinite(fold_z)) {
      out.fin_options.top_z = std::min(out.fin_options.top_z, fold_z - kFinFoldMarginMm);
    }
  }
  out.fins = MakeFins(out.fin_options, *out.profile);
  return out;
}

}  // namespace gs360
