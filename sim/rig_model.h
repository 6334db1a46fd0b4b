#pragma once
// The simulated rig's static description: the sensor (gel outer surface and LED fins), the
// camera (nominal CAD values and the hidden TRUE values the simulator renders with), and the
// mount on the virtual CNC.
//
// Frames (see docs/architecture.md): sensor S (origin at the centre of the base plane, +z toward
// the tip), camera C (OpenCV), machine M (GRBL MPos). Units: mm, rad (degrees only in option
// names that say so).
//
// Nominal vs true: production code is given the NOMINAL intrinsics and cam_from_sensor (what the
// CAD says, SimRig::nominal_*()); the simulator renders with TRUE values that differ from them by
// a seeded perturbation of fixed size (TruePerturbationOptions). The true values are reachable
// only through sim/ground_truth.h, which production code never includes.
//
// Default geometry: RigConfig's (the cylinder-with-cap sensor, fins from z = 1.5 mm up, camera
// on the axis at z = -1.5 mm looking +z): the fins, seen almost edge-on, cross the image as a grey
// cross covering ~10% of the image circle, and every ray of the 160-degree field lands on the gel
// (the rim ray at 80 deg meets the wall at z ~ 0.3 mm).

#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <string>

#include "geometry/bvh.h"
#include "geometry/fisheye.h"
#include "geometry/mesh.h"
#include "geometry/rigid3.h"
#include "geometry/shapes.h"
#include "rig/rig_config.h"

namespace gs360 {

// How far the TRUE camera is from the nominal one. Magnitudes are fixed; directions and signs
// are drawn from SimRigOptions::seed. Defaults: the camera centre 0.3 mm away from the nominal
// one (random direction), its orientation 1.0 deg off (random axis); fx scaled by 1 +- 1.0%, fy by
// fx's factor +- 0.3%; the principal point 3.0 px away (random direction); k1 = +-0.010,
// k2 = +-0.003 (k3 = k4 = 0), where the nominal lens is equidistant (k = 0).
struct TruePerturbationOptions {
  double translation_mm = 0.3;
  double rotation_deg = 1.0;
  double focal_relative = 0.010;
  double aspect_relative = 0.003;
  double principal_point_px = 3.0;
  double k1 = 0.010;
  double k2 = 0.003;
  // Throws std::invalid_argument naming the field: negative or non-finite values, rotation >= 90
  // deg, focal_relative or aspect_relative >= 0.2, k1 or k2 large enough to fold the lens inside
  // the field (checked by SimRig).
  void Check() const;
  // All zeros: the true camera equals the nominal one.
  static TruePerturbationOptions None();
};

struct SimRigOptions {
  // The rig as its user describes it (rig/rig_config.h): gel surface (built-in shape, or a mesh
  // in the sensor frame, closed except at the base opening z = 0 or a closed solid whose base
  // is dropped: rig/rig_shape.h), LED fins, NOMINAL camera and mount. Production code is given
  // exactly these values.
  RigConfig rig;
  MeshLoadOptions mesh_load;  // for rig.mesh_path
  TruePerturbationOptions perturbation;
  std::uint64_t seed = 1;  // draws the true-camera perturbation

  // Throws std::invalid_argument naming the field and its value (delegates to the nested
  // options' Check()).
  void Check() const;
};

// The built rig: meshes, profile, nominal and (privately) true camera. Immutable and thread-safe
// after construction.
class SimRig {
 public:
  // Builds the gel mesh (built-in shape or LoadMesh(mesh_path); MeshError propagates), the fins,
  // the BVHs, and the true camera. Throws std::invalid_argument for invalid options or a lens
  // that the perturbation folds inside the field.
  explicit SimRig(const SimRigOptions& options);

  const SimRigOptions& options() const { return options_; }
  // Gel outer surface (sensor frame, outward normals) and both fins (triangles [0, n/2) are the
  // xz fin, [n/2, n) the yz fin).
  const TriangleMesh& gel_mesh() const { return gel_bvh_->mesh(); }
  const TriangleMesh& fin_mesh() const { return fin_bvh_->mesh(); }
  const Bvh& gel_bvh() const { return *gel_bvh_; }
  const Bvh& fin_bvh() const { return *fin_bvh_; }
  // The surface of revolution the fins and LEDs are laid out on: the built-in profile, or the one
  // fitted inside a loaded mesh.
  const RevolutionProfile& profile() const { return *profile_; }
  // The fins as built (rig/rig_shape.h RigShape::fin_options): the LEDs are laid out on them.
  const FinOptions& fin_options() const { return fin_options_; }
  std::shared_ptr<const RevolutionProfile> profile_ptr() const { return profile_; }
  // "cylinder", "cone", "spline" or the mesh path.
  std::string Describe() const;

  // What production code is given (config).
  const FisheyeIntrinsics& nominal_intrinsics() const { return options_.rig.camera; }
  Rigid3d nominal_cam_from_sensor() const { return options_.rig.cam_from_sensor(); }
  Rigid3d machine_from_sensor() const { return options_.rig.machine_from_sensor(); }
  const Eigen::Vector3d& tool_offset() const { return options_.rig.tool_offset; }
  double ball_radius() const { return options_.rig.ball_radius; }

  // Ball centre in the sensor frame for a machine position (MPos, mm).
  Eigen::Vector3d BallCenterSensor(const Eigen::Vector3d& machine_position) const;
  // Machine position that puts the ball centre at `ball_center_sensor`.
  Eigen::Vector3d MachinePositionForBall(const Eigen::Vector3d& ball_center_sensor) const;

 private:
  friend class SimGroundTruth;

  SimRigOptions options_;
  std::shared_ptr<const RevolutionProfile> profile_;
  std::unique_ptr<Bvh> gel_bvh_;
  std::unique_ptr<Bvh> fin_bvh_;
  FinOptions fin_options_;
  FisheyeIntrinsics true_intrinsics_;
  Rigid3d true_cam_from_sensor_;
};

}  // namespace gs360
