// bench_raycast: BVH build time and single-thread ray casting throughput on a ~200k-triangle
// cylinder-cap finger (the target: >= 2 million rays per second per core).
// Usage: bench_raycast [triangles=200000] [seconds_per_case=1.0]

#include <chrono>
#include <cstdio>
#include <ctime>
#include <limits>
#include <optional>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>

#include "geometry/bvh.h"
#include "geometry/fisheye.h"
#include "geometry/shapes.h"

using namespace gs360;

namespace {

double Now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

// CPU time of the calling thread: throughput per core even when the machine is shared.
double ThreadCpu() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

struct Result {
  double mrays_per_cpu_s;  // per core
  double mrays_per_wall_s;
  double hit_fraction;
};

// Casts the rays repeatedly for at least `seconds`; closest-hit or any-hit with per-ray t_max.
Result Run(const Bvh& bvh, const std::vector<Ray>& rays, const std::vector<double>& t_max,
           bool any_hit, double seconds) {
  long long cast = 0, hits = 0;
  double checksum = 0.0;
  const double start = Now();
  const double cpu_start = ThreadCpu();
  double elapsed = 0.0;
  do {
    for (std::size_t i = 0; i < rays.size(); ++i) {
      if (any_hit) {
        hits += bvh.Occluded(rays[i], 0.0, t_max[i]);
      } else if (const auto h = bvh.Intersect(rays[i], 0.0, t_max[i])) {
        ++hits;
        checksum += h->t;
      }
    }
    cast += static_cast<long long>(rays.size());
    elapsed = Now() - start;
  } while (elapsed < seconds);
  if (checksum == 1.2345) std::printf(" ");  // keep the work observable
  const double cpu = ThreadCpu() - cpu_start;
  return {cast / cpu / 1e6, cast / elapsed / 1e6, static_cast<double>(hits) / cast};
}

}  // namespace

int main(int argc, char** argv) {
  int triangles = 200000;
  double seconds = 1.0;
  CLI::App app(
      "bench_raycast: BVH build time and single-thread ray casting throughput on a cylinder-cap "
      "finger");
  app.option_defaults()->always_capture_default();
  app.add_option("triangles", triangles, "triangles of the finger mesh")
      ->check(CLI::PositiveNumber);
  app.add_option("seconds_per_case", seconds, "minimum casting time per case, s");
  CLI11_PARSE(app, argc, argv);
  const auto profile = MakeCylinderCapProfile({});
  const TriangleMesh finger =
      MakeRevolutionMesh(*profile, TessellationOptions::ForTriangleCount(*profile, triangles));
  TriangleMesh fins_scene = finger;
  fins_scene.Append(MakeFins(FinOptions{}, *profile));
  const TriangleMesh& with_fins = fins_scene;

  std::printf("bench_raycast: cylinder-cap finger (r 10 mm, h 30 mm), %d triangles; +fins %d\n",
              finger.NumTriangles(), with_fins.NumTriangles());
  std::printf(
      "single thread; each case runs >= %.1f s; Mrays/s per core = rays / thread CPU time\n\n",
      seconds);

  // Camera rays: every valid pixel of the default 160-degree 640x480 fisheye, camera 1 mm below
  // the centre of the base plane looking +z (sensor frame = camera frame up to axis labels).
  const FisheyeCamera camera;
  std::vector<Ray> cam_rays;
  for (int v = 0; v < camera.height(); ++v)
    for (int u = 0; u < camera.width(); ++u)
      if (const auto d = camera.PixelToRay(Eigen::Vector2d(u, v)))
        cam_rays.push_back(Ray{Eigen::Vector3d(0, 0, -1.0), *d});
  // Random rays: origins uniform in the finger's bounding box (inflated 20%), directions uniform.
  std::mt19937_64 rng(1);
  std::uniform_real_distribution<double> uni(-1.0, 1.0);
  std::normal_distribution<double> gauss;
  std::vector<Ray> random_rays(200000);
  for (auto& r : random_rays) {
    r.origin = Eigen::Vector3d(12 * uni(rng), 12 * uni(rng), 15 + 18 * uni(rng));
    r.direction = Eigen::Vector3d(gauss(rng), gauss(rng), gauss(rng)).normalized();
  }
  const std::vector<double> inf_cam(cam_rays.size(), std::numeric_limits<double>::infinity());
  const std::vector<double> inf_rand(random_rays.size(), std::numeric_limits<double>::infinity());

  const Bvh surface_only(finger);
  for (const TriangleMesh* mesh : {&finger, &with_fins}) {
    const double t0 = Now();
    const Bvh bvh(*mesh);
    const double build = Now() - t0;
    std::printf("%s: build %.3f s (%d nodes, %d leaves, depth %d)\n",
                mesh == &finger ? "finger" : "finger+fins", build, bvh.stats().nodes,
                bvh.stats().leaves, bvh.stats().max_depth);
    // Shadow-like any-hit: from the camera to 99% of the distance to the surface (the fin
    // occlusion test of the surface map; mostly unoccluded, so the whole path is traversed).
    std::vector<double> to_surface(cam_rays.size());
    for (std::size_t i = 0; i < cam_rays.size(); ++i) {
      const auto h = surface_only.Intersect(cam_rays[i]);
      to_surface[i] = h ? 0.99 * h->t : 0.0;
    }
    struct Case {
      const char* name;
      const std::vector<Ray>* rays;
      const std::vector<double>* t_max;
      bool any;
    };
    const Case cases[] = {{"camera rays, closest hit", &cam_rays, &inf_cam, false},
                          {"random rays, closest hit", &random_rays, &inf_rand, false},
                          {"camera rays, any hit before the surface", &cam_rays, &to_surface, true},
                          {"random rays, any hit", &random_rays, &inf_rand, true}};
    for (const Case& c : cases) {
      const Result r = Run(bvh, *c.rays, *c.t_max, c.any, seconds);
      std::printf("  %-42s %6.2f Mrays/s per core (wall %5.2f)  hit %5.1f%%\n", c.name,
                  r.mrays_per_cpu_s, r.mrays_per_wall_s, 100.0 * r.hit_fraction);
    }
    // Two threads on the shared BVH (const queries): scaling check.
    Result per[2];
    std::thread a([&] { per[0] = Run(bvh, cam_rays, inf_cam, false, seconds); });
    std::thread b([&] { per[1] = Run(bvh, cam_rays, inf_cam, false, seconds); });
    a.join();
    b.join();
    std::printf("  %-42s %6.2f Mrays/s total wall (per core %.2f, %.2f)\n\n",
                "camera rays, closest hit, 2 threads",
                per[0].mrays_per_wall_s + per[1].mrays_per_wall_s, per[0].mrays_per_cpu_s,
                per[1].mrays_per_cpu_s);
  }
  return 0;
}
