// bench_sampling: blue-noise sampling time (weighted sample elimination, 5x candidates) for
// 10,000 points on the default cylinder-cap finger (issue target: under 1 s), plus the spacing
// achieved. Usage: bench_sampling [count=10000] [repeats=5]

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <ctime>
#include <limits>
#include <vector>

#include <CLI/CLI.hpp>

#include "geometry/sampling.h"
#include "geometry/shapes.h"

using namespace gs360;

namespace {

double Now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

// CPU time of the calling thread (the figure that does not depend on other load).
double ThreadCpu() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

}  // namespace

int main(int argc, char** argv) {
  int count = 10000, repeats = 5;
  CLI::App app(
      "bench_sampling: blue-noise sampling time (weighted sample elimination) and spacing on the "
      "cylinder-cap finger");
  app.option_defaults()->always_capture_default();
  app.add_option("count", count, "points sampled")->check(CLI::PositiveNumber);
  app.add_option("repeats", repeats, "timed runs per case")
      ->transform(CLI::Bound(1, std::numeric_limits<int>::max()).description("raised to >= 1"));
  CLI11_PARSE(app, argc, argv);
  const auto profile = MakeCylinderCapProfile({});
  for (int triangles : {0, 200000}) {
    const TriangleMesh mesh =
        triangles == 0 ? MakeRevolutionMesh(*profile)
                       : MakeRevolutionMesh(
                             *profile, TessellationOptions::ForTriangleCount(*profile, triangles));
    std::printf("mesh: %d triangles, area %.1f mm^2\n", mesh.NumTriangles(), mesh.Area());
    for (bool region : {false, true}) {
      std::vector<double> times, cpu;
      std::vector<SurfaceSample> s;
      BlueNoiseOptions o;
      o.count = count;
      const SamplePredicate keep = region ? SamplePredicate([](const SurfaceSample& x) {
        return x.point.z() > 10.0 && x.point.x() > 0.0;
      })
                                          : SamplePredicate();
      for (int r = 0; r < repeats; ++r) {
        o.seed = r + 1;
        const double t0 = Now(), c0 = ThreadCpu();
        s = SampleBlueNoise(mesh, o, keep);
        times.push_back(Now() - t0);
        cpu.push_back(ThreadCpu() - c0);
      }
      std::sort(times.begin(), times.end());
      std::sort(cpu.begin(), cpu.end());
      const double area = region ? 0.5 * (mesh.Area() * 20.0 / 30.0) : mesh.Area();
      const double ideal = IdealBlueNoiseSpacing(area, count);
      std::printf(
          "  %-36s %d points: median %.3f s wall, %.3f s CPU (wall min %.3f, max %.3f); min "
          "spacing %.4f mm = %.3f x ideal %.4f mm\n",
          region ? "region z > 10 mm, x > 0 (predicate)" : "whole surface",
          static_cast<int>(s.size()), times[times.size() / 2], cpu[cpu.size() / 2], times.front(),
          times.back(), MinimumSpacing(s), MinimumSpacing(s) / ideal, ideal);
    }
    const double t0 = Now();
    const auto u = SampleUniform(mesh, count, 1);
    std::printf("  %-36s %d points: %.4f s; min spacing %.4f mm\n",
                "uniform (white) for comparison", static_cast<int>(u.size()), Now() - t0,
                MinimumSpacing(u));
  }
  return 0;
}
