// The virtual rig on a sensor given as a mesh: a closed solid (a CAD export with its flat base)
// renders as its open surface does, the camera looking up through the base.
#include <catch2/catch.hpp>

#include <cmath>
#include <filesystem>
#include <memory>

#include "camera_test_util.h"
#include "geometry/shapes.h"
#include "sim/rig_model.h"
#include "sim/tactile_camera.h"

using namespace gs360;
using namespace gs360::camera_test;
namespace fs = std::filesystem;

namespace {

// A GelTip-like finger (radius 11.5 mm, 55.5 mm tall) as binary STL, open at its base or closed
// by a fan of triangles on z = 0.
fs::path WriteFinger(const std::string& name, bool closed) {
  CylinderCapOptions cylinder;
  cylinder.radius = 11.5;
  cylinder.height = 55.5;
  TessellationOptions t;
  t.segments = 96;
  TriangleMesh m = MakeRevolutionMesh(*MakeCylinderCapProfile(cylinder), t);
  if (closed) {
    m.vertices.emplace_back(0.0, 0.0, 0.0);
    const int centre = m.NumVertices() - 1;
    for (int k = 0; k < t.segments; ++k) m.triangles.emplace_back(centre, (k + 1) % 96, k);
  }
  m.normals.clear();
  const fs::path dir = fs::path(GS360_BINARY_DIR) / "test_tmp" / "sim_camera_mesh";
  fs::create_directories(dir);
  WriteStlBinary(dir / name, m);
  return dir / name;
}

std::shared_ptr<const SimRig> MeshRig(const fs::path& mesh) {
  SimRigOptions options;
  options.rig.mesh_path = mesh.string();
  return std::make_shared<const SimRig>(options);
}

}  // namespace

TEST_CASE("rig: a closed mesh renders as its open surface, seen through the base",
          "[sim][camera]") {
  TactileCameraOptions clean;
  clean.sensor.noise = false;
  TactileCamera open(MeshRig(WriteFinger("finger_open.stl", false)), clean);
  TactileCamera closed(MeshRig(WriteFinger("finger_closed.stl", true)), clean);
  CHECK(closed.rig().gel_mesh().NumTriangles() == open.rig().gel_mesh().NumTriangles());

  const cv::Mat open_ref = open.RenderReference(0);
  const cv::Mat closed_ref = closed.RenderReference(0);
  CHECK(cv::mean(open_ref)[0] > 5.0);  // the gel is lit, not the inside of a lid
  CHECK(cv::countNonZero(AbsDiffSum(open_ref, closed_ref)) == 0);
  // A press on the wall shows the same impression.
  const Eigen::Vector3d normal(std::cos(0.6), std::sin(0.6), 0.0);
  const Eigen::Vector3d ball = (11.5 + 2.0 - 0.8) * normal + Eigen::Vector3d(0.0, 0.0, 25.0);
  const cv::Mat open_press = open.RenderAtBall(ball, 1);
  const cv::Mat closed_press = closed.RenderAtBall(ball, 1);
  REQUIRE(DifferenceBlob(open_press, open_ref, 30));
  CHECK(cv::countNonZero(AbsDiffSum(open_press, closed_press)) == 0);
}
