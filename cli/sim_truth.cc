#include "cli/sim_truth.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <unordered_map>

#include "sim/ground_truth.h"

namespace gs360::cli {
namespace {

// Distance queries against one displaced patch: a uniform grid over its triangles, searched in
// the cells around the query point, falling back to a scan when nothing is near.
class PatchTruth : public ProbeSurfaceTruth {
 public:
  explicit PatchTruth(DisplacedPatch patch) : patch_(std::move(patch)) {
    const TriangleMesh& m = patch_.mesh;
    if (m.Empty()) return;
    const Eigen::AlignedBox3d box = m.Bounds();
    origin_ = box.min();
    for (int t = 0; t < m.NumTriangles(); ++t) {
      const auto& tri = m.triangles[static_cast<std::size_t>(t)];
      Eigen::AlignedBox3d b;
      for (int k = 0; k < 3; ++k) b.extend(m.vertices[static_cast<std::size_t>(tri[k])]);
      const Eigen::Vector3i lo = Cell(b.min()), hi = Cell(b.max());
      for (int x = lo.x(); x <= hi.x(); ++x) {
        for (int y = lo.y(); y <= hi.y(); ++y) {
          for (int z = lo.z(); z <= hi.z(); ++z) cells_[Key(x, y, z)].push_back(t);
        }
      }
    }
  }

  double Distance(const Eigen::Vector3d& x, Eigen::Vector3d* normal) const override {
    const TriangleMesh& m = patch_.mesh;
    if (m.Empty()) {
      *normal = patch_.contact_normal;
      return std::abs((x - patch_.contact_point).dot(patch_.contact_normal));
    }
    double best = std::numeric_limits<double>::infinity();
    int best_t = -1;
    double best_s = 0.0, best_u = 0.0;
    auto test = [&](int t) {
      const auto& tri = m.triangles[static_cast<std::size_t>(t)];
      double s, u;
      const Eigen::Vector3d q =
          ClosestPointOnTriangle(x, m.vertices[static_cast<std::size_t>(tri[0])],
                                 m.vertices[static_cast<std::size_t>(tri[1])],
                                 m.vertices[static_cast<std::size_t>(tri[2])], &s, &u);
      const double d = (q - x).norm();
      if (d < best) best = d, best_t = t, best_s = s, best_u = u;
    };
    const Eigen::Vector3i c = Cell(x);
    for (int dx = -1; dx <= 1; ++dx) {
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dz = -1; dz <= 1; ++dz) {
          auto it = cells_.find(Key(c.x() + dx, c.y() + dy, c.z() + dz));
          if (it == cells_.end()) continue;
          for (int t : it->second) test(t);
        }
      }
    }
    // The 3x3x3 block guarantees the answer only within one cell of x.
    if (!(best <= kCell)) {
      for (int t = 0; t < m.NumTriangles(); ++t) test(t);
    }
    const auto& tri = m.triangles[static_cast<std::size_t>(best_t)];
    if (m.HasNormals()) {
      *normal = ((1.0 - best_s - best_u) * m.normals[static_cast<std::size_t>(tri[0])] +
                 best_s * m.normals[static_cast<std::size_t>(tri[1])] +
                 best_u * m.normals[static_cast<std::size_t>(tri[2])])
                    .normalized();
    } else {
      *normal = m.TriangleNormal(best_t);
    }
    return best;
  }

  double PeakIndentation() const override { return patch_.max_displacement; }

 private:
  static constexpr double kCell = 0.25;  // mm
  Eigen::Vector3i Cell(const Eigen::Vector3d& p) const {
    return ((p - origin_) / kCell).array().floor().cast<int>();
  }
  static std::int64_t Key(int x, int y, int z) {
    return (static_cast<std::int64_t>(x + 4096) << 40) |
           (static_cast<std::int64_t>(y + 4096) << 20) | static_cast<std::int64_t>(z + 4096);
  }

  DisplacedPatch patch_;
  Eigen::Vector3d origin_ = Eigen::Vector3d::Zero();
  std::unordered_map<std::int64_t, std::vector<int>> cells_;
};

}  // namespace

Eigen::Vector3d ClosestPointOnTriangle(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                                       const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                                       double* s, double* t) {
  // Voronoi-region walk (Ericson, Real-Time Collision Detection, 5.1.5).
  const Eigen::Vector3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0.0 && d2 <= 0.0) return *s = 0.0, *t = 0.0, a;
  const Eigen::Vector3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0.0 && d4 <= d3) return *s = 1.0, *t = 0.0, b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) {
    const double v = d1 / (d1 - d3);
    return *s = v, *t = 0.0, a + v * ab;
  }
  const Eigen::Vector3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0.0 && d5 <= d6) return *s = 0.0, *t = 1.0, c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) {
    const double w = d2 / (d2 - d6);
    return *s = 0.0, *t = w, a + w * ac;
  }
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {
    const double w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
    return *s = 1.0 - w, *t = w, b + w * (c - b);
  }
  const double denom = 1.0 / (va + vb + vc);
  const double v = vb * denom, w = vc * denom;
  *s = v, *t = w;
  return a + ab * v + ac * w;
}

SimValidationTruth::SimValidationTruth(std::shared_ptr<const SimRig> rig,
                                       const GelDeformationOptions& gel)
    : rig_(std::move(rig)),
      gel_(gel),
      builder_(std::make_unique<GelPatchBuilder>(rig_->gel_mesh(), gel_)) {}

std::string SimValidationTruth::Describe() const {
  return "virtual rig physical truth (" + rig_->Describe() + ", elastic edge " +
         std::to_string(gel_.elastic_length) + " mm, bulge " + std::to_string(gel_.bulge_fraction) +
         ")";
}

std::optional<Rigid3d> SimValidationTruth::TrueCamFromSensor() const {
  return SimGroundTruth::TrueCamFromSensor(*rig_);
}

std::unique_ptr<ProbeSurfaceTruth> SimValidationTruth::ForProbe(
    const Eigen::Vector3d& ball_center_sensor, double ball_radius) const {
  return std::make_unique<PatchTruth>(builder_->Build(ball_center_sensor, ball_radius));
}

}  // namespace gs360::cli
