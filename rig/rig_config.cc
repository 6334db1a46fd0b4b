#include "rig/rig_config.h"

#include <cmath>
#include <stdexcept>

#include <nlohmann/json.hpp>

#include "base/json_reader.h"

namespace gs360 {
namespace {

void RequireFinite(const Eigen::Vector3d& v, const char* field) {
  if (!v.allFinite()) {
    throw std::invalid_argument(std::string("RigConfig.") + field + " must be finite");
  }
}

nlohmann::json Vec(const Eigen::Vector3d& v) {
  return {v.x(), v.y(), v.z()};
}

constexpr NumberRange kShapeMm{0.0, 1000.0, true, "mm"};
constexpr std::size_t kMaxControlPoints = 1000;

}  // namespace

FinOptions RigConfig::DefaultFins() {
  FinOptions fins;
  fins.thickness = 0.45;
  fins.inset = 1.5;
  fins.bottom_z = 1.5;
  return fins;
}

Rigid3d RigConfig::cam_from_sensor() const {
  // Camera axes = sensor axes (OpenCV z forward = sensor +z), centre at (0, 0, camera_z).
  return Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.0, 0.0, -camera_z));
}

Rigid3d RigConfig::machine_from_sensor() const {
  return Rigid3d(Eigen::Quaterniond::Identity(), base_in_machine);
}

void RigConfig::Check() const {
  if (mesh_path.empty()) shape.Check();
  if (!(mesh_scale > 0.0) || !std::isfinite(mesh_scale)) {
    throw std::invalid_argument("RigConfig.mesh_scale must be finite and > 0, got " +
                                std::to_string(mesh_scale));
  }
  fins.Check();
  camera.Check();
  if (!std::isfinite(camera_z) || camera_z >= fins.bottom_z) {
    throw std::invalid_argument("RigConfig.camera_z must be finite and below fins.bottom_z (" +
                                std::to_string(fins.bottom_z) + "), got " +
                                std::to_string(camera_z));
  }
  RequireFinite(base_in_machine, "base_in_machine");
  RequireFinite(tool_offset, "tool_offset");
  if (!(ball_radius > 0.0 && ball_radius < 50.0)) {
    throw std::invalid_argument("RigConfig.ball_radius must be in (0, 50) mm, got " +
                                std::to_string(ball_radius));
  }
  if (!(gel_thickness > 0.0 && gel_thickness < 50.0)) {
    throw std::invalid_argument("RigConfig.gel_thickness must be in (0, 50) mm, got " +
                                std::to_string(gel_thickness));
  }
}

nlohmann::json SensorShapeToJson(const SensorShapeOptions& shape) {
  nlohmann::json spline = nlohmann::json::array();
  for (const auto& p : shape.spline.control_points) spline.push_back({p.x(), p.y()});
  return {{"type", std::string(SensorShapeName(shape.shape))},
          {"cylinder", {{"radius", shape.cylinder.radius}, {"height", shape.cylinder.height}}},
          {"cone",
           {{"base_radius", shape.cone.base_radius},
            {"height", shape.cone.height},
            {"tip_radius", shape.cone.tip_radius}}},
          {"spline", {{"control_points", spline}}},
          {"segments", shape.tessellation.segments},
          {"rings", shape.tessellation.rings}};
}

nlohmann::json RigConfigToJson(const RigConfig& c) {
  return {
      {"shape", SensorShapeToJson(c.shape)},
      {"mesh_path", c.mesh_path},
      {"mesh_scale", c.mesh_scale},
      {"fins",
       {{"enabled", c.fins.enabled},
        {"thickness", c.fins.thickness},
        {"inset", c.fins.inset},
        {"bottom_z", c.fins.bottom_z},
        {"top_z", c.fins.top_z}}},
      {"camera",
       {{"width", c.camera.width},
        {"height", c.camera.height},
        {"fx", c.camera.fx},
        {"fy", c.camera.fy},
        {"cx", c.camera.cx},
        {"cy", c.camera.cy},
        {"skew", c.camera.skew},
        {"k", {c.camera.k[0], c.camera.k[1], c.camera.k[2], c.camera.k[3]}},
        {"max_theta", c.camera.max_theta},
        {"camera_z", c.camera_z}}},
      {"base_in_machine", Vec(c.base_in_machine)},
      {"tool_offset", Vec(c.tool_offset)},
      {"ball_radius", c.ball_radius},
      {"gel_thickness", c.gel_thickness},
  };
}

void ReadSensorShape(JsonReader& s, SensorShapeOptions& shape) {
  std::string type(SensorShapeName(shape.shape));
  s.Get("type", type);
  try {
    shape.shape = ParseSensorShape(type);
  } catch (const std::exception& e) {
    s.Fail("type", e.what());
  }
  // The sizes a user may give, checked as they are read (the shapes' own Check()s hold the
  // relations between them): a fingertip sensor, not a building, and a mesh of at most some
  // millions of triangles.
  s.Object("cylinder", [&](JsonReader& o) {
    o.Get("radius", shape.cylinder.radius, kShapeMm);
    o.Get("height", shape.cylinder.height, kShapeMm);
  });
  s.Object("cone", [&](JsonReader& o) {
    o.Get("base_radius", shape.cone.base_radius, kShapeMm);
    o.Get("height", shape.cone.height, kShapeMm);
    o.Get("tip_radius", shape.cone.tip_radius, kShapeMm);
  });
  s.Object("spline", [&](JsonReader& o) {
    if (const auto* pts = o.Raw("control_points")) {
      if (!pts->is_array() || pts->size() > kMaxControlPoints) {
        o.Fail("control_points", "expected [[z, r], ...] of at most " +
                                     std::to_string(kMaxControlPoints) + " points");
      }
      shape.spline.control_points.clear();
      for (const auto& p : *pts) {
        const auto in_range = [](const nlohmann::json& v) {
          return v.is_number() && v.get<double>() >= 0.0 && v.get<double>() <= kShapeMm.max;
        };
        if (!p.is_array() || p.size() != 2 || !in_range(p[0]) || !in_range(p[1])) {
          o.Fail("control_points",
                 "expected [[z, r], ...], each in [0, 1000] mm, got element " + p.dump());
        }
        shape.spline.control_points.emplace_back(p[0].get<double>(), p[1].get<double>());
      }
    }
  });
  s.Get("segments", shape.tessellation.segments, IntRange{3, 4096});
  s.Get("rings", shape.tessellation.rings, IntRange{0, 4096});
}

void ReadRigConfig(JsonReader& r, RigConfig& c) {
  r.Object("shape", [&](JsonReader& s) { ReadSensorShape(s, c.shape); });
  r.Get("mesh_path", c.mesh_path);
  r.Get("mesh_scale", c.mesh_scale);
  r.Object("fins", [&](JsonReader& o) {
    o.Get("enabled", c.fins.enabled);
    o.Get("thickness", c.fins.thickness);
    o.Get("inset", c.fins.inset);
    o.Get("bottom_z", c.fins.bottom_z);
    o.Get("top_z", c.fins.top_z);
  });
  r.Object("camera", [&](JsonReader& o) {
    o.Get("width", c.camera.width);
    o.Get("height", c.camera.height);
    o.Get("fx", c.camera.fx);
    o.Get("fy", c.camera.fy);
    o.Get("cx", c.camera.cx);
    o.Get("cy", c.camera.cy);
    o.Get("skew", c.camera.skew);
    if (const auto* k = o.Raw("k")) {
      if (!k->is_array() || k->size() != 4) o.Fail("k", "expected [k1, k2, k3, k4]");
      for (int i = 0; i < 4; ++i) {
        const auto& v = (*k)[static_cast<std::size_t>(i)];
        if (!v.is_number()) o.Fail("k", "expected [k1, k2, k3, k4], got " + k->dump());
        c.camera.k[i] = v.get<double>();
      }
    }
    o.Get("max_theta", c.camera.max_theta);
    o.Get("camera_z", c.camera_z);
  });
  r.Get("base_in_machine", c.base_in_machine);
  r.Get("tool_offset", c.tool_offset);
  r.Get("ball_radius", c.ball_radius);
  r.Get("gel_thickness", c.gel_thickness);
}

RigConfig RigConfigFromJson(const nlohmann::json& json, const std::string& where) {
  RigConfig c;
  JsonReader r(json, where, "rig");
  ReadRigConfig(r, c);
  r.RejectUnknown();
  try {
    c.Check();
  } catch (const std::invalid_argument& e) {
    throw ConfigError(where + ": rig: " + e.what(), "rig");
  }
  return c;
}

}  // namespace gs360
