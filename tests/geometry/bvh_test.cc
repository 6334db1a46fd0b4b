#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <optional>
#include <random>
#include <thread>
#include <vector>

#include "geometry/bvh.h"
#include "geometry/shapes.h"

using namespace gs360;

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

struct BruteHit {
  double t;
  int triangle;
  // Other triangles hit at the same t up to rounding (coplanar overlaps: the two fins' bottom
  // faces share the plane z = 0 where they cross).
  std::vector<int> ties;
};

// Independent reference: Moeller-Trumbore over every triangle, closest t, lowest index on ties.
std::optional<BruteHit> BruteForce(const TriangleMesh& m, const Ray& ray, double t_min,
                                   double t_max) {
  std::optional<BruteHit> best;
  for (int i = 0; i < m.NumTriangles(); ++i) {
    const Eigen::Vector3d& a = m.vertices[m.triangles[i][0]];
    const Eigen::Vector3d e1 = m.vertices[m.triangles[i][1]] - a;
    const Eigen::Vector3d e2 = m.vertices[m.triangles[i][2]] - a;
    const Eigen::Vector3d p = ray.direction.cross(e2);
    const double det = e1.dot(p);
    if (det == 0.0) continue;
    const Eigen::Vector3d s = ray.origin - a;
    const double u = s.dot(p) / det;
    if (u < 0.0 || u > 1.0) continue;
    const Eigen::Vector3d q = s.cross(e1);
    const double v = ray.direction.dot(q) / det;
    if (v < 0.0 || u + v > 1.0) continue;
    const double t = e2.dot(q) / det;
    if (t < t_min || t > t_max) continue;
    if (!best || t < best->t) best = BruteHit{t, i, {}};
  }
  if (best) {
    for (int i = 0; i < m.NumTriangles(); ++i) {
      if (i == best->triangle) continue;
      const auto single = [&]() -> std::optional<double> {
        TriangleMesh one;
        for (int k = 0; k < 3; ++k) one.vertices.push_back(m.vertices[m.triangles[i][k]]);
        one.triangles.emplace_back(0, 1, 2);
        const Eigen::Vector3d& a = one.vertices[0];
        const Eigen::Vector3d e1 = one.vertices[1] - a, e2 = one.vertices[2] - a;
        const Eigen::Vector3d p = ray.direction.cross(e2);
        const double det = e1.dot(p);
        if (det == 0.0) return std::nullopt;
        const Eigen::Vector3d s = ray.origin - a;
        const double u = s.dot(p) / det;
        const Eigen::Vector3d q = s.cross(e1);
        const double v = ray.direction.dot(q) / det;
        if (u < -1e-9 || v < -1e-9 || u + v > 1.0 + 1e-9) return std::nullopt;
        return e2.dot(q) / det;
      }();
      if (single && std::abs(*single - best->t) <= 1e-12 * std::max(1.0, best->t))
        best->ties.push_back(i);
    }
  }
  return best;
}

TriangleMesh Scene() {
  // A finger with its fins: the geometry the surface map casts against.
  const auto profile = MakeCylinderCapProfile({});
  TessellationOptions tess;
  tess.segments = 64;
  TriangleMesh m = MakeRevolutionMesh(*profile, tess);
  m.Append(MakeFins(FinOptions{}, *profile));
  m.ComputeVertexNormals();
  return m;
}

Eigen::Vector3d RandomUnit(std::mt19937_64& rng) {
  std::normal_distribution<double> g;
  Eigen::Vector3d d(g(rng), g(rng), g(rng));
  return d.normalized();
}

}  // namespace

TEST_CASE("Bvh closest hit equals brute force on thousands of random rays", "[bvh]") {
  const TriangleMesh scene = Scene();
  const Bvh bvh(scene);
  CHECK(bvh.stats().nodes > 0);
  CHECK(bvh.stats().leaves > scene.NumTriangles() / 4);
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  int hits = 0, misses = 0, agree = 0, ties = 0;
  const int n = 3000;
  for (int i = 0; i < n; ++i) {
    Ray ray;
    if (i % 3 == 0) {
      // Camera-like: from near the base centre, into the finger.
      ray.origin = Eigen::Vector3d(0.3 * u(rng), 0.3 * u(rng), -0.5);
      Eigen::Vector3d d = RandomUnit(rng);
      d.z() = std::abs(d.z());
      ray.direction = d.normalized();
    } else if (i % 3 == 1) {
      // From outside toward the finger.
      ray.origin = Eigen::Vector3d(40 * u(rng), 40 * u(rng), 15 + 40 * u(rng));
      const Eigen::Vector3d target(8 * u(rng), 8 * u(rng), 15 + 15 * u(rng));
      ray.direction = (target - ray.origin).normalized();
    } else {
      // Anywhere, any direction, with a finite interval.
      ray.origin = Eigen::Vector3d(12 * u(rng), 12 * u(rng), 15 + 16 * u(rng));
      ray.direction = RandomUnit(rng);
    }
    const double t_min = i % 3 == 2 ? 0.5 : 0.0;
    const double t_max = i % 3 == 2 ? 20.0 : kInf;
    const auto ref = BruteForce(scene, ray, t_min, t_max);
    const auto hit = bvh.Intersect(ray, t_min, t_max);
    INFO("ray " << i);
    REQUIRE(ref.has_value() == hit.has_value());
    CHECK(bvh.Occluded(ray, t_min, t_max) == ref.has_value());
    if (!ref) {
      ++misses;
      continue;
    }
    ++hits;
    CHECK(hit->t == Approx(ref->t).margin(1e-9));
    const bool same = hit->triangle == ref->triangle;
    const bool tie =
        std::find(ref->ties.begin(), ref->ties.end(), hit->triangle) != ref->ties.end();
    CHECK((same || tie));
    if (same) ++agree;
    if (!ref->ties.empty()) ++ties;
    CHECK((hit->point - (ray.origin + ref->t * ray.direction)).norm() < 1e-9);
    // Barycentrics reproduce the point.
    const Eigen::Vector3i& f = scene.triangles[hit->triangle];
    const Eigen::Vector3d pb = (1 - hit->b1 - hit->b2) * scene.vertices[f[0]] +
                               hit->b1 * scene.vertices[f[1]] + hit->b2 * scene.vertices[f[2]];
    CHECK((pb - hit->point).norm() < 1e-9);
    CHECK(hit->b1 >= -1e-12);
    CHECK(hit->b2 >= -1e-12);
    CHECK(hit->b1 + hit->b2 <= 1.0 + 1e-12);
    CHECK(hit->normal.norm() == Approx(1.0));
    CHECK(hit->front_face == (ray.direction.dot(hit->geometric_normal) < 0.0));
    // Occlusion just short of the hit is false, just past it true.
    CHECK_FALSE(bvh.Occluded(ray, t_min, ref->t * (1 - 1e-9) - 1e-12));
    CHECK(bvh.Occluded(ray, t_min, ref->t + 1e-9));
  }
  CHECK(hits > 1500);
  CHECK(misses > 100);
  // Exactly the reference triangle except where two coplanar triangles tie (fin bottoms).
  CHECK(agree + ties >= hits);
  CHECK(ties < hits / 20);
}

TEST_CASE("Bvh smooth normals follow the analytic surface", "[bvh]") {
  const auto profile = MakeCylinderCapProfile({});
  TessellationOptions tess;
  tess.segments = 48;
  const TriangleMesh mesh = MakeRevolutionMesh(*profile, tess);  // exact vertex normals
  const Bvh bvh(mesh);
  std::mt19937_64 rng(3);
  double smooth_sum = 0.0, flat_sum = 0.0;
  int n = 0;
  for (int i = 0; i < 2000; ++i) {
    Ray ray;
    ray.origin = Eigen::Vector3d(0, 0, 1.0);
    Eigen::Vector3d d = RandomUnit(rng);
    d.z() = std::abs(d.z());
    ray.direction = d.normalized();
    const auto hit = bvh.Intersect(ray);
    REQUIRE(hit);
    CHECK_FALSE(hit->front_face);  // seen from inside
    const auto c = profile->ClosestPoint(hit->point);
    const double smooth = std::acos(std::min(1.0, hit->normal.dot(c.normal)));
    const double flat = std::acos(std::min(1.0, hit->geometric_normal.dot(c.normal)));
    CHECK(smooth < 1.5 * std::numbers::pi / 180.0);
    smooth_sum += smooth;
    flat_sum += flat;
    ++n;
  }
  // Blending vertex normals is several times closer to the true normal than the facet normal.
  CHECK(smooth_sum < 0.3 * flat_sum);
}

TEST_CASE("Bvh is watertight at shared edges and vertices", "[bvh]") {
  const auto profile = MakeCylinderCapProfile({});
  TessellationOptions tess;
  tess.segments = 40;
  tess.rings = 30;
  const TriangleMesh mesh = MakeRevolutionMesh(*profile, tess);
  const Bvh bvh(mesh);
  // From an interior point, rays aimed exactly at every vertex and edge midpoint must hit the
  // closed part of the surface (never slip through a crack).
  const Eigen::Vector3d origin(0.1, -0.2, 12.0);
  int tested = 0;
  for (const auto& f : mesh.triangles) {
    for (int k = 0; k < 3; ++k) {
      const Eigen::Vector3d& a = mesh.vertices[f[k]];
      const Eigen::Vector3d& b = mesh.vertices[f[(k + 1) % 3]];
      for (const Eigen::Vector3d& target : {a, Eigen::Vector3d(0.5 * (a + b))}) {
        if (target.z() <= 1e-9) continue;  // the open base
        Ray ray{origin, (target - origin).normalized()};
        const auto hit = bvh.Intersect(ray);
        REQUIRE(hit);
        CHECK(hit->t == Approx((target - origin).norm()).epsilon(1e-6));
        ++tested;
      }
    }
  }
  CHECK(tested > 5000);
}

TEST_CASE("Bvh respects t_min and t_max and finds the far wall", "[bvh]") {
  const auto profile = MakeCylinderCapProfile({});
  const TriangleMesh mesh = MakeRevolutionMesh(*profile);
  const Bvh bvh(mesh);
  // Along the x axis at z = 10 from outside: enters at x = -10, leaves at x = +10 (the rings'
  // vertices sit on the exact circle at azimuth 0 and pi).
  const Ray ray{Eigen::Vector3d(-30, 0, 10), Eigen::Vector3d(1, 0, 0)};
  const auto first = bvh.Intersect(ray);
  REQUIRE(first);
  CHECK(first->t == Approx(20.0).epsilon(1e-6));
  CHECK(first->front_face);
  const auto second = bvh.Intersect(ray, first->t + 1e-6);
  REQUIRE(second);
  CHECK(second->t == Approx(40.0).epsilon(1e-6));
  CHECK_FALSE(second->front_face);
  CHECK_FALSE(bvh.Intersect(ray, second->t + 1e-6));
  CHECK_FALSE(bvh.Intersect(ray, 0.0, 19.9));
  CHECK(bvh.Occluded(ray, 0.0, 20.1));
  CHECK_FALSE(bvh.Occluded(ray, 20.1, 39.9));
  // Degenerate queries never hit.
  CHECK_FALSE(bvh.Intersect(Ray{Eigen::Vector3d(0, 0, 5), Eigen::Vector3d::Zero()}));
  CHECK_FALSE(bvh.Intersect(Ray{Eigen::Vector3d(0, 0, std::nan("")), Eigen::Vector3d::UnitX()}));
  CHECK_FALSE(bvh.Intersect(ray, 30.0, 10.0));
  // An exactly degenerate triangle lying along a ray is never hit.
  TriangleMesh sliver;
  sliver.vertices = {{0, 0, 5}, {1, 0, 5}, {2, 0, 5}};
  sliver.triangles = {{0, 1, 2}};
  CHECK_FALSE(Bvh(sliver).Intersect(Ray{Eigen::Vector3d(-1, 0, 5), Eigen::Vector3d::UnitX()}));
  // An empty mesh is allowed and never hit.
  const Bvh empty{TriangleMesh{}};
  CHECK_FALSE(empty.Intersect(ray));
  CHECK_FALSE(empty.Occluded(ray));
  // Bad input is rejected with the index.
  TriangleMesh bad = mesh;
  bad.triangles[5][1] = 1 << 30;
  CHECK_THROWS_WITH(Bvh(bad), Catch::Contains("triangle 5"));
  BvhOptions bo;
  bo.max_leaf_size = 0;
  CHECK_THROWS_WITH(Bvh(mesh, bo), Catch::Contains("BvhOptions.max_leaf_size"));
}

TEST_CASE("Bvh is deterministic across builds, options and threads", "[bvh]") {
  const TriangleMesh scene = Scene();
  const Bvh a(scene);
  BvhOptions wide;
  wide.max_leaf_size = 16;
  wide.sah_bins = 7;
  const Bvh b(scene, wide);
  std::vector<Ray> rays;
  std::mt19937_64 rng(11);
  for (int i = 0; i < 4000; ++i) rays.push_back(Ray{Eigen::Vector3d(0, 0, 0.5), RandomUnit(rng)});
  std::vector<RayHit> ra(rays.size()), rb(rays.size()), rc(rays.size());
  auto cast = [&](const Bvh& bvh, std::vector<RayHit>& out, std::size_t begin, std::size_t step) {
    for (std::size_t i = begin; i < rays.size(); i += step) {
      const auto hit = bvh.Intersect(rays[i]);
      out[i] = hit ? *hit : RayHit{};
    }
  };
  cast(a, ra, 0, 1);
  cast(b, rb, 0, 1);
  std::thread t1(cast, std::cref(a), std::ref(rc), 0, 2);
  std::thread t2(cast, std::cref(a), std::ref(rc), 1, 2);
  t1.join();
  t2.join();
  for (std::size_t i = 0; i < rays.size(); ++i) {
    INFO("ray " << i);
    CHECK(ra[i].triangle == rb[i].triangle);
    CHECK(ra[i].t == rb[i].t);
    CHECK(ra[i].triangle == rc[i].triangle);
    CHECK(ra[i].t == rc[i].t);
    CHECK(ra[i].normal == rc[i].normal);
  }
}

TEST_CASE("Bvh handles stacked duplicates and clustered triangles, ties go to the lowest index",
          "[bvh]") {
  TriangleMesh m;
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  // 300 random small triangles in a 2 mm cube, then 300 exact copies of one triangle (all with
  // the same centroid: the SAH cannot split them), then more random ones.
  auto add = [&](const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c) {
    const int base = m.NumVertices();
    m.vertices.insert(m.vertices.end(), {a, b, c});
    m.triangles.emplace_back(base, base + 1, base + 2);
  };
  auto random_tri = [&] {
    const Eigen::Vector3d c(u(rng), u(rng), u(rng));
    add(c, c + 0.3 * Eigen::Vector3d(u(rng), u(rng), u(rng)),
        c + 0.3 * Eigen::Vector3d(u(rng), u(rng), u(rng)));
  };
  for (int i = 0; i < 300; ++i) random_tri();
  const int first_copy = m.NumTriangles();
  for (int i = 0; i < 300; ++i) add({-1, -1, 0.1}, {1, -1, 0.1}, {0, 1, 0.1});
  for (int i = 0; i < 300; ++i) random_tri();
  const Bvh bvh(m);
  // Straight down through the stacked copies: all tie at the same t, the first copy wins
  // unless a random triangle is in front.
  int copies_hit = 0;
  for (int i = 0; i < 500; ++i) {
    const Ray ray{Eigen::Vector3d(0.4 * u(rng), 0.4 * u(rng) - 0.2, 3.0),
                  Eigen::Vector3d(0, 0, -1)};
    const auto ref = BruteForce(m, ray, 0.0, kInf);
    const auto hit = bvh.Intersect(ray);
    REQUIRE(ref);
    REQUIRE(hit);
    CHECK(hit->triangle == ref->triangle);
    CHECK(hit->t == Approx(ref->t).margin(1e-12));
    if (std::abs(ref->t - 2.9) < 1e-12) {
      CHECK(hit->triangle == first_copy);
      ++copies_hit;
    }
  }
  CHECK(copies_hit > 50);
  for (int i = 0; i < 2000; ++i) {
    const Ray ray{Eigen::Vector3d(3 * u(rng), 3 * u(rng), 3 * u(rng)), RandomUnit(rng)};
    const auto ref = BruteForce(m, ray, 0.0, kInf);
    const auto hit = bvh.Intersect(ray);
    REQUIRE(ref.has_value() == hit.has_value());
    if (ref) {
      CHECK(hit->triangle == ref->triangle);
      CHECK(hit->t == Approx(ref->t).margin(1e-12));
    }
  }
  CHECK(bvh.stats().max_depth < 95);
}

namespace {

struct ExactHit {
  double t = 0.0;
  int triangle = -1;
  double b1 = 0.0, b2 = 0.0;
};

// Reference for the exactness check: the watertight test (Woop, Benthin, Wald 2013) written out
// again, in double, over every triangle: closest t, lowest index among equal t. The Bvh must give
// the same triangle and t (its pre-tests and box culling may only skip triangles this rejects).
std::optional<ExactHit> BruteWatertight(const TriangleMesh& m, const Ray& ray, double t_min,
                                        double t_max) {
  const Eigen::Vector3d& d = ray.direction;
  int kz = 0;
  if (std::abs(d.y()) > std::abs(d[kz])) kz = 1;
  if (std::abs(d.z()) > std::abs(d[kz])) kz = 2;
  int kx = (kz + 1) % 3, ky = (kx + 1) % 3;
  if (d[kz] < 0.0) std::swap(kx, ky);
  const double sx = d[kx] / d[kz], sy = d[ky] / d[kz], sz = 1.0 / d[kz];
  std::optional<ExactHit> best;
  for (int i = 0; i < m.NumTriangles(); ++i) {
    const Eigen::Vector3d a = m.vertices[m.triangles[i][0]] - ray.origin;
    const Eigen::Vector3d b = m.vertices[m.triangles[i][1]] - ray.origin;
    const Eigen::Vector3d c = m.vertices[m.triangles[i][2]] - ray.origin;
    const double ax = a[kx] - sx * a[kz], ay = a[ky] - sy * a[kz];
    const double bx = b[kx] - sx * b[kz], by = b[ky] - sy * b[kz];
    const double cx = c[kx] - sx * c[kz], cy = c[ky] - sy * c[kz];
    const double u = cx * by - cy * bx, v = ax * cy - ay * cx, w = bx * ay - by * ax;
    if ((u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0)) continue;
    const double det = u + v + w;
    if (det == 0.0) continue;
    const double az = sz * a[kz], bz = sz * b[kz], cz = sz * c[kz];
    const double t = (u * az + v * bz + w * cz) / det;
    if (!(t >= t_min && t <= t_max)) continue;
    if (!best || t < best->t) best = ExactHit{t, i, v / det, w / det};
  }
  return best;
}

// Rays that stress the float pre-test: aimed exactly at vertices and edge midpoints (the edge
// functions are ~0 there), grazing, from far away, with non-unit directions and finite intervals.
void CheckExactAgainstBruteForce(const TriangleMesh& m, const Eigen::Vector3d& centre, double size,
                                 std::uint64_t seed, const BvhOptions& options = {},
                                 int min_hits = 900) {
  const Bvh bvh(m, options);
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  int hits = 0, checked = 0;
  for (int i = 0; i < 1500; ++i) {
    Ray ray;
    double t_min = 0.0, t_max = kInf;
    const Eigen::Vector3i& f = m.triangles[rng() % m.triangles.size()];
    const Eigen::Vector3d& a = m.vertices[f[0]];
    const Eigen::Vector3d& b = m.vertices[f[1]];
    switch (i % 5) {
      case 0:  // at a vertex, from inside the bounding box
        ray.origin = centre + 0.5 * size * Eigen::Vector3d(u(rng), u(rng), u(rng));
        ray.direction = (a - ray.origin).normalized();
        break;
      case 1:  // at an edge midpoint, non-unit direction
        ray.origin = centre + 0.5 * size * Eigen::Vector3d(u(rng), u(rng), u(rng));
        ray.direction = 7.3 * (0.5 * (a + b) - ray.origin);
        break;
      case 2:  // from far away at a vertex
        ray.origin = centre + 50.0 * size * RandomUnit(rng);
        ray.direction = (a - ray.origin).normalized();
        break;
      case 3:  // random, finite interval
        ray.origin = centre + 0.6 * size * Eigen::Vector3d(u(rng), u(rng), u(rng));
        ray.direction = RandomUnit(rng);
        t_min = 0.1 * size * (1.0 + u(rng));
        t_max = t_min + 0.5 * size * (1.0 + u(rng));
        break;
      default:  // axis-parallel or nearly so
        ray.origin = centre + 0.6 * size * Eigen::Vector3d(u(rng), u(rng), u(rng));
        ray.direction = Eigen::Vector3d::Zero();
        ray.direction[i % 3] = u(rng) < 0.0 ? -1.0 : 1.0;
        ray.direction[(i + 1) % 3] = 1e-12 * u(rng);
        break;
    }
    const auto ref = BruteWatertight(m, ray, t_min, t_max);
    const auto hit = bvh.Intersect(ray, t_min, t_max);
    INFO("ray " << i);
    REQUIRE(ref.has_value() == hit.has_value());
    CHECK(bvh.Occluded(ray, t_min, t_max) == ref.has_value());
    ++checked;
    if (!ref) continue;
    ++hits;
    CHECK(hit->triangle == ref->triangle);
    CHECK(std::abs(hit->t - ref->t) <= 1e-12 * std::abs(ref->t));
    CHECK(hit->b1 == ref->b1);
    CHECK(hit->b2 == ref->b2);
  }
  CHECK(checked == 1500);
  CHECK(hits > min_hits);
}

}  // namespace

TEST_CASE("Bvh gives exactly the brute-force watertight result (same triangle, same t)", "[bvh]") {
  TriangleMesh scene = Scene();
  CheckExactAgainstBruteForce(scene, Eigen::Vector3d(0, 0, 15), 30.0, 21);
  // Far from the origin (large coordinates: the float pre-test's error bound grows with them).
  for (auto& v : scene.vertices) v += Eigen::Vector3d(2.5e5, -1.25e5, 4e4);
  CheckExactAgainstBruteForce(scene, Eigen::Vector3d(2.5e5, -1.25e5, 4e4 + 15), 30.0, 22);
  // Tiny (micrometre-scale) geometry.
  TriangleMesh tiny = Scene();
  for (auto& v : tiny.vertices) v *= 1e-6;
  CheckExactAgainstBruteForce(tiny, Eigen::Vector3d(0, 0, 15e-6), 30e-6, 23);
}

TEST_CASE("Bvh is exact for any leaf size, with many distinct vertices per leaf, and tiny meshes",
          "[bvh]") {
  // Disjoint random triangles in a 2 mm cube: every triangle brings three distinct vertices, so
  // 64-triangle leaves hold 192 of them (the most a leaf can have).
  TriangleMesh cloud;
  std::mt19937_64 rng(31);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int i = 0; i < 2000; ++i) {
    const Eigen::Vector3d c(u(rng), u(rng), u(rng));
    const int base = cloud.NumVertices();
    cloud.vertices.insert(cloud.vertices.end(),
                          {c, c + 0.2 * Eigen::Vector3d(u(rng), u(rng), u(rng)),
                           c + 0.2 * Eigen::Vector3d(u(rng), u(rng), u(rng))});
    cloud.triangles.emplace_back(base, base + 1, base + 2);
  }
  BvhOptions big;  // leaves as large as allowed: splitting never pays
  big.max_leaf_size = 64;
  big.traversal_cost = 1e9;
  BvhOptions single;  // one triangle per leaf
  single.max_leaf_size = 1;
  BvhOptions coarse;  // few SAH bins, odd leaf size
  coarse.max_leaf_size = 3;
  coarse.sah_bins = 2;
  const Bvh big_bvh(cloud, big);
  CHECK(big_bvh.stats().leaves * 64 >= cloud.NumTriangles());
  CHECK(big_bvh.stats().leaves < cloud.NumTriangles() / 16);  // the leaves really are large
  CHECK(Bvh(cloud, single).stats().leaves == cloud.NumTriangles());
  std::uint64_t seed = 40;
  for (const BvhOptions& options : {big, single, coarse, BvhOptions{}})
    CheckExactAgainstBruteForce(cloud, Eigen::Vector3d::Zero(), 2.0, ++seed, options, 900);
  // Meshes of one to five triangles: a root with empty slots (which must never be entered).
  // Rays aimed exactly at an isolated triangle's vertex or edge miss it about half the time.
  for (const int n : {1, 2, 3, 5}) {
    INFO(n << " triangles");
    TriangleMesh few = cloud;
    few.triangles.resize(n);
    CheckExactAgainstBruteForce(few, Eigen::Vector3d::Zero(), 2.0, ++seed, {}, 400);
  }
}
