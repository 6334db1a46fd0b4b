#pragma once
// The rig's solid parts built from its description: the gel's outer surface, the surface of
// revolution the fins are laid out on, and the fins. One builder for the planner
// (plan/plan.h MakeRigGeometry) and the virtual rig (sim/rig_model.h).
//
// Frame: sensor (mm). Throws MeshError (geometry/mesh.h) for a mesh file that cannot be used,
// std::invalid_argument for an invalid RigConfig or fins that do not fit the shape.

#include <memory>

#include "geometry/mesh.h"
#include "geometry/shapes.h"
#include "rig/rig_config.h"

namespace gs360 {

struct RigShape {
  TriangleMesh gel;  // outer gel surface, outward normals
  // The built-in shape's exact profile, or for a mesh a profile inscribed in it (good enough to
  // lay the fins along the inner wall, not to stand for the surface).
  std::shared_ptr<const RevolutionProfile> profile;
  bool profile_is_exact = false;  // true for a built-in shape
  TriangleMesh fins;              // both fins: triangles [0, n/2) xz (red), [n/2, n) yz (green)
};

RigShape BuildRigShape(const RigConfig& rig, const MeshLoadOptions& load = {});

}  // namespace gs360
