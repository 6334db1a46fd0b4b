#include "sim/gel_deformation.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <string>
#include <unordered_map>

#include "base/field_error.h"

namespace gs360 {
namespace {

[[noreturn]] void ThrowField(const std::string& field, double value, const std::string& why) {
  ThrowFieldError("GelDeformationOptions." + field, value, why);
}

// Barycentrics (of a, b, c) of the point of triangle (a, b, c) closest to p (Ericson,
// Real-Time Collision Detection 5.1.5).
Eigen::Vector3d ClosestBarycentrics(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                                    const Eigen::Vector3d& b, const Eigen::Vector3d& c) {
  const Eigen::Vector3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0.0 && d2 <= 0.0) return {1.0, 0.0, 0.0};
  const Eigen::Vector3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0.0 && d4 <= d3) return {0.0, 1.0, 0.0};
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) {
    const double v = d1 / (d1 - d3);
    return {1.0 - v, v, 0.0};
  }
  const Eigen::Vector3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0.0 && d5 <= d6) return {0.0, 0.0, 1.0};
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) {
    const double w = d2 / (d2 - d6);
    return {1.0 - w, 0.0, w};
  }
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {
    const double w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
    return {0.0, 1.0 - w, w};
  }
  const double denom = 1.0 / (va + vb + vc);
  const double v = vb * denom, w = vc * denom;
  return {1.0 - v - w, v, w};
}

double PointTriangleDistance2(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                              const Eigen::Vector3d& b, const Eigen::Vector3d& c) {
  const Eigen::Vector3d w = ClosestBarycentrics(p, a, b, c);
  return (p - (w[0] * a + w[1] * b + w[2] * c)).squaredNorm();
}

constexpr int kMaxSubdivisions = 256;  // a power of two

}  // namespace

void GelDeformationOptions::Check() const {
  if (!std::isfinite(elastic_length) || elastic_length < 0.0) {
    ThrowField("elastic_length", elastic_length, "must be finite and >= 0");
  }
  if (!std::isfinite(bulge_fraction) || bulge_fraction < 0.0 || bulge_fraction > 0.5) {
    ThrowField("bulge_fraction", bulge_fraction, "must be in [0, 0.5]");
  }
  if (!std::isfinite(bulge_extent) || !(bulge_extent > 0.0)) {
    ThrowField("bulge_extent", bulge_extent, "must be finite and > 0");
  }
  if (!(max_edge >= 0.005 && max_edge <= 1.0)) {
    ThrowField("max_edge", max_edge, "must be in [0.005, 1] mm");
  }
  if (!(bulge_max_edge >= 0.005 && bulge_max_edge <= 1.0)) {
    ThrowField("bulge_max_edge", bulge_max_edge, "must be in [0.005, 1] mm");
  }
}

GelDeformationOptions GelDeformationOptions::Rigid() {
  GelDeformationOptions o;
  o.elastic_length = 0.0;
  o.bulge_fraction = 0.0;
  return o;
}

BallIndentation::BallIndentation(const Eigen::Vector3d& ball_center, double ball_radius,
                                 const GelDeformationOptions& options)
    : center_(ball_center), radius_(ball_radius), options_(options) {
  options_.Check();
  if (!std::isfinite(ball_radius) || !(ball_radius > 0.0)) {
    throw std::invalid_argument("BallIndentation: ball radius " + std::to_string(ball_radius) +
                                " must be finite and > 0");
  }
  if (!ball_center.allFinite()) {
    throw std::invalid_argument("BallIndentation: ball centre is not finite");
  }
}

double BallIndentation::Penetration(const Eigen::Vector3d& x0, const Eigen::Vector3d& n0) const {
  const Eigen::Vector3d d = x0 - center_;
  const double b = n0.dot(d);  // < 0 when the ball lies outward (along +n0) of x0
  const double dd = d.squaredNorm();
  const double r2 = radius_ * radius_;
  const double disc = b * b - dd + r2;
  // Inside the ball: the normal line's exit point on the inner side (rigid depth along -n0).
  if (dd < r2) return b + std::sqrt(std::max(0.0, disc));
  if (b < 0.0) {
    // Ball outward: minus the gap along +n0 to the ball, continued past the tangent line by the
    // line's miss distance.
    if (disc >= 0.0) return b + std::sqrt(disc);
    return b - (std::sqrt(std::max(0.0, dd - b * b)) - radius_);
  }
  // Ball inward of a point outside it (e.g. the far side of a thin tip): never in contact.
  return (radius_ - std::sqrt(dd)) - b;
}

double BallIndentation::SoftDepth(double p) const {
  const double w = options_.elastic_length;
  if (w <= 0.0) return std::max(0.0, p);
  if (p <= -w) return 0.0;
  if (p >= w) return p;
  return (p + w) * (p + w) / (4.0 * w);
}

double BallIndentation::Bulge(const Eigen::Vector3d& x0, double max_depth) const {
  if (options_.bulge_fraction <= 0.0 || max_depth <= 0.0) return 0.0;
  const double u = ((x0 - center_).norm() - radius_) / options_.bulge_extent;
  if (!(u > 0.0 && u < 1.0)) return 0.0;
  const double s = u * (1.0 - u);
  return options_.bulge_fraction * max_depth * 16.0 * s * s;
}

double BallIndentation::InfluenceRadius() const {
  double reach = options_.elastic_length;
  if (options_.bulge_fraction > 0.0) reach = std::max(reach, options_.bulge_extent);
  return radius_ + reach;
}

GelPatchBuilder::GelPatchBuilder(const TriangleMesh& gel_mesh, const GelDeformationOptions& options)
    : mesh_(gel_mesh), options_(options) {
  options_.Check();
  if (!mesh_.HasNormals()) {
    throw std::invalid_argument("GelPatchBuilder: the gel mesh has no vertex normals");
  }
  const int nt = mesh_.NumTriangles();
  Eigen::AlignedBox3d bounds = mesh_.Bounds();
  if (nt == 0 || bounds.isEmpty()) {
    grid_origin_ = Eigen::Vector3d::Zero();
    grid_dims_ = Eigen::Vector3i::Ones();
    cell_start_.assign(2, 0);
    return;
  }
  // Cell ~ 2 average edge lengths (at least 0.25 mm), at most ~2M cells.
  double edge_sum = 0.0;
  for (int t = 0; t < nt; ++t) {
    const auto& tri = mesh_.triangles[t];
    edge_sum += (mesh_.vertices[tri[1]] - mesh_.vertices[tri[0]]).norm();
  }
  cell_ = std::max(0.25, 2.0 * edge_sum / nt);
  const Eigen::Vector3d extent = bounds.sizes();
  while (true) {
    grid_dims_ = ((extent / cell_).array().floor() + 1.0).cast<int>().matrix();
    if (static_cast<double>(grid_dims_.x()) * grid_dims_.y() * grid_dims_.z() <= 2e6) break;
    cell_ *= 1.5;
  }
  grid_origin_ = bounds.min();
  const int cells = grid_dims_.x() * grid_dims_.y() * grid_dims_.z();
  auto cell_range = [&](int t, Eigen::Vector3i* lo, Eigen::Vector3i* hi) {
    const auto& tri = mesh_.triangles[t];
    Eigen::AlignedBox3d box;
    for (int k = 0; k < 3; ++k) box.extend(mesh_.vertices[tri[k]]);
    for (int a = 0; a < 3; ++a) {
      (*lo)[a] = std::clamp(static_cast<int>((box.min()[a] - grid_origin_[a]) / cell_), 0,
                            grid_dims_[a] - 1);
      (*hi)[a] = std::clamp(static_cast<int>((box.max()[a] - grid_origin_[a]) / cell_), 0,
                            grid_dims_[a] - 1);
    }
  };
  cell_start_.assign(cells + 1, 0);
  for (int pass = 0; pass < 2; ++pass) {
    std::vector<int> fill;
    if (pass == 1) {
      for (int c = 0; c < cells; ++c) cell_start_[c + 1] += cell_start_[c];
      cell_items_.resize(cell_start_[cells]);
      fill.assign(cell_start_.begin(), cell_start_.end() - 1);
    }
    for (int t = 0; t < nt; ++t) {
      Eigen::Vector3i lo, hi;
      cell_range(t, &lo, &hi);
      for (int z = lo.z(); z <= hi.z(); ++z) {
        for (int y = lo.y(); y <= hi.y(); ++y) {
          for (int x = lo.x(); x <= hi.x(); ++x) {
            const int c = (z * grid_dims_.y() + y) * grid_dims_.x() + x;
            if (pass == 0) {
              ++cell_start_[c + 1];
            } else {
              cell_items_[fill[c]++] = t;
            }
          }
        }
      }
    }
  }
}

std::vector<int> GelPatchBuilder::TrianglesNear(const Eigen::Vector3d& center,
                                                double radius) const {
  std::vector<int> candidates;
  if (cell_items_.empty()) return candidates;
  Eigen::Vector3i lo, hi;
  for (int a = 0; a < 3; ++a) {
    const double l = (center[a] - radius - grid_origin_[a]) / cell_;
    const double h = (center[a] + radius - grid_origin_[a]) / cell_;
    if (h < 0.0 || l >= grid_dims_[a]) return candidates;
    lo[a] = std::clamp(static_cast<int>(std::floor(l)), 0, grid_dims_[a] - 1);
    hi[a] = std::clamp(static_cast<int>(std::floor(h)), 0, grid_dims_[a] - 1);
  }
  for (int z = lo.z(); z <= hi.z(); ++z) {
    for (int y = lo.y(); y <= hi.y(); ++y) {
      for (int x = lo.x(); x <= hi.x(); ++x) {
        const int c = (z * grid_dims_.y() + y) * grid_dims_.x() + x;
        candidates.insert(candidates.end(), cell_items_.begin() + cell_start_[c],
                          cell_items_.begin() + cell_start_[c + 1]);
      }
    }
  }
  std::sort(candidates.begin(), candidates.end());
  candidates.erase(std::unique(candidates.begin(), candidates.end()), candidates.end());
  std::vector<int> result;
  const double r2 = radius * radius;
  for (const int t : candidates) {
    const auto& tri = mesh_.triangles[t];
    if (PointTriangleDistance2(center, mesh_.vertices[tri[0]], mesh_.vertices[tri[1]],
                               mesh_.vertices[tri[2]]) < r2) {
      result.push_back(t);
    }
  }
  return result;
}

namespace {

// Key of the coarse edge (a, b), either direction.
std::uint64_t EdgeKey(int a, int b) {
  const int lo = std::min(a, b), hi = std::max(a, b);
  return (static_cast<std::uint64_t>(lo) << 32) | static_cast<std::uint32_t>(hi);
}

// Lattice point (i, j) of a triangle subdivided n times, in row order.
int LatticeIndex(int n, int i, int j) {
  return j * (n + 1) - j * (j - 1) / 2 + i;
}

// Subdivision per coarse triangle: a power of two, finer in the contact zone (within
// `contact_zone` of the ball centre). *max_subdivisions: the largest.
std::vector<int> Subdivisions(const TriangleMesh& mesh, const std::vector<int>& coarse,
                              const Eigen::Vector3d& ball_center, double contact_zone,
                              const GelDeformationOptions& options, int* max_subdivisions) {
  const auto& V = mesh.vertices;
  const int nc = static_cast<int>(coarse.size());
  std::vector<int> tri_n(nc);
  for (int ct = 0; ct < nc; ++ct) {
    const auto& tri = mesh.triangles[coarse[ct]];
    double longest = 0.0;
    for (int k = 0; k < 3; ++k)
      longest = std::max(longest, (V[tri[(k + 1) % 3]] - V[tri[k]]).norm());
    const double d2 = PointTriangleDistance2(ball_center, V[tri[0]], V[tri[1]], V[tri[2]]);
    const double target =
        d2 < contact_zone * contact_zone ? options.max_edge : options.bulge_max_edge;
    int n = 1;
    while (n < kMaxSubdivisions && longest / n > target) n *= 2;
    tri_n[ct] = n;
    *max_subdivisions = std::max(*max_subdivisions, n);
  }
  return tri_n;
}

// Per coarse edge (lo, hi): the coarser of its two sides.
std::unordered_map<std::uint64_t, int> EdgeSubdivisions(const TriangleMesh& mesh,
                                                        const std::vector<int>& coarse,
                                                        const std::vector<int>& tri_n) {
  const int nc = static_cast<int>(coarse.size());
  std::unordered_map<std::uint64_t, int> edge_n;
  edge_n.reserve(3 * nc);
  for (int ct = 0; ct < nc; ++ct) {
    const auto& tri = mesh.triangles[coarse[ct]];
    for (int k = 0; k < 3; ++k) {
      auto [it, inserted] = edge_n.try_emplace(EdgeKey(tri[k], tri[(k + 1) % 3]), tri_n[ct]);
      if (!inserted) it->second = std::min(it->second, tri_n[ct]);
    }
  }
  return edge_n;
}

// A refined vertex on a finer triangle's edge between two shared points of the coarser edge:
// interpolated (at s) between vertices a and b.
struct Snap {
  int vertex, a, b;
  double s;
};

// The refined vertices of the coarse triangles. "Free" vertices get the model's displacement;
// "snapped" ones are interpolated between two free vertices afterwards.
struct Lattices {
  std::vector<Eigen::Vector3d> rest;     // undeformed position
  std::vector<Eigen::Vector3d> normal0;  // smooth normal
  std::vector<Snap> snaps;
  std::vector<int> start;  // per coarse triangle: its first lattice point in ids (and the end)
  std::vector<int> ids;    // refined vertex of each lattice point (LatticeIndex order)
};

// Builds the Lattices (once per builder): vertices shared along coarse edges and at corners are
// made once.
class LatticeBuilder {
 public:
  LatticeBuilder(const TriangleMesh& mesh, const std::unordered_map<std::uint64_t, int>& edge_n)
      : mesh_(mesh), vertices_(mesh.vertices), normals_(mesh.normals), edge_n_(edge_n) {}

  Lattices Build(const std::vector<int>& coarse, const std::vector<int>& tri_n) {
    const int nc = static_cast<int>(coarse.size());
    out_.start.assign(nc + 1, 0);
    for (int ct = 0; ct < nc; ++ct)
      out_.start[ct + 1] = out_.start[ct] + (tri_n[ct] + 1) * (tri_n[ct] + 2) / 2;
    out_.ids.resize(out_.start[nc]);
    for (int ct = 0; ct < nc; ++ct) {
      const auto& tri = mesh_.triangles[coarse[ct]];
      const int A = tri[0], B = tri[1], C = tri[2];
      const int n = tri_n[ct];
      const double inv_n = 1.0 / n;
      int* out = out_.ids.data() + out_.start[ct];
      for (int j = 0; j <= n; ++j) {
        for (int i = 0; i + j <= n; ++i) {
          int id;
          if (i == 0 && j == 0) {
            id = Corner(A);
          } else if (i == n) {
            id = Corner(B);
          } else if (j == n) {
            id = Corner(C);
          } else if (j == 0) {
            id = EdgePoint(A, B, n, i);
          } else if (i == 0) {
            id = EdgePoint(A, C, n, j);
          } else if (i + j == n) {
            id = EdgePoint(B, C, n, j);
          } else {
            id = static_cast<int>(out_.rest.size());
            const double wa = static_cast<double>(n - i - j), wb = i, wc = j;
            out_.rest.push_back((wa * vertices_[A] + wb * vertices_[B] + wc * vertices_[C]) *
                                inv_n);
            out_.normal0.push_back(
                (wa * normals_[A] + wb * normals_[B] + wc * normals_[C]).normalized());
          }
          out[LatticeIndex(n, i, j)] = id;
        }
      }
    }
    return std::move(out_);
  }

 private:
  int Corner(int v) {
    auto [it, inserted] = corner_id_.try_emplace(v, static_cast<int>(out_.rest.size()));
    if (inserted) {
      out_.rest.push_back(vertices_[v]);
      out_.normal0.push_back(normals_[v].normalized());
    }
    return it->second;
  }

  // Shared vertex j (0..ne) of the edge (lo, hi), counted from lo.
  int SharedPoint(int lo, int hi, int ne, int j) {
    if (j == 0) return Corner(lo);
    if (j == ne) return Corner(hi);
    auto [it, inserted] =
        edge_base_.try_emplace(EdgeKey(lo, hi), static_cast<int>(out_.rest.size()));
    if (inserted) {
      const double inv = 1.0 / ne;
      for (int m = 1; m < ne; ++m) {
        const double a = static_cast<double>(ne - m), b = static_cast<double>(m);
        out_.rest.push_back((a * vertices_[lo] + b * vertices_[hi]) * inv);
        out_.normal0.push_back((a * normals_[lo] + b * normals_[hi]).normalized());
      }
    }
    return it->second + (j - 1);
  }

  // Lattice point k (0..n) of triangle edge p -> q (n = that triangle's subdivision).
  int EdgePoint(int p, int q, int n, int k) {
    const int lo = std::min(p, q), hi = std::max(p, q);
    const int k_lo = p == lo ? k : n - k;
    const int ne = edge_n_.at(EdgeKey(p, q));
    const int step = n / ne;  // both powers of two, ne <= n
    if (k_lo % step == 0) return SharedPoint(lo, hi, ne, k_lo / step);
    const int j = k_lo / step;
    Snap snap;
    snap.a = SharedPoint(lo, hi, ne, j);
    snap.b = SharedPoint(lo, hi, ne, j + 1);
    snap.s = static_cast<double>(k_lo % step) / step;
    snap.vertex = static_cast<int>(out_.rest.size());  // after SharedPoint may have added some
    out_.rest.push_back((1.0 - snap.s) * out_.rest[snap.a] + snap.s * out_.rest[snap.b]);
    out_.normal0.push_back(
        ((1.0 - snap.s) * out_.normal0[snap.a] + snap.s * out_.normal0[snap.b]).normalized());
    out_.snaps.push_back(snap);
    return snap.vertex;
  }

  const TriangleMesh& mesh_;
  const std::vector<Eigen::Vector3d>& vertices_;
  const std::vector<Eigen::Vector3d>& normals_;
  const std::unordered_map<std::uint64_t, int>& edge_n_;
  Lattices out_;
  std::unordered_map<int, int> corner_id_;
  std::unordered_map<std::uint64_t, int> edge_base_;
};

// Per refined vertex: p, delta and the moved position.
struct Displacement {
  std::vector<double> penetration, delta;
  std::vector<Eigen::Vector3d> moved;
  double max_depth = 0.0;  // largest p
};

// The model at free vertices, interpolation at snapped ones.
Displacement Displace(const BallIndentation& indentation, const Lattices& lat) {
  const std::size_t nv = lat.rest.size();
  std::vector<std::uint8_t> snapped(nv, 0);
  for (const Snap& snap : lat.snaps) snapped[snap.vertex] = 1;
  Displacement d;
  d.penetration.assign(nv, 0.0);
  d.delta.assign(nv, 0.0);
  for (std::size_t v = 0; v < nv; ++v) {
    if (snapped[v]) continue;
    d.penetration[v] = indentation.Penetration(lat.rest[v], lat.normal0[v]);
    d.max_depth = std::max(d.max_depth, d.penetration[v]);
  }
  for (std::size_t v = 0; v < nv; ++v) {
    if (snapped[v]) continue;
    d.delta[v] =
        indentation.SoftDepth(d.penetration[v]) - indentation.Bulge(lat.rest[v], d.max_depth);
  }
  d.moved.resize(nv);
  for (std::size_t v = 0; v < nv; ++v) {
    if (!snapped[v]) d.moved[v] = lat.rest[v] - d.delta[v] * lat.normal0[v];
  }
  for (const Snap& snap : lat.snaps) {
    const double s = snap.s;
    d.penetration[snap.vertex] = (1.0 - s) * d.penetration[snap.a] + s * d.penetration[snap.b];
    d.delta[snap.vertex] = (1.0 - s) * d.delta[snap.a] + s * d.delta[snap.b];
    d.moved[snap.vertex] = (1.0 - s) * d.moved[snap.a] + s * d.moved[snap.b];
  }
  return d;
}

// Keeps the coarse triangles that move: emits their sub-triangles into the patch with compacted
// vertex ids.
void EmitMovedTriangles(const std::vector<int>& coarse, const std::vector<int>& tri_n,
                        const Lattices& lat, const Displacement& d, DisplacedPatch* patch) {
  std::vector<int> remap(lat.rest.size(), -1);
  for (int ct = 0; ct < static_cast<int>(coarse.size()); ++ct) {
    const int n = tri_n[ct];
    const int* ids = lat.ids.data() + lat.start[ct];
    const int count = lat.start[ct + 1] - lat.start[ct];
    bool any_moved = false;
    for (int k = 0; k < count && !any_moved; ++k) any_moved = d.delta[ids[k]] != 0.0;
    if (!any_moved) continue;
    patch->replaced_triangles.push_back(coarse[ct]);
    auto vid = [&](int i, int j) {
      const int g = ids[LatticeIndex(n, i, j)];
      if (remap[g] < 0) {
        remap[g] = static_cast<int>(patch->rest_vertices.size());
        patch->rest_vertices.push_back(lat.rest[g]);
        patch->rest_normals.push_back(lat.normal0[g]);
        patch->displacement.push_back(d.delta[g]);
        patch->penetration.push_back(d.penetration[g]);
        patch->mesh.vertices.push_back(d.moved[g]);
      }
      return remap[g];
    };
    for (int j = 0; j < n; ++j) {
      for (int i = 0; i + j < n; ++i) {
        patch->mesh.triangles.emplace_back(vid(i, j), vid(i + 1, j), vid(i, j + 1));
        if (i + j < n - 1) {
          patch->mesh.triangles.emplace_back(vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1));
        }
      }
    }
  }
}

// Contact point: the undeformed surface point of the replaced triangles closest to the ball
// centre.
void SetContactPoint(const TriangleMesh& mesh, const Eigen::Vector3d& ball_center,
                     DisplacedPatch* patch) {
  const auto& V = mesh.vertices;
  const auto& N = mesh.normals;
  double closest = std::numeric_limits<double>::infinity();
  for (const int t : patch->replaced_triangles) {
    const auto& tri = mesh.triangles[t];
    const Eigen::Vector3d w = ClosestBarycentrics(ball_center, V[tri[0]], V[tri[1]], V[tri[2]]);
    const Eigen::Vector3d x = w[0] * V[tri[0]] + w[1] * V[tri[1]] + w[2] * V[tri[2]];
    const double d2 = (x - ball_center).squaredNorm();
    if (d2 < closest) {
      closest = d2;
      patch->contact_point = x;
      patch->contact_normal = (w[0] * N[tri[0]] + w[1] * N[tri[1]] + w[2] * N[tri[2]]).normalized();
    }
  }
}

// Shading normals: n0 rotated by the change of the refined mesh's area-weighted vertex normal.
// Also flags the triangles that moved.
void SetShadingNormals(DisplacedPatch* patch) {
  const std::size_t pv = patch->rest_vertices.size();
  std::vector<Eigen::Vector3d> sum_rest(pv, Eigen::Vector3d::Zero());
  std::vector<Eigen::Vector3d> sum_moved(pv, Eigen::Vector3d::Zero());
  patch->triangle_displaced.resize(patch->mesh.triangles.size());
  for (std::size_t t = 0; t < patch->mesh.triangles.size(); ++t) {
    const Eigen::Vector3i& f = patch->mesh.triangles[t];
    const auto& R = patch->rest_vertices;
    const auto& M = patch->mesh.vertices;
    const Eigen::Vector3d nr = (R[f[1]] - R[f[0]]).cross(R[f[2]] - R[f[0]]);
    const Eigen::Vector3d nm = (M[f[1]] - M[f[0]]).cross(M[f[2]] - M[f[0]]);
    for (int k = 0; k < 3; ++k) {
      sum_rest[f[k]] += nr;
      sum_moved[f[k]] += nm;
    }
    patch->triangle_displaced[t] = patch->displacement[f[0]] != 0.0 ||
                                   patch->displacement[f[1]] != 0.0 ||
                                   patch->displacement[f[2]] != 0.0;
  }
  patch->mesh.normals.resize(pv);
  for (std::size_t v = 0; v < pv; ++v) {
    if (sum_rest[v] == sum_moved[v] || sum_rest[v].squaredNorm() == 0.0 ||
        sum_moved[v].squaredNorm() == 0.0) {
      patch->mesh.normals[v] = patch->rest_normals[v];
    } else {
      const Eigen::Quaterniond q =
          Eigen::Quaterniond::FromTwoVectors(sum_rest[v].normalized(), sum_moved[v].normalized());
      patch->mesh.normals[v] = (q * patch->rest_normals[v]).normalized();
    }
  }
}

}  // namespace

DisplacedPatch GelPatchBuilder::Build(const Eigen::Vector3d& ball_center,
                                      double ball_radius) const {
  DisplacedPatch patch;
  const BallIndentation indentation(ball_center, ball_radius, options_);
  const std::vector<int> coarse = TrianglesNear(ball_center, indentation.InfluenceRadius());
  if (coarse.empty()) return patch;
  const double contact_zone = ball_radius + options_.elastic_length + 0.1;
  const std::vector<int> tri_n =
      Subdivisions(mesh_, coarse, ball_center, contact_zone, options_, &patch.max_subdivisions);
  const std::unordered_map<std::uint64_t, int> edge_n = EdgeSubdivisions(mesh_, coarse, tri_n);
  const Lattices lat = LatticeBuilder(mesh_, edge_n).Build(coarse, tri_n);
  const Displacement d = Displace(indentation, lat);
  EmitMovedTriangles(coarse, tri_n, lat, d, &patch);
  if (patch.replaced_triangles.empty()) return patch;
  patch.max_depth = d.max_depth;
  SetContactPoint(mesh_, ball_center, &patch);
  patch.replaced.assign(mesh_.NumTriangles(), 0);
  for (const int t : patch.replaced_triangles) patch.replaced[t] = 1;
  for (const double delta : patch.displacement) {
    patch.max_displacement = std::max(patch.max_displacement, delta);
  }
  SetShadingNormals(&patch);
  return patch;
}

}  // namespace gs360
