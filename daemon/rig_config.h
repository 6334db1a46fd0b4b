#pragma once
// The rig as the user describes it: the sensor (a built-in shape or a mesh file), the LED fins,
// the NOMINAL camera (intrinsics and CAD pose), the mount on the machine and the probe's tool
// offset. Production code only ever sees these nominal values; calibration estimates the truth.
//
// Frames: sensor (S), camera (C, OpenCV), machine (M, GRBL MPos). Units: mm, rad.

#include <Eigen/Core>
#include <string>

#include <nlohmann/json_fwd.hpp>

#include "gcode/plan.h"
#include "geometry/fisheye.h"
#include "geometry/rigid3.h"
#include "geometry/shapes.h"

namespace gs360 {

struct RigConfig {
  SensorShapeOptions shape;  // built-in sensor (ignored when mesh_path is set)
  std::string mesh_path;     // STL / OBJ / PLY in the sensor frame, mm (optional)
  FinOptions fins = DefaultFinOptions();
  FisheyeIntrinsics camera = FisheyeIntrinsics::Default160();
  // Nominal camera: on the sensor axis at z = camera_z (below the fins' bottom edge), looking +z,
  // camera x = sensor x, camera y = sensor y.
  double camera_z = -1.5;
  // Mount: the sensor upright (sensor +z = machine +z), base centre at this machine position.
  // The defaults centre a 30 mm finger in a small desktop mill's travel (300 x 180 x 45 mm,
  // GRBL MPos in [-travel, 0]): with the ball 50 mm below the spindle, pressing from the base
  // ring to above the tip spans machine Z from about -41.5 to -3 mm.
  Eigen::Vector3d base_in_machine{-150.0, -90.0, -93.0};
  // Ball centre (machine frame) = machine position (MPos) + tool_offset.
  Eigen::Vector3d tool_offset{0.0, 0.0, -50.0};
  double ball_radius = 2.0;

  static FinOptions DefaultFinOptions();
  Rigid3d cam_from_sensor() const;
  Rigid3d machine_from_sensor() const;
  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

// The planner's view of the rig: the mesh (loaded or built), the exact profile of a built-in
// shape (for a mesh: a fitted profile for the fins only), fins, nominal camera, mount. Throws
// MeshError for an unreadable mesh file.
RigGeometry MakeRigGeometry(const RigConfig& config);

// JSON round trip. FromJson rejects unknown keys and wrong types, naming `where` (a file name)
// and the field path, e.g. "rig.json: rig.shape.cylinder.radius: expected a number".
nlohmann::json RigConfigToJson(const RigConfig& config);
RigConfig RigConfigFromJson(const nlohmann::json& json, const std::string& where);

}  // namespace gs360
