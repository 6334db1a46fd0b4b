// Geometry at its edges: degenerate triangles, a mesh in metres, NaN vertices, a spline that
// turns back on itself. Meshes go through real files (STL via assimp), as a user's would.

#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <limits>
#include <numbers>
#include <random>
#include <stdexcept>
#include <string>

#include "geometry/bvh.h"
#include "geometry/mesh.h"
#include "geometry/shapes.h"
#include "rig/rig_shape.h"
#include "stress/stress_cases.h"

namespace gs360::stress {
namespace {

// A file in the temporary directory, removed when it goes out of scope.
class TempFile {
 public:
  explicit TempFile(const std::string& name)
      : path_(std::filesystem::temp_directory_path() /
              ("gs360-stress-" + std::to_string(::getpid()) + "-" + name)) {}
  ~TempFile() {
    std::error_code ec;
    std::filesystem::remove(path_, ec);
  }
  TempFile(const TempFile&) = delete;
  TempFile& operator=(const TempFile&) = delete;
  const std::filesystem::path& path() const { return path_; }

 private:
  std::filesystem::path path_;
};

TriangleMesh DefaultFinger() {
  return MakeSensorMesh(SensorShapeOptions{});
}

// Rays from inside the finger (on its axis, 10 mm up) in directions that cannot leave through
// the open base: how many miss the surface.
int RaysMissing(const TriangleMesh& mesh, std::uint64_t seed, int rays) {
  const Bvh bvh(mesh);
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> z(-0.5, 1.0), phi(0.0, 2.0 * std::numbers::pi);
  int missing = 0;
  for (int i = 0; i < rays; ++i) {
    const double dz = z(rng), a = phi(rng), r = std::sqrt(1.0 - dz * dz);
    Ray ray;
    ray.origin = Eigen::Vector3d(0.0, 0.0, 10.0);
    ray.direction = Eigen::Vector3d(r * std::cos(a), r * std::sin(a), dz);
    if (!bvh.Intersect(ray)) ++missing;
  }
  return missing;
}

StressCase Degenerate() {
  return {"geometry", "a finger mesh with 20 % extra degenerate triangles (STL)",
          "every degenerate triangle removed and counted; 10,000 rays from inside all hit",
          [](const StressContext& c, std::string* observed) {
            TriangleMesh mesh = DefaultFinger();
            const int original = static_cast<int>(mesh.triangles.size());
            int added = 0;
            for (int t = 0; t < original; t += 10) {
              const Eigen::Vector3i f = mesh.triangles[static_cast<std::size_t>(t)];
              // A repeated vertex, and a sliver whose third vertex lies on the first edge.
              mesh.triangles.emplace_back(f[0], f[0], f[1]);
              mesh.vertices.push_back(0.5 * (mesh.vertices[f[0]] + mesh.vertices[f[1]]));
              mesh.triangles.emplace_back(f[0], f[1], static_cast<int>(mesh.vertices.size()) - 1);
              added += 2;
            }
            mesh.normals.clear();
            const TempFile file("degenerate.stl");
            WriteStlBinary(file.path(), mesh);
            MeshReport report;
            const TriangleMesh loaded = LoadMesh(file.path(), {}, &report);
            const int missing = RaysMissing(loaded, c.seed, 10000);
            *observed = Format(
                "%d degenerate added, %d removed; %zu triangles kept of %d; %d of "
                "10,000 rays missed; %d holes off the base",
                added, report.degenerate_triangles, loaded.triangles.size(), original, missing,
                report.boundary_edges_off_base);
            return report.degenerate_triangles >= added && missing == 0 &&
                   static_cast<int>(loaded.triangles.size()) == original;
          }};
}

StressCase Metres() {
  return {"geometry", "the sensor mesh in metres (a 30 mm finger as 0.03)",
          "MeshError naming the file and mesh_scale = 1000; with mesh_scale = 1000 it builds",
          [](const StressContext&, std::string* observed) {
            TriangleMesh mesh = DefaultFinger();
            for (Eigen::Vector3d& v : mesh.vertices) v *= 1e-3;
            mesh.normals.clear();
            const TempFile file("metres.stl");
            WriteStlBinary(file.path(), mesh);
            RigConfig rig;
            rig.mesh_path = file.path().string();
            bool refused = false;
            try {
              BuildRigShape(rig);
              *observed = "built without an error; ";
            } catch (const MeshError& e) {
              *observed = std::string(e.what()) + "; ";
              refused = std::string(e.what()).find("mesh_scale = 1000") != std::string::npos &&
                        std::string(e.what()).find(file.path().string()) != std::string::npos;
            }
            rig.mesh_scale = 1000.0;
            const RigShape shape = BuildRigShape(rig);
            const double height = shape.profile->Height();
            *observed += Format("with mesh_scale = 1000: %.2f mm tall", height);
            return refused && std::abs(height - 30.0) < 0.1;
          }};
}

StressCase NonFiniteVertex() {
  return {"geometry", "a mesh with a NaN vertex", "MeshError naming the file and the count",
          [](const StressContext&, std::string* observed) {
            TriangleMesh mesh = DefaultFinger();
            mesh.vertices[17].y() = std::numeric_limits<double>::quiet_NaN();
            mesh.normals.clear();
            const TempFile file("nan.stl");
            WriteStlBinary(file.path(), mesh);
            try {
              LoadMesh(file.path());
              *observed = "loaded without an error";
              return false;
            } catch (const MeshError& e) {
              *observed = e.what();
              return std::string(e.what()).find(file.path().filename().string()) !=
                     std::string::npos;
            }
          }};
}

StressCase SplineTurningBack() {
  return {
      "geometry", "a spline whose profile turns back (z decreasing: self-intersecting)",
      "std::invalid_argument naming the control point",
      [](const StressContext&, std::string* observed) {
        SplineOptions spline;
        spline.control_points = {{0.0, 10.0}, {12.0, 9.0}, {8.0, 11.0}, {20.0, 6.0}, {30.0, 0.0}};
        try {
          MakeSplineProfile(spline);
          *observed = "made a profile";
          return false;
        } catch (const std::invalid_argument& e) {
          *observed = e.what();
          return std::string(e.what()).find("control_points[2]") != std::string::npos;
        }
      }};
}

}  // namespace

std::vector<StressCase> GeometryCases() {
  return {Degenerate(), Metres(), NonFiniteVertex(), SplineTurningBack()};
}

}  // namespace gs360::stress
