#pragma once
// The rig's solid parts built from its description: the gel's outer surface, the surface of
// revolution the fins are laid out on, and the fins. One builder for the planner
// (plan/plan.h MakeRigGeometry) and the virtual rig (sim/rig_model.h).
//
// Frame: sensor (mm). Throws MeshError (geometry/mesh.h) for a mesh file that cannot be used,
// std::invalid_argument for an invalid RigConfig or fins that do not fit the shape.
//
// A mesh file may be the open sensing surface or a closed solid with its flat base (a CAD export
// of the elastomer): the base's faces, on the base plane z = 0 after rig.mesh_scale
// (geometry/mesh.h RemoveBaseFaces, its default tolerances), are dropped, so that both give the
// same gel. The camera looks up through the base: the base neither hides the gel nor is surface
// to probe, for the planner and the virtual rig alike.

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
  // The fins as built: rig.fins, except that for a mesh whose inscribed profile narrows too fast
  // for the boards (their inner-wall outline would fold, FinFoldZ) top_z is lowered to
  // kFinFoldMarginMm below the fold. The LEDs are laid out on these.
  FinOptions fin_options;
  int base_faces_removed = 0;  // a mesh's base faces dropped (0 for an open surface)
};

inline constexpr double kFinFoldMarginMm = 1.0;

RigShape BuildRigShape(const RigConfig& rig, const MeshLoadOptions& load = {});

}  // namespace gs360
