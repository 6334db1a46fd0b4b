#include "rig/rig_shape.h"

#include "geometry/bvh.h"

namespace gs360 {

RigShape BuildRigShape(const RigConfig& rig, const MeshLoadOptions& load) {
  rig.Check();
  RigShape out;
  if (rig.mesh_path.empty()) {
    out.profile = MakeProfile(rig.shape);
    out.profile_is_exact = true;
    out.gel = MakeRevolutionMesh(*out.profile, rig.shape.tessellation);
  } else {
    out.gel = LoadMesh(rig.mesh_path, load);
    if (!out.gel.HasNormals()) out.gel.ComputeVertexNormals();
    // The fins follow the inner wall; for a mesh, a profile inscribed in it.
    const Bvh bvh(out.gel);
    out.profile = MakeSplineProfile(FitInscribedProfile(bvh, 24));
  }
  out.fins = MakeFins(rig.fins, *out.profile);
  return out;
}

}  // namespace gs360
