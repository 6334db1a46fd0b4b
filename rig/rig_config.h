#pragma once
// The rig, described once: the sensor (a built-in shape or a mesh file), the LED fins, the
// NOMINAL camera (intrinsics and CAD pose), the mount on the machine, the probe's tool offset and
// ball. Planning (plan/plan.h MakeRigGeometry), the run and daemon configurations and the
// virtual rig (sim/rig_model.h, which adds its hidden truth on top) all take this struct; its
// defaults here are the only ones. Production code only ever sees these nominal values;
// calibration estimates the truth.
//
// Frames: sensor (S: origin at the centre of the base plane, +z along the finger axis), camera
// (C, OpenCV), machine (M, GRBL MPos). Units: mm, rad.

#include <Eigen/Core>
#include <string>

#include <nlohmann/json_fwd.hpp>

#include "geometry/fisheye.h"
#include "geometry/rigid3.h"
#include "geometry/shapes.h"

namespace gs360 {

struct RigConfig {
  SensorShapeOptions shape;  // built-in sensor (ignored when mesh_path is set)
  std::string mesh_path;     // STL / OBJ / PLY in the sensor frame (optional)
  double mesh_scale = 1.0;   // millimetres per unit of the mesh file (1000 for a file in metres)
  FinOptions fins = DefaultFins();
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
  // The gel layer over the rigid shell (mm): no press may go this deep.
  double gel_thickness = 1.5;

  // Fins 0.45 mm thick (board and LEDs), 1.5 mm inside the outer surface (gel and shell), from
  // z = 1.5 mm up: the camera at z = -1.5 sits 3 mm below their bottom edge.
  static FinOptions DefaultFins();
  Rigid3d cam_from_sensor() const;
  Rigid3d machine_from_sensor() const;
  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

class JsonReader;

// JSON round trip. FromJson rejects unknown keys and wrong types, naming `where` (a file name)
// and the field path, e.g. "rig.json: rig.shape.cylinder.radius: expected a number".
nlohmann::json RigConfigToJson(const RigConfig& config);
RigConfig RigConfigFromJson(const nlohmann::json& json, const std::string& where);
// Reads the keys present into `config` (absent keys keep its values); no Check(). For readers of
// larger documents (the run and daemon configurations).
void ReadRigConfig(JsonReader& reader, RigConfig& config);
// The "shape" object alone (type, cylinder, cone, spline, segments, rings).
void ReadSensorShape(JsonReader& reader, SensorShapeOptions& shape);
nlohmann::json SensorShapeToJson(const SensorShapeOptions& shape);

}  // namespace gs360
