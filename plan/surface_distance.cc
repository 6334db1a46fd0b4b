#include "plan/surface_distance.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numeric>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <vector>

namespace gs360 {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

// --- Revolution backend --------------------------------------------------------------------------

struct Box2 {
  Eigen::Vector2d lo{kInf, kInf};
  Eigen::Vector2d hi{-kInf, -kInf};
  void Extend(const Eigen::Vector2d& p) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  double SquaredDistance(const Eigen::Vector2d& p) const {
    const Eigen::Vector2d d = (lo - p).cwiseMax(p - hi).cwiseMax(0.0);
    return d.squaredNorm();
  }
};

struct Node2 {
  Box2 box;
  int lo = 0, hi = 0;  // segment range [lo, hi)
  int left = -1, right = -1;
};

}  // namespace

struct SurfaceDistance::Impl {
  using Closest = SurfaceDistance::Closest;
  virtual ~Impl() = default;
  virtual double Signed(const Eigen::Vector3d& p, Eigen::Vector3d* closest) const = 0;
  virtual Closest ClosestPoint(const Eigen::Vector3d& p) const = 0;
  Eigen::AlignedBox3d bounds;
  double bounding_radius = 0.0;
};

namespace {

class RevolutionImpl final : public SurfaceDistance::Impl {
 public:
  RevolutionImpl(std::shared_ptr<const RevolutionProfile> profile, int segments)
      : profile_(std::move(profile)) {
    verts_.resize(segments + 1);
    params_.resize(segments + 1);
    const double length = profile_->ArcLength();
    for (int i = 0; i <= segments; ++i) {
      const double t = i == 0          ? 0.0
                       : i == segments ? 1.0
                                       : profile_->ParameterAtArcLength(length * i / segments);
      params_[i] = t;
      verts_[i] = profile_->Point(t);
    }
    verts_.back().x() = 0.0;  // the tip is on the axis
    for (int i = 1; i <= segments; ++i) {
      if (!(verts_[i].y() > verts_[i - 1].y())) {
        // Flat pieces of the table (z not strictly increasing) would break RadiusAt: nudge.
        verts_[i].y() = std::nextafter(verts_[i - 1].y(), kInf);
      }
    }
    height_ = verts_.back().y();
    double rmax = 0.0;
    for (const auto& v : verts_) rmax = std::max(rmax, v.x());
    bounding_radius = rmax;
    bounds = Eigen::AlignedBox3d(Eigen::Vector3d(-rmax, -rmax, verts_.front().y()),
                                 Eigen::Vector3d(rmax, rmax, height_));
    Build(0, segments);
    // Sparse table for range maxima of the vertex radii.
    const int n = static_cast<int>(verts_.size());
    sparse_.emplace_back(n);
    for (int i = 0; i < n; ++i) sparse_[0][i] = verts_[i].x();
    for (int k = 1; (1 << k) <= n; ++k) {
      sparse_.emplace_back(n - (1 << k) + 1);
      for (int i = 0; i + (1 << k) <= n; ++i) {
        sparse_[k][i] = std::max(sparse_[k - 1][i], sparse_[k - 1][i + (1 << (k - 1))]);
      }
    }
  }

  double Signed(const Eigen::Vector3d& p, Eigen::Vector3d* closest) const override {
    int seg = 0;
    double u = 0.0;
    return Query(p, closest, &seg, &u);
  }

  Closest ClosestPoint(const Eigen::Vector3d& p) const override {
    int seg = 0;
    double u = 0.0;
    Closest c;
    const double polyline = Query(p, nullptr, &seg, &u);
    const double rho = std::hypot(p.x(), p.y());
    const Eigen::Vector2d q(rho, p.z());
    // Refine on the exact profile around the polyline's answer (golden section over the
    // neighbouring segments' parameter range).
    const int last = static_cast<int>(params_.size()) - 1;
    double lo = params_[std::max(seg - 1, 0)], hi = params_[std::min(seg + 2, last)];
    const double g = 0.5 * (std::sqrt(5.0) - 1.0);
    double x1 = hi - g * (hi - lo), x2 = lo + g * (hi - lo);
    double f1 = (profile_->Point(x1) - q).squaredNorm(),
           f2 = (profile_->Point(x2) - q).squaredNorm();
    for (int it = 0; it < 48 && hi - lo > 1e-15; ++it) {
      if (f1 < f2) {
        hi = x2;
        x2 = x1;
        f2 = f1;
        x1 = hi - g * (hi - lo);
        f1 = (profile_->Point(x1) - q).squaredNorm();
      } else {
        lo = x1;
        x1 = x2;
        f1 = f2;
        x2 = lo + g * (hi - lo);
        f2 = (profile_->Point(x2) - q).squaredNorm();
      }
    }
    double t = 0.5 * (lo + hi);
    const double t_poly = params_[seg] + u * (params_[seg + 1] - params_[seg]);
    if ((profile_->Point(t_poly) - q).squaredNorm() < (profile_->Point(t) - q).squaredNorm()) {
      t = t_poly;
    }
    const double phi = rho > 0.0 ? std::atan2(p.y(), p.x()) : 0.0;
    c.point = profile_->SurfacePoint(t, phi);
    c.normal = profile_->SurfaceNormal(t, phi);
    const double d = (profile_->Point(t) - q).norm();
    c.signed_distance = polyline < 0.0 ? -d : d;
    return c;
  }

  double Query(const Eigen::Vector3d& p, Eigen::Vector3d* closest, int* best_seg,
               double* best_u) const {
    const double rho = std::hypot(p.x(), p.y());
    const Eigen::Vector2d q(rho, p.z());
    Eigen::Vector2d best_point = verts_.front();
    double best = kInf;
    int stack[64];
    int top = 0;
    stack[top++] = 0;
    while (top > 0) {
      const Node2& node = nodes_[stack[--top]];
      if (node.box.SquaredDistance(q) >= best) continue;
      if (node.left < 0) {
        for (int s = node.lo; s < node.hi; ++s) {
          const Eigen::Vector2d& a = verts_[s];
          const Eigen::Vector2d ab = verts_[s + 1] - a;
          const double len2 = ab.squaredNorm();
          const double u = len2 > 0.0 ? std::clamp((q - a).dot(ab) / len2, 0.0, 1.0) : 0.0;
          const Eigen::Vector2d c = a + u * ab;
          const double d2 = (q - c).squaredNorm();
          if (d2 < best) {
            best = d2;
            best_point = c;
            *best_seg = s;
            *best_u = u;
          }
        }
        continue;
      }
      const Node2& l = nodes_[node.left];
      const Node2& r = nodes_[node.right];
      const double dl = l.box.SquaredDistance(q), dr = r.box.SquaredDistance(q);
      // Push the farther first so the nearer is visited first.
      if (dl < dr) {
        if (dr < best) stack[top++] = node.right;
        if (dl < best) stack[top++] = node.left;
      } else {
        if (dl < best) stack[top++] = node.left;
        if (dr < best) stack[top++] = node.right;
      }
    }
    if (closest) {
      const double c = rho > 0.0 ? p.x() / rho : 1.0;
      const double s = rho > 0.0 ? p.y() / rho : 0.0;
      *closest = Eigen::Vector3d(best_point.x() * c, best_point.x() * s, best_point.y());
    }
    const double d = std::sqrt(best);
    const bool inside = p.z() >= 0.0 && p.z() <= height_ && rho < RadiusAt(p.z());
    return inside ? -d : d;
  }

  double RadiusAt(double z) const {
    if (z < verts_.front().y() || z > height_) return 0.0;
    const auto it = std::upper_bound(verts_.begin(), verts_.end(), z,
                                     [](double v, const Eigen::Vector2d& w) { return v < w.y(); });
    if (it == verts_.end()) return verts_.back().x();
    if (it == verts_.begin()) return verts_.front().x();
    const Eigen::Vector2d& b = *it;
    const Eigen::Vector2d& a = *(it - 1);
    const double f = (z - a.y()) / (b.y() - a.y());
    return a.x() + f * (b.x() - a.x());
  }

  double MaxRadius(double z0, double z1) const {
    z0 = std::max(z0, verts_.front().y());
    z1 = std::min(z1, height_);
    if (!(z0 <= z1)) return -kInf;
    double m = std::max(RadiusAt(z0), RadiusAt(z1));
    // Vertices strictly inside (z0, z1).
    auto cmp = [](const Eigen::Vector2d& w, double v) { return w.y() < v; };
    const int i0 = static_cast<int>(
        std::upper_bound(verts_.begin(), verts_.end(), z0,
                         [](double v, const Eigen::Vector2d& w) { return v < w.y(); }) -
        verts_.begin());
    const int i1 =
        static_cast<int>(std::lower_bound(verts_.begin(), verts_.end(), z1, cmp) - verts_.begin());
    if (i0 < i1) {
      const int len = i1 - i0;
      int k = 0;
      while ((2 << k) <= len) ++k;
      m = std::max({m, sparse_[k][i0], sparse_[k][i1 - (1 << k)]});
    }
    return m;
  }

 private:
  int Build(int lo, int hi) {
    const int index = static_cast<int>(nodes_.size());
    nodes_.emplace_back();
    Node2 node;
    node.lo = lo;
    node.hi = hi;
    for (int i = lo; i <= hi; ++i) node.box.Extend(verts_[i]);
    if (hi - lo > 4) {
      const int mid = (lo + hi) / 2;
      node.left = Build(lo, mid);
      node.right = Build(mid, hi);
    }
    nodes_[index] = node;
    return index;
  }

  std::shared_ptr<const RevolutionProfile> profile_;
  std::vector<Eigen::Vector2d> verts_;
  std::vector<double> params_;
  std::vector<Node2> nodes_;
  std::vector<std::vector<double>> sparse_;
  double height_ = 0.0;
};

// --- Mesh backend --------------------------------------------------------------------------------

struct Triangle {
  Eigen::Vector3d v[3];
  Eigen::Vector3d face_normal;
  Eigen::Vector3d edge_normal[3];    // edge i: v[i] -> v[(i + 1) % 3]
  Eigen::Vector3d vertex_normal[3];  // angle-weighted pseudo-normals
};

struct Node3 {
  Eigen::AlignedBox3d box;
  int lo = 0, hi = 0;
  int left = -1, right = -1;
};

double BoxSquaredDistance(const Eigen::AlignedBox3d& box, const Eigen::Vector3d& p) {
  const Eigen::Vector3d d = (box.min() - p).cwiseMax(p - box.max()).cwiseMax(0.0);
  return d.squaredNorm();
}

// Closest point on triangle abc to p (Ericson, Real-Time Collision Detection, 5.1.5). `feature`:
// 0..2 vertex, 3..5 edge (3 + i: edge i from vertex i to i + 1), 6 face.
Eigen::Vector3d ClosestOnTriangle(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                                  const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                                  int* feature) {
  const Eigen::Vector3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0.0 && d2 <= 0.0) {
    *feature = 0;
    return a;
  }
  const Eigen::Vector3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0.0 && d4 <= d3) {
    *feature = 1;
    return b;
  }
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) {
    *feature = 3;
    return a + (d1 / (d1 - d3)) * ab;
  }
  const Eigen::Vector3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0.0 && d5 <= d6) {
    *feature = 2;
    return c;
  }
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) {
    *feature = 5;  // edge c -> a
    return a + (d2 / (d2 - d6)) * ac;
  }
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {
    *feature = 4;
    return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b);
  }
  const double denom = 1.0 / (va + vb + vc);
  *feature = 6;
  return a + ab * (vb * denom) + ac * (vc * denom);
}

class MeshImpl final : public SurfaceDistance::Impl {
 public:
  explicit MeshImpl(const TriangleMesh& mesh) {
    const int nv = mesh.NumVertices();
    for (const auto& v : mesh.vertices) {
      if (!v.allFinite())
        throw std::invalid_argument("SurfaceDistance: mesh has a non-finite vertex");
    }
    std::vector<Eigen::Vector3d> vertex_normal(nv, Eigen::Vector3d::Zero());
    std::unordered_map<std::uint64_t, Eigen::Vector3d> edge_normal;
    auto edge_key = [](int a, int b) {
      const auto lo = static_cast<std::uint64_t>(std::min(a, b));
      const auto hi = static_cast<std::uint64_t>(std::max(a, b));
      return (lo << 32) | hi;
    };
    std::vector<Eigen::Vector3i> used;
    for (const Eigen::Vector3i& t : mesh.triangles) {
      bool ok = true;
      for (int k = 0; k < 3; ++k) ok = ok && t[k] >= 0 && t[k] < nv;
      if (!ok) continue;
      const Eigen::Vector3d& a = mesh.vertices[t[0]];
      const Eigen::Vector3d& b = mesh.vertices[t[1]];
      const Eigen::Vector3d& c = mesh.vertices[t[2]];
      const Eigen::Vector3d n = (b - a).cross(c - a);
      const double len = n.norm();
      if (!(len > 1e-300)) continue;
      const Eigen::Vector3d un = n / len;
      used.push_back(t);
      for (int k = 0; k < 3; ++k) {
        const Eigen::Vector3d& p = mesh.vertices[t[k]];
        const Eigen::Vector3d e1 = (mesh.vertices[t[(k + 1) % 3]] - p).normalized();
        const Eigen::Vector3d e2 = (mesh.vertices[t[(k + 2) % 3]] - p).normalized();
        const double angle = std::acos(std::clamp(e1.dot(e2), -1.0, 1.0));
        vertex_normal[t[k]] += angle * un;
        // (operator[] would leave a new Eigen vector uninitialised)
        edge_normal.try_emplace(edge_key(t[k], t[(k + 1) % 3]), Eigen::Vector3d::Zero())
            .first->second += un;
      }
    }
    if (used.empty()) {
      throw std::invalid_argument("SurfaceDistance: mesh has no non-degenerate triangle");
    }
    tris_.reserve(used.size());
    bounds.setEmpty();
    for (const Eigen::Vector3i& t : used) {
      Triangle tri;
      for (int k = 0; k < 3; ++k) {
        tri.v[k] = mesh.vertices[t[k]];
        tri.vertex_normal[k] = vertex_normal[t[k]];
        tri.edge_normal[k] = edge_normal[edge_key(t[k], t[(k + 1) % 3])];
        bounds.extend(tri.v[k]);
        bounding_radius = std::max(bounding_radius, std::hypot(tri.v[k].x(), tri.v[k].y()));
      }
      tri.face_normal = (tri.v[1] - tri.v[0]).cross(tri.v[2] - tri.v[0]).normalized();
      tris_.push_back(tri);
    }
    order_.resize(tris_.size());
    std::iota(order_.begin(), order_.end(), 0);
    centroids_.resize(tris_.size());
    for (std::size_t i = 0; i < tris_.size(); ++i) {
      centroids_[i] = (tris_[i].v[0] + tris_[i].v[1] + tris_[i].v[2]) / 3.0;
    }
    Build(0, static_cast<int>(tris_.size()));
    // Reorder triangles into leaf order for locality.
    std::vector<Triangle> sorted(tris_.size());
    for (std::size_t i = 0; i < order_.size(); ++i) sorted[i] = tris_[order_[i]];
    tris_ = std::move(sorted);
    centroids_.clear();
    order_.clear();
  }

  double Signed(const Eigen::Vector3d& p, Eigen::Vector3d* closest) const override {
    Eigen::Vector3d normal;
    return Query(p, closest, &normal);
  }

  Closest ClosestPoint(const Eigen::Vector3d& p) const override {
    Closest c;
    Eigen::Vector3d normal;
    c.signed_distance = Query(p, &c.point, &normal);
    c.normal =
        normal.norm() > 0.0 ? Eigen::Vector3d(normal.normalized()) : Eigen::Vector3d::UnitZ();
    return c;
  }

  double Query(const Eigen::Vector3d& p, Eigen::Vector3d* closest, Eigen::Vector3d* normal) const {
    double best = kInf;
    Eigen::Vector3d best_point = Eigen::Vector3d::Zero();
    Eigen::Vector3d best_normal = Eigen::Vector3d::UnitZ();
    // Stack of (node, squared box distance); nearer child visited first.
    int stack[128];
    double stack_d2[128];
    int top = 0;
    stack[top] = 0;
    stack_d2[top++] = BoxSquaredDistance(nodes_[0].box, p);
    while (top > 0) {
      --top;
      if (stack_d2[top] >= best) continue;
      const Node3& node = nodes_[stack[top]];
      if (node.left < 0) {
        for (int i = node.lo; i < node.hi; ++i) {
          const Triangle& t = tris_[i];
          int feature = 6;
          const Eigen::Vector3d c = ClosestOnTriangle(p, t.v[0], t.v[1], t.v[2], &feature);
          const double d2 = (p - c).squaredNorm();
          if (d2 < best) {
            best = d2;
            best_point = c;
            best_normal = feature < 3   ? t.vertex_normal[feature]
                          : feature < 6 ? t.edge_normal[feature - 3]
                                        : t.face_normal;
          }
        }
        continue;
      }
      const double dl = BoxSquaredDistance(nodes_[node.left].box, p);
      const double dr = BoxSquaredDistance(nodes_[node.right].box, p);
      const bool left_first = dl < dr;
      const int far = left_first ? node.right : node.left;
      const int near = left_first ? node.left : node.right;
      const double d_far = left_first ? dr : dl, d_near = left_first ? dl : dr;
      if (d_far < best) {
        stack[top] = far;
        stack_d2[top++] = d_far;
      }
      if (d_near < best) {
        stack[top] = near;
        stack_d2[top++] = d_near;
      }
    }
    if (closest) *closest = best_point;
    *normal = best_normal;
    const double d = std::sqrt(best);
    return (p - best_point).dot(best_normal) < 0.0 ? -d : d;
  }

 private:
  int Build(int lo, int hi) {
    const int index = static_cast<int>(nodes_.size());
    nodes_.emplace_back();
    Node3 node;
    node.lo = lo;
    node.hi = hi;
    node.box.setEmpty();
    Eigen::AlignedBox3d cbox;
    cbox.setEmpty();
    for (int i = lo; i < hi; ++i) {
      const Triangle& t = tris_[order_[i]];
      for (int k = 0; k < 3; ++k) node.box.extend(t.v[k]);
      cbox.extend(centroids_[order_[i]]);
    }
    if (hi - lo > 4) {
      int axis = 0;
      cbox.sizes().maxCoeff(&axis);
      const int mid = (lo + hi) / 2;
      std::nth_element(order_.begin() + lo, order_.begin() + mid, order_.begin() + hi,
                       [&](int a, int b) { return centroids_[a][axis] < centroids_[b][axis]; });
      // Depth stays ~log2(n / 4) thanks to the median split: the query stack of 128 suffices.
      const int left = Build(lo, mid);
      const int right = Build(mid, hi);
      node.left = left;
      node.right = right;
    }
    nodes_[index] = node;
    return index;
  }

  std::vector<Triangle> tris_;
  std::vector<Node3> nodes_;
  std::vector<int> order_;
  std::vector<Eigen::Vector3d> centroids_;
};

}  // namespace

SurfaceDistance SurfaceDistance::FromProfile(std::shared_ptr<const RevolutionProfile> profile,
                                             int segments) {
  if (!profile) throw std::invalid_argument("SurfaceDistance::FromProfile: null profile");
  if (segments < 16) {
    throw std::invalid_argument("SurfaceDistance::FromProfile: segments must be >= 16, got " +
                                std::to_string(segments));
  }
  return SurfaceDistance(std::make_shared<RevolutionImpl>(std::move(profile), segments));
}

SurfaceDistance SurfaceDistance::FromMesh(const TriangleMesh& mesh) {
  return SurfaceDistance(std::make_shared<MeshImpl>(mesh));
}

double SurfaceDistance::Signed(const Eigen::Vector3d& p) const {
  return impl_->Signed(p, nullptr);
}

double SurfaceDistance::Signed(const Eigen::Vector3d& p, Eigen::Vector3d* closest) const {
  return impl_->Signed(p, closest);
}

SurfaceDistance::Closest SurfaceDistance::ClosestPoint(const Eigen::Vector3d& p) const {
  return impl_->ClosestPoint(p);
}

bool SurfaceDistance::IsRevolution() const {
  return dynamic_cast<const RevolutionImpl*>(impl_.get()) != nullptr;
}

double SurfaceDistance::RadiusAt(double z) const {
  const auto* rev = dynamic_cast<const RevolutionImpl*>(impl_.get());
  if (!rev) throw std::logic_error("SurfaceDistance::RadiusAt: not a surface of revolution");
  return rev->RadiusAt(z);
}

double SurfaceDistance::MaxRadius(double z0, double z1) const {
  const auto* rev = dynamic_cast<const RevolutionImpl*>(impl_.get());
  if (!rev) throw std::logic_error("SurfaceDistance::MaxRadius: not a surface of revolution");
  return rev->MaxRadius(z0, z1);
}

const Eigen::AlignedBox3d& SurfaceDistance::Bounds() const {
  return impl_->bounds;
}

double SurfaceDistance::BoundingRadius() const {
  return impl_->bounding_radius;
}

}  // namespace gs360
