#pragma once
// Small helpers shared by the daemon's source files (not part of any public contract).

#include <Eigen/Core>
#include <chrono>
#include <string>

#include <nlohmann/json.hpp>

namespace gs360::daemon_util {

inline double UnixNow() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

inline nlohmann::json Vec(const Eigen::Vector3d& v) {
  return nlohmann::json::array({v.x(), v.y(), v.z()});
}

// The mesh formats the daemon accepts (file extensions, lower case).
inline bool IsMeshFormat(const std::string& f) {
  return f == "stl" || f == "obj" || f == "ply";
}

}  // namespace gs360::daemon_util
