#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <numbers>
#include <string>

#include "geometry/mesh.h"
#include "geometry/shapes.h"

namespace fs = std::filesystem;
using gs360::LoadMesh;
using gs360::MeshError;
using gs360::MeshLoadOptions;
using gs360::MeshReport;
using gs360::TriangleMesh;
using gs360::ValidateAndRepair;

namespace {

fs::path TempDir() {
  const fs::path dir = fs::path(GS360_BINARY_DIR) / "test_tmp" / "geometry_mesh";
  fs::create_directories(dir);
  return dir;
}

void WriteText(const fs::path& p, const std::string& text) {
  std::ofstream out(p, std::ios::binary);
  out << text;
}

// Cube [0, s]^3 as 6 quads (v: 8 corners), outward CCW.
const int kQuads[6][4] = {{0, 3, 2, 1}, {4, 5, 6, 7}, {0, 1, 5, 4},
                          {2, 3, 7, 6}, {1, 2, 6, 5}, {0, 4, 7, 3}};
Eigen::Vector3d CubeCorner(int i, double s) {
  return Eigen::Vector3d((i == 1 || i == 2 || i == 5 || i == 6) ? s : 0.0,
                         (i == 2 || i == 3 || i == 6 || i == 7) ? s : 0.0, i >= 4 ? s : 0.0);
}

TriangleMesh Cube(double s) {
  TriangleMesh m;
  for (int i = 0; i < 8; ++i) m.vertices.push_back(CubeCorner(i, s));
  for (const auto& q : kQuads) {
    m.triangles.emplace_back(q[0], q[1], q[2]);
    m.triangles.emplace_back(q[0], q[2], q[3]);
  }
  return m;
}

TriangleMesh SmallFinger() {
  gs360::CylinderCapOptions o;
  gs360::TessellationOptions t;
  t.segments = 24;
  t.rings = 12;
  return gs360::MakeRevolutionMesh(*gs360::MakeCylinderCapProfile(o), t);
}

}  // namespace

TEST_CASE("LoadMesh reads ASCII STL, binary STL, OBJ and PLY", "[mesh]") {
  const fs::path dir = TempDir();
  const double s = 10.0;
  const TriangleMesh cube = Cube(s);

  // ASCII STL written by hand here (independent of the writer), one facet per triangle.
  std::string stl = "solid cube\n";
  for (const auto& f : cube.triangles) {
    stl += "facet normal 0 0 0\nouter loop\n";
    for (int k = 0; k < 3; ++k) {
      const auto& v = cube.vertices[f[k]];
      stl += "vertex " + std::to_string(v.x()) + " " + std::to_string(v.y()) + " " +
             std::to_string(v.z()) + "\n";
    }
    stl += "endloop\nendfacet\n";
  }
  stl += "endsolid cube\n";
  WriteText(dir / "cube_ascii.stl", stl);
  gs360::WriteStlBinary(dir / "cube_binary.stl", cube);

  // OBJ and PLY with quads (triangulated on import).
  std::string obj = "# cube\n";
  for (int i = 0; i < 8; ++i) {
    const auto v = CubeCorner(i, s);
    obj += "v " + std::to_string(v.x()) + " " + std::to_string(v.y()) + " " +
           std::to_string(v.z()) + "\n";
  }
  for (const auto& q : kQuads) {
    obj += "f " + std::to_string(q[0] + 1) + " " + std::to_string(q[1] + 1) + " " +
           std::to_string(q[2] + 1) + " " + std::to_string(q[3] + 1) + "\n";
  }
  WriteText(dir / "cube.obj", obj);
  std::string ply =
      "ply\nformat ascii 1.0\nelement vertex 8\nproperty float x\nproperty float y\n"
      "property float z\nelement face 6\nproperty list uchar int vertex_indices\nend_header\n";
  for (int i = 0; i < 8; ++i) {
    const auto v = CubeCorner(i, s);
    ply += std::to_string(v.x()) + " " + std::to_string(v.y()) + " " + std::to_string(v.z()) + "\n";
  }
  for (const auto& q : kQuads) {
    ply += "4 " + std::to_string(q[0]) + " " + std::to_string(q[1]) + " " + std::to_string(q[2]) +
           " " + std::to_string(q[3]) + "\n";
  }
  WriteText(dir / "cube.ply", ply);

  for (const char* name : {"cube_ascii.stl", "cube_binary.stl", "cube.obj", "cube.ply"}) {
    INFO(name);
    MeshReport report;
    const TriangleMesh m = LoadMesh(dir / name, {}, &report);
    CHECK(m.NumVertices() == 8);
    CHECK(m.NumTriangles() == 12);
    CHECK(m.Area() == Approx(6 * s * s).epsilon(1e-9));
    CHECK(m.SignedVolume() == Approx(s * s * s).epsilon(1e-9));
    CHECK(report.ClosedExceptBase());
    CHECK(report.boundary_edges == 0);
    CHECK(report.Ok());
    REQUIRE(m.HasNormals());
    // The corner (s, s, s) has the outward normal (1, 1, 1)/sqrt(3) by symmetry.
    for (int i = 0; i < m.NumVertices(); ++i) {
      if ((m.vertices[i] - Eigen::Vector3d::Constant(s)).norm() < 1e-9) {
        CHECK(m.normals[i].dot(Eigen::Vector3d::Constant(1.0).normalized()) ==
              Approx(1.0).epsilon(1e-12));
      }
    }
  }
  // STL stores triangle soup: the report says how many vertices were welded.
  MeshReport report;
  LoadMesh(dir / "cube_binary.stl", {}, &report);
  CHECK(report.input_vertices == 36);
  CHECK(report.welded_vertices == 28);

  // Scale and placement options.
  MeshLoadOptions opt;
  opt.scale = 0.5;
  opt.sensor_from_file = gs360::Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0, 0, 1));
  const TriangleMesh scaled = LoadMesh(dir / "cube.obj", opt);
  CHECK(scaled.Bounds().min().z() == Approx(1.0));
  CHECK(scaled.Bounds().max().x() == Approx(5.0));
}

TEST_CASE("A built-in shape survives a binary STL round trip", "[mesh]") {
  const fs::path dir = TempDir();
  const TriangleMesh finger = SmallFinger();
  gs360::WriteStlBinary(dir / "finger.stl", finger);
  gs360::WriteObj(dir / "finger.obj", finger);
  gs360::WritePlyAscii(dir / "finger.ply", finger);
  for (const char* name : {"finger.stl", "finger.obj", "finger.ply"}) {
    INFO(name);
    MeshReport report;
    MeshLoadOptions opt;
    opt.reject_open = true;  // open only at the base: accepted
    const TriangleMesh m = LoadMesh(dir / name, opt, &report);
    CHECK(m.NumVertices() == finger.NumVertices());
    CHECK(m.NumTriangles() == finger.NumTriangles());
    CHECK(m.Area() == Approx(finger.Area()).epsilon(1e-6));
    CHECK(report.boundary_edges_on_base == 24);
    CHECK(report.boundary_edges_off_base == 0);
    CHECK(report.reoriented_components == 0);
    CHECK(report.flipped_triangles == 0);
    CHECK(report.Ok());
  }
  // Identical files give identical hashes.
  CHECK(LoadMesh(dir / "finger.stl").Hash() == LoadMesh(dir / "finger.stl").Hash());
}

TEST_CASE("LoadMesh turns a crash or a hang of the importer into an error naming the file",
          "[mesh]") {
  const fs::path dir = TempDir() / "importer";
  fs::create_directories(dir);
  // Found by tests/fuzz (mesh, corpus regression-crash-2): assimp 5.2 dies of a bus error in its
  // post-processing on this PLY. It reads files in a child process, so this one is an error.
  WriteText(dir / "crashes.ply",
            "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
            "property float z\nelement face 4\nproperty list uchar int vertex_indices\n"
            "end_header\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 t z\nelement face 4\n"
            "property list uchar int vertex_in0 1 3\n3 0 3 2\n3 1 2 3\n");
  CHECK_THROWS_WITH(LoadMesh(dir / "crashes.ply"),
                    Catch::Contains("crashes.ply") && Catch::Contains("crashed on it"));
  // The process that asked is unharmed and reads the next file.
  const TriangleMesh finger = SmallFinger();
  gs360::WriteStlBinary(dir / "finger.stl", finger);
  CHECK(LoadMesh(dir / "finger.stl").NumTriangles() == finger.NumTriangles());
  // An importer that does not finish in time is killed.
  MeshLoadOptions hasty;
  hasty.import_timeout_s = 1e-4;
  CHECK_THROWS_WITH(LoadMesh(dir / "finger.stl", hasty),
                    Catch::Contains("finger.stl") && Catch::Contains("had not finished after"));
  hasty.import_timeout_s = 0.0;
  CHECK_THROWS_AS(LoadMesh(dir / "finger.stl", hasty), std::invalid_argument);
  fs::remove_all(dir);
}

TEST_CASE("LoadMesh errors name the file and the problem", "[mesh]") {
  const fs::path dir = TempDir();
  try {
    LoadMesh(dir / "does_not_exist.stl");
    FAIL("no exception");
  } catch (const MeshError& e) {
    CHECK_THAT(e.what(), Catch::Contains("not found") && Catch::Contains("does_not_exist.stl"));
  }
  WriteText(dir / "empty.stl", "");
  CHECK_THROWS_WITH(LoadMesh(dir / "empty.stl"),
                    Catch::Contains("empty") && Catch::Contains("empty.stl"));
  WriteText(dir / "garbage.ply", "ply\nthis is not a ply file\n");
  CHECK_THROWS_AS(LoadMesh(dir / "garbage.ply"), MeshError);
  // Found by tests/fuzz (mesh): assimp never returned on this header; it is refused before.
  WriteText(dir / "loops.ply",
            "ply\nformat ascii 1.00solid t\nf\ne\377\377\377lement vertex 4\npropa\377\377e");
  CHECK_THROWS_WITH(LoadMesh(dir / "loops.ply"), Catch::Contains("malformed PLY header") &&
                                                     Catch::Contains("loops.ply") &&
                                                     Catch::Contains("line 2"));
  WriteText(dir / "huge.ply",
            "ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\n"
            "end_header\n");
  CHECK_THROWS_WITH(LoadMesh(dir / "huge.ply"), Catch::Contains("claims 4000000000 entries"));
  WriteText(dir / "points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n");
  CHECK_THROWS_AS(LoadMesh(dir / "points.obj"), MeshError);

  // NaN vertices: rejected with counts by default, removed (and reported) on request.
  TriangleMesh finger = SmallFinger();
  finger.vertices[100].x() = std::numeric_limits<double>::quiet_NaN();
  finger.vertices[101].z() = std::numeric_limits<double>::infinity();
  gs360::WriteStlBinary(dir / "nan.stl", finger);
  try {
    LoadMesh(dir / "nan.stl");
    FAIL("no exception");
  } catch (const MeshError& e) {
    // Binary STL has no shared vertices: each use of a corner is its own vertex (6 + 6 uses);
    // the two ring neighbours share 2 of their 6 + 6 triangles.
    CHECK_THAT(e.what(), Catch::Contains("nan.stl") && Catch::Contains("NaN/Inf") &&
                             Catch::Contains("12 vertices") &&
                             Catch::Contains("used by 10 triangles"));
  }
  MeshLoadOptions lenient;
  lenient.reject_nonfinite = false;
  MeshReport report;
  const TriangleMesh m = LoadMesh(dir / "nan.stl", lenient, &report);
  CHECK(report.nonfinite_vertices == 12);
  CHECK(report.nonfinite_triangles == 10);
  CHECK(m.NumTriangles() == finger.NumTriangles() - 10);
  CHECK(report.boundary_edges_off_base > 0);  // the removal left a hole
  CHECK_FALSE(report.Ok());
  lenient.reject_open = true;
  CHECK_THROWS_WITH(LoadMesh(dir / "nan.stl", lenient),
                    Catch::Contains("not closed") && Catch::Contains("nan.stl"));

  CHECK_THROWS_AS(gs360::WriteMesh(dir / "x.xyz", finger), MeshError);
  CHECK_THROWS_AS(gs360::WriteStlBinary(dir / "no_such_dir" / "x.stl", finger), MeshError);
  MeshLoadOptions bad;
  bad.scale = 0.0;
  CHECK_THROWS_WITH(LoadMesh(dir / "nan.stl", bad), Catch::Contains("MeshLoadOptions.scale"));
}

TEST_CASE("ValidateAndRepair makes the winding consistent and outward", "[mesh]") {
  const TriangleMesh original = SmallFinger();
  SECTION("half the triangles flipped") {
    TriangleMesh m = original;
    int flipped = 0;
    for (int t = 0; t < m.NumTriangles(); t += 2, ++flipped)
      std::swap(m.triangles[t][1], m.triangles[t][2]);
    const MeshReport r = ValidateAndRepair(m);
    // Net effect: every triangle has its original winding again.
    for (int t = 0; t < m.NumTriangles(); ++t) {
      INFO("triangle " << t);
      CHECK(m.TriangleNormal(t).dot(original.TriangleNormal(t)) > 0.99);
    }
    CHECK((r.flipped_triangles == flipped ||
           (r.flipped_triangles == m.NumTriangles() - flipped && r.reoriented_components == 1)));
    CHECK(r.signed_volume > 0.0);
    CHECK(r.Ok());
    CHECK_THAT(r.Summary(), Catch::Contains("consistent winding"));
  }
  SECTION("a few triangles flipped") {
    TriangleMesh m = original;
    for (int t : {3, 50, 200}) std::swap(m.triangles[t][0], m.triangles[t][1]);
    const MeshReport r = ValidateAndRepair(m);
    CHECK(r.flipped_triangles == 3);
    CHECK(r.reoriented_components == 0);
    for (int t : {3, 50, 200}) CHECK(m.TriangleNormal(t).dot(original.TriangleNormal(t)) > 0.99);
  }
  SECTION("everything inside out") {
    TriangleMesh m = original;
    for (auto& f : m.triangles) std::swap(f[1], f[2]);
    CHECK(m.SignedVolume() < 0.0);
    const MeshReport r = ValidateAndRepair(m);
    CHECK(r.flipped_triangles == 0);
    CHECK(r.reoriented_components == 1);
    CHECK(m.SignedVolume() == Approx(original.SignedVolume()));
    CHECK_THAT(r.Summary(), Catch::Contains("reoriented 1 component outward"));
  }
  SECTION("a clean mesh is left alone") {
    TriangleMesh m = original;
    const MeshReport r = ValidateAndRepair(m);
    CHECK(r.problems.empty());
    CHECK(r.fixes.empty());
    CHECK(m.Hash() == original.Hash());  // exact normals kept, nothing touched
    CHECK(r.components == 1);
    CHECK(r.boundary_edges == 24);
    CHECK(r.boundary_edges_on_base == 24);
  }
}

// Found by tests/fuzz (mesh): welding hashed each coordinate's cell through a cast that is
// undefined past 2^63 cells. A far vertex (1e32 mm) is welded to its twin and nothing else.
TEST_CASE("ValidateAndRepair welds vertices at any distance", "[mesh]") {
  TriangleMesh m;
  m.vertices = {{0, 0, 0}, {1e32, 0, 0}, {0, -2.5e32, 0}, {1e32, 0, 0}, {0, 0, 1}};
  m.triangles = {{0, 1, 2}, {0, 3, 4}};
  const MeshReport r = ValidateAndRepair(m);
  CHECK(r.welded_vertices == 1);
}

TEST_CASE("ValidateAndRepair counts and removes duplicates, degenerates, NaN and welds", "[mesh]") {
  const TriangleMesh original = SmallFinger();
  SECTION("duplicates (either winding)") {
    TriangleMesh m = original;
    m.triangles.push_back(m.triangles[10]);
    m.triangles.push_back(
        Eigen::Vector3i(m.triangles[11][0], m.triangles[11][2], m.triangles[11][1]));
    m.triangles.push_back(m.triangles[10]);
    const MeshReport r = ValidateAndRepair(m);
    CHECK(r.duplicate_triangles == 3);
    CHECK(m.NumTriangles() == original.NumTriangles());
    CHECK(r.ClosedExceptBase());
    CHECK_THAT(r.Summary(), Catch::Contains("removed 3 duplicate triangles"));
  }
  SECTION("degenerate triangles") {
    TriangleMesh m = original;
    m.triangles.emplace_back(5, 5, 6);  // repeated vertex
    const int a = m.NumVertices();
    m.vertices.emplace_back(0, 0, 50);
    m.vertices.emplace_back(1, 0, 50);
    m.vertices.emplace_back(2, 0, 50);  // collinear
    m.triangles.emplace_back(a, a + 1, a + 2);
    const MeshReport r = ValidateAndRepair(m);
    CHECK(r.degenerate_triangles == 2);
    CHECK(r.unreferenced_vertices == 3);
    CHECK(m.NumTriangles() == original.NumTriangles());
    CHECK(m.NumVertices() == original.NumVertices());
    CHECK(r.ClosedExceptBase());
  }
  SECTION("NaN vertex: its triangles removed, the hole reported") {
    TriangleMesh m = original;
    m.vertices[60].y() = std::numeric_limits<double>::quiet_NaN();
    const MeshReport r = ValidateAndRepair(m);
    CHECK(r.nonfinite_vertices == 1);
    CHECK(r.nonfinite_triangles == 6);  // a ring vertex has 6 incident triangles
    CHECK(m.NumTriangles() == original.NumTriangles() - 6);
    CHECK(r.boundary_edges_off_base == 6);
    CHECK_FALSE(r.ClosedExceptBase());
    CHECK_THAT(r.Summary(),
               Catch::Contains("1 vertex has NaN/Inf") && Catch::Contains("not closed"));
  }
  SECTION("NaN kept on request: the report is not ok") {
    TriangleMesh m = original;
    m.vertices[60].y() = std::numeric_limits<double>::quiet_NaN();
    gs360::MeshRepairOptions keep;
    keep.remove_nonfinite = false;
    const MeshReport r = ValidateAndRepair(m, keep);
    CHECK(r.nonfinite_triangles == 6);
    CHECK(m.NumTriangles() == original.NumTriangles());
    CHECK_FALSE(r.Ok());
  }
  SECTION("triangle soup is welded within the tolerance") {
    TriangleMesh soup;
    for (const auto& f : original.triangles) {
      const int base = soup.NumVertices();
      for (int k = 0; k < 3; ++k) {
        // Perturb below the weld tolerance (1e-5 mm).
        soup.vertices.push_back(original.vertices[f[k]] + Eigen::Vector3d(3e-6 * k, -2e-6, 0.0));
      }
      soup.triangles.emplace_back(base, base + 1, base + 2);
    }
    const MeshReport r = ValidateAndRepair(soup);
    CHECK(r.welded_vertices == 3 * original.NumTriangles() - original.NumVertices());
    CHECK(soup.NumVertices() == original.NumVertices());
    CHECK(r.ClosedExceptBase());
    CHECK(r.boundary_edges_on_base == 24);
  }
}

TEST_CASE("ValidateAndRepair reports holes away from the base and non-manifold edges", "[mesh]") {
  const TriangleMesh original = SmallFinger();
  SECTION("hole in the side wall") {
    TriangleMesh m = original;
    // Remove one quad (2 triangles) in the middle of the wall: 4 boundary edges.
    const int quad = 24 * 5 + 7;
    m.triangles.erase(m.triangles.begin() + 2 * quad, m.triangles.begin() + 2 * quad + 2);
    const MeshReport r = ValidateAndRepair(m);
    CHECK(r.boundary_edges_off_base == 4);
    CHECK(r.boundary_edges_on_base == 24);
    CHECK_FALSE(r.ClosedExceptBase());
    CHECK_FALSE(r.Ok());
    CHECK_THAT(r.Summary(), Catch::Contains("4 boundary edges away from the base"));
  }
  SECTION("base moved: the opening is no longer on the base plane") {
    TriangleMesh m = original;
    gs360::MeshRepairOptions o;
    o.base_z = -1.0;
    const MeshReport r = ValidateAndRepair(m, o);
    CHECK(r.boundary_edges_off_base == 24);
  }
  SECTION("non-manifold edge") {
    TriangleMesh m = original;
    const Eigen::Vector3i f = m.triangles[100];
    m.vertices.emplace_back(0.0, 0.0, 15.0);
    m.triangles.emplace_back(f[0], f[1], m.NumVertices() - 1);
    const MeshReport r = ValidateAndRepair(m);
    CHECK(r.non_manifold_edges == 1);
    CHECK_FALSE(r.ClosedExceptBase());
    CHECK_THAT(r.Summary(), Catch::Contains("non-manifold"));
  }
  SECTION("closed mesh with no base opening") {
    TriangleMesh m = Cube(5.0);
    const MeshReport r = ValidateAndRepair(m);
    CHECK(r.boundary_edges == 0);
    CHECK(r.Ok());
    CHECK(r.signed_volume == Approx(125.0));
  }
}

TEST_CASE("TriangleMesh hash, bounds, area, transform and append", "[mesh]") {
  const TriangleMesh a = SmallFinger();
  TriangleMesh b = a;
  CHECK(a.Hash() == b.Hash());
  CHECK(a.HashHex().size() == 16);
  b.vertices[7].z() += 1e-12;
  CHECK(a.Hash() != b.Hash());
  b = a;
  std::swap(b.triangles[0][0], b.triangles[0][1]);
  CHECK(a.Hash() != b.Hash());

  const TriangleMesh cube = Cube(2.0);
  CHECK(cube.Area() == Approx(24.0));
  CHECK(cube.TriangleArea(0) == Approx(2.0));
  CHECK(cube.Bounds().max() == Eigen::Vector3d(2, 2, 2));
  TriangleMesh moved = cube;
  moved.ComputeVertexNormals();
  moved.Transform(gs360::Rigid3d::FromAxisAngle(Eigen::Vector3d::UnitZ(), std::numbers::pi / 2,
                                                Eigen::Vector3d(0, 0, 3)));
  CHECK(moved.Bounds().min().isApprox(Eigen::Vector3d(-2, 0, 3), 1e-12));
  CHECK(moved.SignedVolume() == Approx(8.0));
  TriangleMesh two = cube;
  two.Append(moved);
  CHECK(two.NumTriangles() == 24);
  CHECK(two.SignedVolume() == Approx(16.0));
  CHECK(two.normals.empty());  // cube had none
}

namespace {

// SmallFinger closed by its base: a fan from a centre vertex (or from rim vertex 0), facing -z.
TriangleMesh ClosedFinger(bool centre_fan) {
  TriangleMesh m = SmallFinger();
  const int segments = 24;  // rim vertices 0..23, counter-clockwise seen from +z
  if (centre_fan) {
    m.vertices.emplace_back(0.0, 0.0, 0.0);
    const int c = m.NumVertices() - 1;
    for (int k = 0; k < segments; ++k) m.triangles.emplace_back(c, (k + 1) % segments, k);
  } else {
    for (int k = 1; k + 1 < segments; ++k) m.triangles.emplace_back(0, k + 1, k);
  }
  m.normals.clear();
  return m;
}

}  // namespace

TEST_CASE("RemoveBaseFaces drops a closed solid's flat base and nothing else", "[mesh]") {
  const TriangleMesh open = SmallFinger();
  SECTION("a fan from a centre vertex, or from the rim") {
    for (const bool centre : {true, false}) {
      TriangleMesh m = ClosedFinger(centre);
      REQUIRE(ValidateAndRepair(m).boundary_edges == 0);  // watertight
      CHECK(gs360::RemoveBaseFaces(m) == (centre ? 24 : 22));
      CHECK(m.NumTriangles() == open.NumTriangles());
      CHECK(m.NumVertices() == open.NumVertices());  // the centre vertex went too
      CHECK(m.Area() == Approx(open.Area()));
      CHECK(m.HasNormals());
      // The rim's normals are the wall's again (horizontal), not tilted toward the base.
      for (int i = 0; i < 24; ++i) CHECK(std::abs(m.normals[i].z()) < 1e-9);
      CHECK(ValidateAndRepair(m).ClosedExceptBase());
    }
  }
  SECTION("an open surface, and faces that are not the base, are kept") {
    TriangleMesh m = open;
    CHECK(gs360::RemoveBaseFaces(m) == 0);
    CHECK(m.Hash() == open.Hash());
    // A cube standing on z = 0 loses its bottom only (its top faces +z, its sides are vertical).
    TriangleMesh cube = Cube(2.0);
    CHECK(gs360::RemoveBaseFaces(cube) == 2);
    for (int t = 0; t < cube.NumTriangles(); ++t) CHECK(cube.TriangleNormal(t).z() > -0.5);
  }
  SECTION("a base a little off z = 0 is still the base; one far from it is not") {
    for (const double dz : {-0.3, 0.004, 0.45}) {
      TriangleMesh m = ClosedFinger(true);
      for (auto& v : m.vertices) v.z() += dz;
      INFO("base at z = " << dz);
      CHECK(gs360::RemoveBaseFaces(m) == 24);
    }
    TriangleMesh high = ClosedFinger(true);
    for (auto& v : high.vertices) v.z() += 0.8;
    CHECK(gs360::RemoveBaseFaces(high) == 0);
    // A base that is not flat keeps the faces that leave the plane.
    TriangleMesh dented = ClosedFinger(true);
    dented.vertices.back().z() = 0.3;  // the centre: every fan triangle leaves the plane
    CHECK(gs360::RemoveBaseFaces(dented) == 0);
  }
  SECTION("options are checked, naming the field") {
    gs360::BasePlaneOptions o;
    o.flatness = -1.0;
    TriangleMesh m = open;
    CHECK_THROWS_WITH(gs360::RemoveBaseFaces(m, o), Catch::Contains("flatness"));
    o = gs360::BasePlaneOptions{};
    o.max_tilt_rad = 2.0;
    CHECK_THROWS_WITH(o.Check(), Catch::Contains("max_tilt_rad") && Catch::Contains("2"));
  }
}
