#include "geometry/mesh.h"

#include <assimp/scene.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <limits>
#include <numbers>
#include <numeric>
#include <sstream>
#include <unordered_map>

#include "base/hash.h"
#include "geometry/assimp_export.h"
#include "geometry/assimp_import.h"

namespace gs360 {
namespace {

bool IsFinite(const Eigen::Vector3d& v) {
  return std::isfinite(v.x()) && std::isfinite(v.y()) && std::isfinite(v.z());
}

std::string Plural(int n, const char* singular, const char* plural) {
  return std::to_string(n) + " " + (n == 1 ? singular : plural);
}

std::string Quoted(const std::filesystem::path& p) {
  return "'" + p.string() + "'";
}

// Union-find over integers (path halving, union by lower index so results are deterministic).
struct DisjointSets {
  std::vector<int> parent;
  explicit DisjointSets(int n) : parent(n) { std::iota(parent.begin(), parent.end(), 0); }
  int Find(int x) {
    while (parent[x] != x) {
      parent[x] = parent[parent[x]];
      x = parent[x];
    }
    return x;
  }
  void Union(int a, int b) {
    a = Find(a);
    b = Find(b);
    if (a == b) return;
    if (a < b) std::swap(a, b);
    parent[a] = b;
  }
};

// One directed edge occurrence: vertices (a, b) in the triangle's winding, sorted by (lo, hi).
struct EdgeUse {
  int lo, hi;
  int triangle;
  bool forward;  // a == lo (the triangle walks lo -> hi)
};

std::vector<EdgeUse> SortedEdgeUses(const std::vector<Eigen::Vector3i>& tris) {
  std::vector<EdgeUse> uses;
  uses.reserve(tris.size() * 3);
  for (int t = 0; t < static_cast<int>(tris.size()); ++t) {
    for (int e = 0; e < 3; ++e) {
      const int a = tris[t][e];
      const int b = tris[t][(e + 1) % 3];
      uses.push_back({std::min(a, b), std::max(a, b), t, a < b});
    }
  }
  std::sort(uses.begin(), uses.end(), [](const EdgeUse& x, const EdgeUse& y) {
    if (x.lo != y.lo) return x.lo < y.lo;
    if (x.hi != y.hi) return x.hi < y.hi;
    return x.triangle < y.triangle;
  });
  return uses;
}

// Merges vertices within `tol` (lowest index wins). Returns old -> representative map.
std::vector<int> WeldMap(const std::vector<Eigen::Vector3d>& v, double tol) {
  const int n = static_cast<int>(v.size());
  std::vector<int> rep(n);
  if (tol <= 0.0) {
    std::unordered_map<std::string, int> exact;
    exact.reserve(n * 2);
    for (int i = 0; i < n; ++i) {
      Eigen::Vector3d p = v[i];
      for (int k = 0; k < 3; ++k)
        if (p[k] == 0.0) p[k] = 0.0;  // fold -0.0
      std::string key(reinterpret_cast<const char*>(p.data()), sizeof(double) * 3);
      rep[i] = exact.emplace(std::move(key), i).first->second;
    }
    return rep;
  }
  // Cells beyond +-2^62 share the last one (casting a larger value is undefined: found by
  // tests/fuzz with coordinates of 1e32); the distance test below keeps the weld exact, only the
  // hashing is coarser there. A non-finite coordinate (lenient loading) goes to cell 0.
  auto cell_of = [tol](double x) {
    constexpr double kLast = 4.611686018427387904e18;  // 2^62
    const double cell = std::floor(x / tol);
    return std::isfinite(cell) ? static_cast<std::int64_t>(std::clamp(cell, -kLast, kLast))
                               : std::int64_t{0};
  };
  auto key_of = [](std::int64_t x, std::int64_t y, std::int64_t z) {
    std::uint64_t h = static_cast<std::uint64_t>(x) * 0x9E3779B97F4A7C15ull;
    h ^= static_cast<std::uint64_t>(y) * 0xC2B2AE3D27D4EB4Full + (h << 6) + (h >> 2);
    h ^= static_cast<std::uint64_t>(z) * 0x165667B19E3779F9ull + (h << 6) + (h >> 2);
    return h;
  };
  std::unordered_map<std::uint64_t, std::vector<int>> grid;
  grid.reserve(n * 2);
  const double tol2 = tol * tol;
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector3d& p = v[i];
    const std::int64_t cx = cell_of(p.x()), cy = cell_of(p.y()), cz = cell_of(p.z());
    int found = -1;
    for (std::int64_t dx = -1; dx <= 1 && found < 0; ++dx)
      for (std::int64_t dy = -1; dy <= 1 && found < 0; ++dy)
        for (std::int64_t dz = -1; dz <= 1; ++dz) {
          auto it = grid.find(key_of(cx + dx, cy + dy, cz + dz));
          if (it == grid.end()) continue;
          for (int j : it->second) {
            if ((v[j] - p).squaredNorm() <= tol2 && (found < 0 || j < found)) found = j;
          }
        }
    if (found >= 0) {
      rep[i] = found;
    } else {
      rep[i] = i;
      grid[key_of(cx, cy, cz)].push_back(i);
    }
  }
  return rep;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// TriangleMesh

Eigen::AlignedBox3d TriangleMesh::Bounds() const {
  Eigen::AlignedBox3d box;
  for (const auto& v : vertices) box.extend(v);
  return box;
}

double TriangleMesh::TriangleArea(int t) const {
  const Eigen::Vector3i& f = triangles[t];
  return 0.5 * (vertices[f[1]] - vertices[f[0]]).cross(vertices[f[2]] - vertices[f[0]]).norm();
}

Eigen::Vector3d TriangleMesh::TriangleNormal(int t) const {
  const Eigen::Vector3i& f = triangles[t];
  const Eigen::Vector3d n =
      (vertices[f[1]] - vertices[f[0]]).cross(vertices[f[2]] - vertices[f[0]]);
  const double len = n.norm();
  return len > 0.0 ? Eigen::Vector3d(n / len) : Eigen::Vector3d::Zero();
}

double TriangleMesh::Area() const {
  double a = 0.0;
  for (int t = 0; t < NumTriangles(); ++t) a += TriangleArea(t);
  return a;
}

double TriangleMesh::SignedVolume(double base_z) const {
  // Integral of (z - base_z) n_z dA over a triangle = (area * n_z) * mean(z - base_z), and
  // area * n_z = 0.5 * cross_z.
  double v = 0.0;
  for (const auto& f : triangles) {
    const Eigen::Vector3d& a = vertices[f[0]];
    const Eigen::Vector3d& b = vertices[f[1]];
    const Eigen::Vector3d& c = vertices[f[2]];
    const double cross_z = (b - a).cross(c - a).z();
    v += 0.5 * cross_z * ((a.z() + b.z() + c.z()) / 3.0 - base_z);
  }
  return v;
}

void TriangleMesh::ComputeVertexNormals() {
  std::vector<Eigen::Vector3d> acc(vertices.size(), Eigen::Vector3d::Zero());
  for (const auto& f : triangles) {
    const Eigen::Vector3d n =
        (vertices[f[1]] - vertices[f[0]]).cross(vertices[f[2]] - vertices[f[0]]);
    const double len = n.norm();
    if (!(len > 0.0)) continue;
    const Eigen::Vector3d unit = n / len;
    for (int k = 0; k < 3; ++k) {
      const Eigen::Vector3d e1 = vertices[f[(k + 1) % 3]] - vertices[f[k]];
      const Eigen::Vector3d e2 = vertices[f[(k + 2) % 3]] - vertices[f[k]];
      const double angle = std::atan2(e1.cross(e2).norm(), e1.dot(e2));
      acc[f[k]] += angle * unit;
    }
  }
  normals.resize(vertices.size());
  for (std::size_t i = 0; i < acc.size(); ++i) {
    const double len = acc[i].norm();
    normals[i] =
        len > 0.0 && std::isfinite(len) ? Eigen::Vector3d(acc[i] / len) : Eigen::Vector3d::UnitZ();
  }
}

void TriangleMesh::Transform(const Rigid3d& b_from_a) {
  for (auto& v : vertices) v = b_from_a * v;
  for (auto& n : normals) n = b_from_a.RotateDirection(n);
}

void TriangleMesh::Append(const TriangleMesh& other) {
  const bool keep_normals = (HasNormals() || vertices.empty()) && other.HasNormals();
  const int offset = NumVertices();
  vertices.insert(vertices.end(), other.vertices.begin(), other.vertices.end());
  for (const auto& f : other.triangles) triangles.push_back(f + Eigen::Vector3i::Constant(offset));
  if (keep_normals) {
    normals.insert(normals.end(), other.normals.begin(), other.normals.end());
  } else {
    normals.clear();
  }
}

std::uint64_t TriangleMesh::Hash() const {
  Hasher h;
  h.Add("gs360.TriangleMesh.v1");
  h.AddPod(static_cast<std::uint64_t>(vertices.size()));
  for (const auto& v : vertices) h.AddDouble(v.x()).AddDouble(v.y()).AddDouble(v.z());
  h.AddPod(static_cast<std::uint64_t>(triangles.size()));
  for (const auto& f : triangles) {
    const std::array<std::int32_t, 3> idx = {f[0], f[1], f[2]};
    h.AddPod(idx);
  }
  h.AddPod(static_cast<std::uint64_t>(normals.size()));
  for (const auto& n : normals) h.AddDouble(n.x()).AddDouble(n.y()).AddDouble(n.z());
  return h.Digest();
}

std::string TriangleMesh::HashHex() const {
  return ToHex64(Hash());
}

// ---------------------------------------------------------------------------------------------
// Validation and repair

void MeshRepairOptions::Check() const {
  auto bad = [](const char* field, double v) {
    std::ostringstream os;
    os << "MeshRepairOptions." << field << " must be finite and >= 0, got " << v;
    throw std::invalid_argument(os.str());
  };
  if (!(weld_tolerance >= 0.0) || !std::isfinite(weld_tolerance))
    bad("weld_tolerance", weld_tolerance);
  if (!(degenerate_area >= 0.0) || !std::isfinite(degenerate_area))
    bad("degenerate_area", degenerate_area);
  if (!(degenerate_height >= 0.0) || !std::isfinite(degenerate_height))
    bad("degenerate_height", degenerate_height);
  if (!(base_tolerance >= 0.0) || !std::isfinite(base_tolerance))
    bad("base_tolerance", base_tolerance);
  if (!std::isfinite(base_z)) {
    throw std::invalid_argument("MeshRepairOptions.base_z must be finite, got " +
                                std::to_string(base_z));
  }
}

bool MeshReport::Ok() const {
  // A kept NaN/Inf vertex makes the signed volume non-finite.
  return ClosedExceptBase() && std::isfinite(signed_volume) && signed_volume > 0.0 &&
         output_triangles > 0;
}

std::string MeshReport::Summary() const {
  std::ostringstream os;
  os << "mesh: " << input_vertices << " vertices, " << input_triangles << " triangles in; "
     << output_vertices << " vertices, " << output_triangles << " triangles out; " << components
     << (components == 1 ? " component" : " components") << "; "
     << (ClosedExceptBase() ? "closed except at the base" : "NOT closed except at the base")
     << "; signed volume " << signed_volume << " mm^3\n";
  for (const auto& p : problems) os << "  problem: " << p << "\n";
  for (const auto& f : fixes) os << "  fixed: " << f << "\n";
  return os.str();
}

namespace {

// Step 1: triangles with an index out of range (always removed: nothing else can be done with
// them).
bool RemoveInvalidIndices(TriangleMesh& mesh, MeshReport& r) {
  bool changed = false;
  const int nv = mesh.NumVertices();
  {
    std::vector<Eigen::Vector3i> kept;
    kept.reserve(mesh.triangles.size());
    for (const auto& f : mesh.triangles) {
      if (f.minCoeff() < 0 || f.maxCoeff() >= nv) {
        ++r.invalid_index_triangles;
      } else {
        kept.push_back(f);
      }
    }
    if (r.invalid_index_triangles > 0) {
      r.problems.push_back(Plural(r.invalid_index_triangles, "triangle has", "triangles have") +
                           " a vertex index out of range [0, " + std::to_string(nv) + ")");
      r.fixes.push_back("removed " + Plural(r.invalid_index_triangles, "triangle", "triangles") +
                        " with out-of-range indices");
      mesh.triangles = std::move(kept);
      changed = true;
    }
  }
  return changed;
}

// Step 2: NaN / Inf vertices and the triangles using them.
bool RemoveNonFinite(TriangleMesh& mesh, const MeshRepairOptions& options, MeshReport& r) {
  bool changed = false;
  const int nv = mesh.NumVertices();
  {
    std::vector<char> bad(nv, 0);
    for (int i = 0; i < nv; ++i) {
      if (!IsFinite(mesh.vertices[i])) {
        bad[i] = 1;
        ++r.nonfinite_vertices;
      }
    }
    if (r.nonfinite_vertices > 0) {
      std::vector<Eigen::Vector3i> kept;
      for (const auto& f : mesh.triangles) {
        if (bad[f[0]] || bad[f[1]] || bad[f[2]]) {
          ++r.nonfinite_triangles;
        } else {
          kept.push_back(f);
        }
      }
      r.problems.push_back(Plural(r.nonfinite_vertices, "vertex has", "vertices have") +
                           " NaN/Inf coordinates, used by " +
                           Plural(r.nonfinite_triangles, "triangle", "triangles"));
      if (options.remove_nonfinite) {
        mesh.triangles = std::move(kept);
        r.fixes.push_back("removed " + Plural(r.nonfinite_triangles, "triangle", "triangles") +
                          " using NaN/Inf vertices (this leaves a hole where they were)");
        changed = true;
      }
    }
  }
  return changed;
}

// Step 3: weld coincident vertices (non-finite ones are never welded).
bool Weld(TriangleMesh& mesh, const MeshRepairOptions& options, MeshReport& r) {
  bool changed = false;
  const int nv = mesh.NumVertices();
  if (options.weld) {
    std::vector<int> finite_ids;
    std::vector<Eigen::Vector3d> finite_pts;
    for (int i = 0; i < nv; ++i) {
      if (IsFinite(mesh.vertices[i])) {
        finite_ids.push_back(i);
        finite_pts.push_back(mesh.vertices[i]);
      }
    }
    const std::vector<int> rep_local = WeldMap(finite_pts, options.weld_tolerance);
    std::vector<int> rep(nv);
    std::iota(rep.begin(), rep.end(), 0);
    for (std::size_t k = 0; k < finite_ids.size(); ++k)
      rep[finite_ids[k]] = finite_ids[rep_local[k]];
    for (int i = 0; i < nv; ++i)
      if (rep[i] != i) ++r.welded_vertices;
    if (r.welded_vertices > 0) {
      for (auto& f : mesh.triangles)
        for (int k = 0; k < 3; ++k) f[k] = rep[f[k]];
      std::ostringstream os;
      os << "welded " << Plural(r.welded_vertices, "vertex", "vertices")
         << " onto coincident ones (tolerance " << options.weld_tolerance << " mm)";
      r.fixes.push_back(os.str());
      changed = true;
    }
  }
  return changed;
}

// Step 4: degenerate triangles (repeated vertex or zero area).
bool RemoveDegenerate(TriangleMesh& mesh, const MeshRepairOptions& options, MeshReport& r) {
  bool changed = false;
  {
    std::vector<Eigen::Vector3i> kept;
    kept.reserve(mesh.triangles.size());
    for (const auto& f : mesh.triangles) {
      bool degenerate = f[0] == f[1] || f[1] == f[2] || f[0] == f[2];
      if (!degenerate) {
        const Eigen::Vector3d& a = mesh.vertices[f[0]];
        const Eigen::Vector3d& b = mesh.vertices[f[1]];
        const Eigen::Vector3d& c = mesh.vertices[f[2]];
        const double area = 0.5 * (b - a).cross(c - a).norm();
        const double longest = std::max({(b - a).norm(), (c - b).norm(), (a - c).norm()});
        const double height = longest > 0.0 ? 2.0 * area / longest : 0.0;
        degenerate = std::isfinite(area) &&
                     (area <= options.degenerate_area || height <= options.degenerate_height);
      }
      if (degenerate) {
        ++r.degenerate_triangles;
        if (!options.remove_degenerate) kept.push_back(f);
      } else {
        kept.push_back(f);
      }
    }
    if (r.degenerate_triangles > 0) {
      std::ostringstream os;
      os << Plural(r.degenerate_triangles, "triangle is", "triangles are")
         << " degenerate (repeated vertex, area <= " << options.degenerate_area
         << " mm^2 or height <= " << options.degenerate_height << " mm)";
      r.problems.push_back(os.str());
      if (options.remove_degenerate) {
        r.fixes.push_back("removed " + Plural(r.degenerate_triangles, "degenerate triangle",
                                              "degenerate triangles"));
        mesh.triangles = std::move(kept);
        changed = true;
      }
    }
  }
  return changed;
}

// Step 5: duplicate triangles (same vertex set, either winding); the first occurrence is kept.
bool RemoveDuplicates(TriangleMesh& mesh, const MeshRepairOptions& options, MeshReport& r) {
  bool changed = false;
  {
    const int nt = mesh.NumTriangles();
    std::vector<std::array<int, 4>> keys(nt);
    for (int t = 0; t < nt; ++t) {
      std::array<int, 3> s = {mesh.triangles[t][0], mesh.triangles[t][1], mesh.triangles[t][2]};
      std::sort(s.begin(), s.end());
      keys[t] = {s[0], s[1], s[2], t};
    }
    std::sort(keys.begin(), keys.end());
    std::vector<char> dup(nt, 0);
    for (int i = 1; i < nt; ++i) {
      if (keys[i][0] == keys[i - 1][0] && keys[i][1] == keys[i - 1][1] &&
          keys[i][2] == keys[i - 1][2]) {
        dup[keys[i][3]] = 1;
        ++r.duplicate_triangles;
      }
    }
    if (r.duplicate_triangles > 0) {
      r.problems.push_back(
          Plural(r.duplicate_triangles, "triangle duplicates", "triangles duplicate") +
          " an earlier one (same three vertices)");
      if (options.remove_duplicates) {
        std::vector<Eigen::Vector3i> kept;
        for (int t = 0; t < nt; ++t)
          if (!dup[t]) kept.push_back(mesh.triangles[t]);
        mesh.triangles = std::move(kept);
        r.fixes.push_back("removed " + Plural(r.duplicate_triangles, "duplicate triangle",
                                              "duplicate triangles"));
        changed = true;
      }
    }
  }
  return changed;
}

// Step 6: unreferenced vertices (compacts the vertex array, keeping the order).
bool RemoveUnreferenced(TriangleMesh& mesh, const MeshRepairOptions& options, MeshReport& r) {
  bool changed = false;
  if (options.remove_unreferenced) {
    std::vector<int> remap(mesh.vertices.size(), -1);
    for (const auto& f : mesh.triangles)
      for (int k = 0; k < 3; ++k) remap[f[k]] = 0;
    int next = 0;
    std::vector<Eigen::Vector3d> verts;
    std::vector<Eigen::Vector3d> norms;
    const bool had_normals = mesh.HasNormals();
    for (std::size_t i = 0; i < remap.size(); ++i) {
      if (remap[i] < 0) continue;
      remap[i] = next++;
      verts.push_back(mesh.vertices[i]);
      if (had_normals) norms.push_back(mesh.normals[i]);
    }
    const int removed = static_cast<int>(mesh.vertices.size()) - next;
    // Welded-away vertices are not reported twice.
    r.unreferenced_vertices = std::max(0, removed - r.welded_vertices);
    if (removed > 0) {
      for (auto& f : mesh.triangles)
        for (int k = 0; k < 3; ++k) f[k] = remap[f[k]];
      mesh.vertices = std::move(verts);
      mesh.normals = std::move(norms);
      if (r.unreferenced_vertices > 0) {
        r.fixes.push_back("removed " + Plural(r.unreferenced_vertices, "vertex", "vertices") +
                          " used by no triangle");
      }
      changed = true;
    }
  }
  return changed;
}

// The triangles' edge topology: manifold adjacency with relative winding, and components.
struct Topology {
  int triangles = 0;
  // Adjacency over manifold edges: (neighbour, same_direction).
  std::vector<std::array<std::pair<int, bool>, 3>> adjacency;
  std::vector<int> adjacency_count;
  std::vector<int> comp_of;  // component of each triangle
};

// Step 7: boundary and non-manifold edges, manifold adjacency and components.
Topology EdgeTopology(const TriangleMesh& mesh, const MeshRepairOptions& options, MeshReport& r) {
  const int nt = mesh.NumTriangles();
  std::vector<EdgeUse> uses = SortedEdgeUses(mesh.triangles);
  DisjointSets components(nt);
  // Adjacency over manifold edges: (neighbour, same_direction).
  std::vector<std::array<std::pair<int, bool>, 3>> adjacency(
      nt, {std::pair<int, bool>{-1, false}, {-1, false}, {-1, false}});
  std::vector<int> adjacency_count(nt, 0);
  auto on_base = [&](int v) {
    return std::abs(mesh.vertices[v].z() - options.base_z) <= options.base_tolerance;
  };
  for (std::size_t i = 0; i < uses.size();) {
    std::size_t j = i;
    while (j < uses.size() && uses[j].lo == uses[i].lo && uses[j].hi == uses[i].hi) ++j;
    const std::size_t count = j - i;
    for (std::size_t k = i + 1; k < j; ++k) components.Union(uses[i].triangle, uses[k].triangle);
    if (count == 1) {
      ++r.boundary_edges;
      if (on_base(uses[i].lo) && on_base(uses[i].hi)) {
        ++r.boundary_edges_on_base;
      } else {
        ++r.boundary_edges_off_base;
      }
    } else if (count == 2) {
      const int a = uses[i].triangle;
      const int b = uses[i + 1].triangle;
      if (a != b) {
        const bool same = uses[i].forward == uses[i + 1].forward;
        adjacency[a][adjacency_count[a]++] = {b, same};
        adjacency[b][adjacency_count[b]++] = {a, same};
      }
    } else {
      ++r.non_manifold_edges;
    }
    i = j;
  }

  std::vector<int> comp_of(nt);
  std::vector<int> comp_roots;
  {
    std::unordered_map<int, int> root_index;
    for (int t = 0; t < nt; ++t) {
      const int root = components.Find(t);
      auto it = root_index.find(root);
      if (it == root_index.end()) {
        it = root_index.emplace(root, static_cast<int>(comp_roots.size())).first;
        comp_roots.push_back(root);
      }
      comp_of[t] = it->second;
    }
  }
  r.components = static_cast<int>(comp_roots.size());
  return Topology{nt, std::move(adjacency), std::move(adjacency_count), std::move(comp_of)};
}

// Step 7, continued: consistent winding, BFS per component from its lowest triangle over
// manifold edges.
bool MakeWindingConsistent(TriangleMesh& mesh, const MeshRepairOptions& options,
                           const Topology& topo, MeshReport& r) {
  bool changed = false;
  const int nt = topo.triangles;
  const auto& adjacency = topo.adjacency;
  const auto& adjacency_count = topo.adjacency_count;
  const auto& comp_of = topo.comp_of;
  if (options.make_consistent && nt > 0) {
    std::vector<int> flip(nt, -1);
    std::vector<int> queue;
    queue.reserve(nt);
    std::vector<std::vector<int>> members(r.components);
    for (int t = 0; t < nt; ++t) members[comp_of[t]].push_back(t);
    int conflicts = 0;
    for (int c = 0; c < r.components; ++c) {
      queue.clear();
      // A component may be split by non-manifold edges into manifold patches: seed each.
      int flipped_here = 0;
      std::vector<int> visited_here;
      for (int seed : members[c]) {
        if (flip[seed] >= 0) continue;
        flip[seed] = 0;
        queue.assign(1, seed);
        for (std::size_t q = 0; q < queue.size(); ++q) {
          const int t = queue[q];
          visited_here.push_back(t);
          for (int k = 0; k < adjacency_count[t]; ++k) {
            const auto [u, same] = adjacency[t][k];
            // Consistent neighbours traverse a shared edge in opposite directions.
            const int want = flip[t] ^ (same ? 1 : 0);
            if (flip[u] < 0) {
              flip[u] = want;
              queue.push_back(u);
            } else if (flip[u] != want && u > t) {
              ++conflicts;
            }
          }
        }
      }
      for (int t : visited_here) flipped_here += flip[t];
      // Flip the minority (the outward step below decides the final side).
      const bool invert = 2 * flipped_here > static_cast<int>(visited_here.size());
      for (int t : visited_here) {
        const int f = invert ? 1 - flip[t] : flip[t];
        if (f) {
          std::swap(mesh.triangles[t][1], mesh.triangles[t][2]);
          ++r.flipped_triangles;
        }
      }
    }
    r.inconsistent_edges = conflicts;
    if (r.flipped_triangles > 0) {
      r.problems.push_back(Plural(r.flipped_triangles, "triangle was", "triangles were") +
                           " wound against its neighbours");
      r.fixes.push_back("flipped " + Plural(r.flipped_triangles, "triangle", "triangles") +
                        " for consistent winding");
      changed = true;
    }
  } else {
    for (int t = 0; t < nt; ++t)
      for (int k = 0; k < adjacency_count[t]; ++k)
        if (adjacency[t][k].second && adjacency[t][k].first > t) ++r.inconsistent_edges;
  }
  if (r.inconsistent_edges > 0) {
    r.problems.push_back(Plural(r.inconsistent_edges, "edge has", "edges have") +
                         " inconsistent winding that cannot be fixed (non-orientable surface)");
  }
  return changed;
}

// Step 8: outward orientation per component (signed volume w.r.t. the base plane).
bool OrientOutward(TriangleMesh& mesh, const MeshRepairOptions& options, const Topology& topo,
                   MeshReport& r) {
  bool changed = false;
  const int nt = topo.triangles;
  const auto& comp_of = topo.comp_of;
  {
    std::vector<double> volume(r.components, 0.0);
    std::vector<int> size(r.components, 0);
    for (int t = 0; t < nt; ++t) {
      const auto& f = mesh.triangles[t];
      const Eigen::Vector3d& a = mesh.vertices[f[0]];
      const Eigen::Vector3d& b = mesh.vertices[f[1]];
      const Eigen::Vector3d& c = mesh.vertices[f[2]];
      volume[comp_of[t]] +=
          0.5 * (b - a).cross(c - a).z() * ((a.z() + b.z() + c.z()) / 3.0 - options.base_z);
      ++size[comp_of[t]];
    }
    if (options.orient_outward) {
      int flipped_tris = 0;
      for (int c = 0; c < r.components; ++c) {
        if (volume[c] < 0.0) {
          ++r.reoriented_components;
          flipped_tris += size[c];
        }
      }
      if (r.reoriented_components > 0) {
        for (int t = 0; t < nt; ++t) {
          if (volume[comp_of[t]] < 0.0) std::swap(mesh.triangles[t][1], mesh.triangles[t][2]);
        }
        r.problems.push_back(Plural(r.reoriented_components, "component faces", "components face") +
                             " inward (negative signed volume)");
        r.fixes.push_back("reoriented " +
                          Plural(r.reoriented_components, "component", "components") +
                          " outward (" + Plural(flipped_tris, "triangle", "triangles") + ")");
        changed = true;
      }
    }
  }
  return changed;
}

}  // namespace

MeshReport ValidateAndRepair(TriangleMesh& mesh, const MeshRepairOptions& options) {
  options.Check();
  MeshReport r;
  r.input_vertices = mesh.NumVertices();
  r.input_triangles = mesh.NumTriangles();
  bool changed = RemoveInvalidIndices(mesh, r);
  changed |= RemoveNonFinite(mesh, options, r);
  changed |= Weld(mesh, options, r);
  changed |= RemoveDegenerate(mesh, options, r);
  changed |= RemoveDuplicates(mesh, options, r);
  changed |= RemoveUnreferenced(mesh, options, r);
  const Topology topo = EdgeTopology(mesh, options, r);
  changed |= MakeWindingConsistent(mesh, options, topo, r);
  changed |= OrientOutward(mesh, options, topo, r);
  const int nt = topo.triangles;
  if (r.boundary_edges_off_base > 0) {
    std::ostringstream os;
    os << "not closed: " << Plural(r.boundary_edges_off_base, "boundary edge", "boundary edges")
       << " away from the base plane z = " << options.base_z << " (holes; not fixable here)";
    r.problems.push_back(os.str());
  }
  if (r.non_manifold_edges > 0) {
    r.problems.push_back(Plural(r.non_manifold_edges, "edge is", "edges are") +
                         " non-manifold (shared by 3+ triangles; not fixable here)");
  }
  if (nt == 0) r.problems.push_back("no triangles left");

  if (options.recompute_normals && (changed || !mesh.HasNormals())) mesh.ComputeVertexNormals();
  if (!mesh.normals.empty() && !mesh.HasNormals()) mesh.normals.clear();
  r.signed_volume = mesh.SignedVolume(options.base_z);
  r.output_vertices = mesh.NumVertices();
  r.output_triangles = mesh.NumTriangles();
  return r;
}

// ---------------------------------------------------------------------------------------------
// The base of a closed solid

void BasePlaneOptions::Check() const {
  auto bad = [](const char* field, double v, const char* rule) {
    std::ostringstream os;
    os << "BasePlaneOptions." << field << " " << rule << ", got " << v;
    throw std::invalid_argument(os.str());
  };
  if (!(max_offset >= 0.0) || !std::isfinite(max_offset))
    bad("max_offset", max_offset, "must be finite and >= 0");
  if (!(flatness >= 0.0) || !std::isfinite(flatness))
    bad("flatness", flatness, "must be finite and >= 0");
  if (!(max_tilt_rad >= 0.0) || !(max_tilt_rad < 0.5 * std::numbers::pi)) {
    bad("max_tilt_rad", max_tilt_rad, "must be in [0, pi/2)");
  }
}

int RemoveBaseFaces(TriangleMesh& mesh, const BasePlaneOptions& options) {
  options.Check();
  double z_min = std::numeric_limits<double>::infinity();
  for (const auto& f : mesh.triangles)
    for (int k = 0; k < 3; ++k) z_min = std::min(z_min, mesh.vertices[f[k]].z());
  if (!(std::abs(z_min) <= options.max_offset)) return 0;
  const double cos_tilt = std::cos(options.max_tilt_rad);
  std::vector<Eigen::Vector3i> kept;
  kept.reserve(mesh.triangles.size());
  for (int t = 0; t < mesh.NumTriangles(); ++t) {
    const Eigen::Vector3i& f = mesh.triangles[t];
    bool on_base = -mesh.TriangleNormal(t).z() >= cos_tilt;
    for (int k = 0; k < 3 && on_base; ++k)
      on_base = mesh.vertices[f[k]].z() - z_min <= options.flatness;
    if (!on_base) kept.push_back(f);
  }
  const int removed = mesh.NumTriangles() - static_cast<int>(kept.size());
  if (removed == 0) return 0;
  mesh.triangles = std::move(kept);
  std::vector<int> remap(mesh.vertices.size(), -1);
  for (const auto& f : mesh.triangles)
    for (int k = 0; k < 3; ++k) remap[f[k]] = 0;
  std::vector<Eigen::Vector3d> vertices;
  for (std::size_t i = 0; i < remap.size(); ++i) {
    if (remap[i] < 0) continue;
    remap[i] = static_cast<int>(vertices.size());
    vertices.push_back(mesh.vertices[i]);
  }
  for (auto& f : mesh.triangles)
    for (int k = 0; k < 3; ++k) f[k] = remap[f[k]];
  mesh.vertices = std::move(vertices);
  mesh.ComputeVertexNormals();
  return removed;
}

// ---------------------------------------------------------------------------------------------
// Loading

void MeshLoadOptions::Check() const {
  if (!(scale > 0.0) || !std::isfinite(scale)) {
    throw std::invalid_argument("MeshLoadOptions.scale must be finite and > 0, got " +
                                std::to_string(scale));
  }
  if (!IsFinite(sensor_from_file.translation) || !std::isfinite(sensor_from_file.rotation.norm())) {
    throw std::invalid_argument("MeshLoadOptions.sensor_from_file must be finite");
  }
  repair.Check();
  if (!(import_timeout_s > 0.0) || !std::isfinite(import_timeout_s)) {
    throw std::invalid_argument("MeshLoadOptions.import_timeout_s must be finite and > 0, got " +
                                std::to_string(import_timeout_s));
  }
}

namespace {

// A PLY file's header, checked before assimp reads it: assimp 5.2 loops without end on some
// malformed PLY headers (found by tests/fuzz), and takes an element count at its word. Every line
// up to end_header must be one PLY defines, and no element may claim more entries than the file
// has bytes. Files not starting with "ply" are left to assimp.
void CheckPlyHeader(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  std::string line;
  if (!std::getline(in, line) || (line != "ply" && line != "ply\r")) return;
  std::error_code ec;
  const auto size = std::filesystem::file_size(path, ec);
  auto bad = [&](int number, const std::string& why) {
    throw MeshError("malformed PLY header in " + Quoted(path) + ", line " + std::to_string(number) +
                    ": " + why);
  };
  for (int number = 2; number <= 10000 && std::getline(in, line); ++number) {
    if (!line.empty() && line.back() == '\r') line.pop_back();
    std::istringstream words(line);
    std::string keyword;
    words >> keyword;
    if (keyword == "end_header") return;
    if (keyword == "comment" || keyword == "obj_info") continue;
    if (keyword == "format") {
      std::string kind, version;
      words >> kind >> version;
      if ((kind != "ascii" && kind != "binary_little_endian" && kind != "binary_big_endian") ||
          version != "1.0") {
        bad(number, "unknown format \"" + line + "\"");
      }
    } else if (keyword == "element") {
      std::string name;
      long long count = -1;
      if (!(words >> name >> count) || count < 0) bad(number, "\"" + line + "\"");
      if (!ec && static_cast<unsigned long long>(count) > size) {
        bad(number, "element " + name + " claims " + std::to_string(count) +
                        " entries in a file of " + std::to_string(size) + " bytes");
      }
    } else if (keyword != "property") {
      bad(number, "unknown keyword \"" + keyword + "\"");
    }
  }
  throw MeshError("malformed PLY header in " + Quoted(path) + ": no end_header");
}

}  // namespace

TriangleMesh LoadMesh(const std::filesystem::path& path, const MeshLoadOptions& options,
                      MeshReport* report) {
  options.Check();
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) throw MeshError("mesh file not found: " + Quoted(path));
  if (std::filesystem::is_directory(path, ec)) {
    throw MeshError("mesh path is a directory, not a file: " + Quoted(path));
  }
  {
    std::ifstream probe(path, std::ios::binary);
    if (!probe) throw MeshError("cannot open mesh file " + Quoted(path) + " for reading");
    if (std::filesystem::file_size(path, ec) == 0)
      throw MeshError("mesh file is empty: " + Quoted(path));
  }

  CheckPlyHeader(path);
  TriangleMesh mesh = geometry_internal::ImportMeshFile(path, options.import_timeout_s);
  if (mesh.triangles.empty()) throw MeshError("mesh file " + Quoted(path) + " has no triangles");

  int nonfinite = 0;
  std::vector<char> bad(mesh.vertices.size(), 0);
  for (std::size_t i = 0; i < mesh.vertices.size(); ++i) {
    if (!IsFinite(mesh.vertices[i])) {
      bad[i] = 1;
      ++nonfinite;
    }
  }
  if (nonfinite > 0 && options.reject_nonfinite) {
    int used = 0;
    for (const auto& f : mesh.triangles)
      if (bad[f[0]] || bad[f[1]] || bad[f[2]]) ++used;
    throw MeshError("mesh file " + Quoted(path) + ": " +
                    Plural(nonfinite, "vertex has", "vertices have") + " NaN/Inf coordinates (of " +
                    std::to_string(mesh.vertices.size()) + "), used by " +
                    Plural(used, "triangle", "triangles") + " (of " +
                    std::to_string(mesh.triangles.size()) + ")");
  }

  for (auto& v : mesh.vertices) v = options.sensor_from_file * (options.scale * v);

  MeshReport r;
  if (options.validate || options.reject_open) {
    r = ValidateAndRepair(mesh, options.repair);
  } else {
    r.input_vertices = r.output_vertices = mesh.NumVertices();
    r.input_triangles = r.output_triangles = mesh.NumTriangles();
    mesh.ComputeVertexNormals();
    r.signed_volume = mesh.SignedVolume(options.repair.base_z);
  }
  if (mesh.triangles.empty()) {
    throw MeshError("mesh file " + Quoted(path) + " has no valid triangles left after repair:\n" +
                    r.Summary());
  }
  if (options.reject_open && !r.ClosedExceptBase()) {
    throw MeshError("mesh file " + Quoted(path) + " is not closed except at the base:\n" +
                    r.Summary());
  }
  if (report != nullptr) *report = std::move(r);
  return mesh;
}

// ---------------------------------------------------------------------------------------------
// Writing

namespace {

// Exports `mesh` with assimp's exporter `format` ("stlb", "stl", "objnomtl", "ply");
// coordinates become float32 (assimp's ai_real).
void Export(const std::filesystem::path& path, const TriangleMesh& mesh, const char* format) {
  auto fill = [&](aiMesh& out) {
    out.mPrimitiveTypes = aiPrimitiveType_TRIANGLE;
    out.mNumVertices = static_cast<unsigned int>(mesh.vertices.size());
    out.mVertices = new aiVector3D[mesh.vertices.size()];
    for (std::size_t i = 0; i < mesh.vertices.size(); ++i) {
      const Eigen::Vector3d& v = mesh.vertices[i];
      out.mVertices[i] = aiVector3D(static_cast<ai_real>(v.x()), static_cast<ai_real>(v.y()),
                                    static_cast<ai_real>(v.z()));
    }
    if (mesh.HasNormals()) {
      out.mNormals = new aiVector3D[mesh.normals.size()];
      for (std::size_t i = 0; i < mesh.normals.size(); ++i) {
        const Eigen::Vector3d& n = mesh.normals[i];
        out.mNormals[i] = aiVector3D(static_cast<ai_real>(n.x()), static_cast<ai_real>(n.y()),
                                     static_cast<ai_real>(n.z()));
      }
    }
    out.mNumFaces = static_cast<unsigned int>(mesh.triangles.size());
    out.mFaces = new aiFace[mesh.triangles.size()];
    for (std::size_t t = 0; t < mesh.triangles.size(); ++t) {
      const Eigen::Vector3i& f = mesh.triangles[t];
      out.mFaces[t].mNumIndices = 3;
      out.mFaces[t].mIndices =
          new unsigned int[3]{static_cast<unsigned int>(f[0]), static_cast<unsigned int>(f[1]),
                              static_cast<unsigned int>(f[2])};
    }
  };
  const std::string error = geometry_internal::ExportOneMesh(path, format, fill);
  if (!error.empty()) throw MeshError("cannot write " + Quoted(path) + ": " + error);
}

}  // namespace

void WriteStlBinary(const std::filesystem::path& path, const TriangleMesh& mesh) {
  Export(path, mesh, "stlb");
}

void WriteStlAscii(const std::filesystem::path& path, const TriangleMesh& mesh) {
  Export(path, mesh, "stl");
}

void WriteObj(const std::filesystem::path& path, const TriangleMesh& mesh) {
  Export(path, mesh, "objnomtl");
}

void WritePlyAscii(const std::filesystem::path& path, const TriangleMesh& mesh) {
  Export(path, mesh, "ply");
}

void WriteMesh(const std::filesystem::path& path, const TriangleMesh& mesh) {
  std::string ext = path.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return std::tolower(c); });
  if (ext == ".stl") {
    WriteStlBinary(path, mesh);
  } else if (ext == ".obj") {
    WriteObj(path, mesh);
  } else if (ext == ".ply") {
    WritePlyAscii(path, mesh);
  } else {
    throw MeshError("cannot write mesh " + Quoted(path) + ": unknown extension '" + ext +
                    "' (use .stl, .obj or .ply)");
  }
}

}  // namespace gs360
