// Log-distance integration on the synthetic cylinder-wall scene (docs/design.md, "Reconstruction"):
// a rigid 2 mm ball pressed `depth` mm into a 10 mm-radius wall, seen by the default 160-degree
// fisheye on the axis at z = -1.5 mm, exact normals, no noise. Per view-angle band, the mean
// errors of plain Poisson, of the discontinuity-aware integrator and of the height field
// (recon/height_field.h; --hf-init starts it from the Poisson solution, as the Reconstructor
// does), its peak indentation error (max h against the press depth), and the time per roi.
// Also the surface map build time (640 x 480, 2 threads) for the cylinder sensor with fins.
//
//   bench_integration [--depth MM] [--iterations N] [--sharpness S] [--scale S]
//                     [--hf-iterations N] [--hf-init] [--verbose]

#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <numbers>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "geometry/bvh.h"
#include "geometry/shapes.h"
#include "recon/height_field.h"
#include "recon/integration.h"
#include "recon/surface_map.h"
#include "tests/recon/integration_scene.h"

using namespace gs360;

namespace {

double Seconds(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

struct Band {
  int n = 0;
  double view = 0, p_rho = 0, d_rho = 0, p_p2s = 0, d_p2s = 0, p_roi = 0, d_roi = 0;
  double p_ms = 0, d_ms = 0, px = 0;
  double h_p2s = 0, h_roi = 0, h_ms = 0, h_peak = 0, h_peak_bias = 0;
};

}  // namespace

int main(int argc, char** argv) {
  double depth = 1.0;
  bool verbose = false;
  IntegrationOptions da;
  HeightFieldOptions hf;
  bool hf_init = false;
  CLI::App app(
      "bench_integration: plain Poisson vs discontinuity-aware vs height-field integration "
      "errors per view-angle band on the cylinder-wall scene, and surface map build time");
  app.option_defaults()->always_capture_default();
  app.add_option("--depth", depth, "press depth of the 2 mm ball into the wall, mm");
  app.add_option("--iterations", da.iterations, "discontinuity-aware re-weighting passes")
      ->check(CLI::Range(1, 1000));
  app.add_option("--sharpness", da.sharpness, "slope of the discontinuity-aware weights' sigmoid")
      ->check(CLI::PositiveNumber);
  app.add_option("--scale", da.scale, "discontinuity-aware residual scale (psi per pixel)")
      ->check(CLI::PositiveNumber);
  app.add_option("--hf-iterations", hf.iterations, "height-field passes")
      ->check(CLI::Range(1, 100));
  app.add_flag("--hf-init", hf_init, "start the height field from the Poisson solution");
  app.add_flag("--verbose", verbose, "print one line per press");
  CLI11_PARSE(app, argc, argv);
  da.Check();
  const FisheyeCamera camera;
  const Rigid3d cam_from_sensor(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0, 0, 1.5));

  // Surface map build time: the built-in cylinder sensor with its fins.
  {
    SensorShapeOptions shape;
    const Bvh gel(MakeSensorMesh(shape));
    const Bvh fins(MakeFins(FinOptions{}, *MakeProfile(shape)));
    for (int threads : {1, 2}) {
      SurfaceMapOptions o;
      o.threads = threads;
      double best = 1e9;
      SurfaceMapStats st;
      for (int rep = 0; rep < 3; ++rep) {
        const SurfaceMap m = SurfaceMap::Build(camera, cam_from_sensor, gel, &fins, o);
        best = std::min(best, m.stats().build_seconds);
        st = m.stats();
      }
      std::printf(
          "surface map 640x480, cylinder sensor (%d tris) + fins, %d thread(s): %.1f ms "
          "(best of 3); visible %d, fin %d, grazing %d, no hit %d, outside %d\n",
          gel.mesh().NumTriangles(), threads, 1e3 * best, st.visible, st.fin, st.grazing, st.no_hit,
          st.outside);
    }
  }

  const Bvh wall_bvh(testing::DenseCylinder(10.0, 45.0, 4096, 2));
  SurfaceMapOptions mo;
  mo.threads = 2;
  const SurfaceMap map = SurfaceMap::Build(camera, cam_from_sensor, wall_bvh, nullptr, mo);
  const double r = 2.0;
  IntegrationOptions poisson;
  poisson.method = IntegrationMethod::kPoisson;
  da.method = IntegrationMethod::kDiscontinuityAware;

  std::map<int, Band> bands;  // 0: < 30, 1: 30-50, 2: > 50 deg
  const double views[] = {17, 24, 31, 38, 45, 50, 56, 60, 64, 68};
  const double azimuths[] = {20, 65, 110, 160, 200, 250, 290, 340};
  if (verbose) {
    std::printf("%6s %6s %5s %7s | %9s %9s | %9s %9s | %8s %8s\n", "view", "azim", "px", "roi",
                "P rho", "DA rho", "P p2s", "DA p2s", "P ms", "DA ms");
  }
  for (double view : views) {
    for (double az_deg : azimuths) {
      const double az = az_deg * std::numbers::pi / 180.0;
      const double z = 10.0 * std::tan(view * std::numbers::pi / 180.0) - 1.5;
      const Eigen::Vector3d n(std::cos(az), std::sin(az), 0.0);
      const Eigen::Vector3d p = 10.0 * n + Eigen::Vector3d(0, 0, z);
      const Eigen::Vector3d c = cam_from_sensor * Eigen::Vector3d(p + n * (r - depth));
      const testing::PressScene s = testing::RenderPress(map, camera, c, r);
      if (s.contact_pixels == 0) continue;
      const testing::DeformedWall wall(10.0, Eigen::Vector3d::Zero(), c, r);
      const LogDepthGradients g = ComputeLogDepthGradients(map, s.roi, s.normals);
      auto t0 = std::chrono::steady_clock::now();
      const IntegrationResult rp = IntegrateLogDepth(map, g, poisson);
      const double p_s = Seconds(t0);
      t0 = std::chrono::steady_clock::now();
      const IntegrationResult rd = IntegrateLogDepth(map, g, da);
      const double d_s = Seconds(t0);
      const testing::PressErrors ep = testing::MeasurePress(map, s, rp.rho, &wall);
      const testing::PressErrors ed = testing::MeasurePress(map, s, rd.rho, &wall);
      t0 = std::chrono::steady_clock::now();
      const cv::Mat h0 =
          hf_init ? IndentationFromRho(map, s.roi, IntegrateLogDepth(map, g, poisson).rho)
                  : cv::Mat();
      const HeightFieldResult rh = IntegrateHeightField(map, camera, s.roi, s.normals, hf, h0);
      const double h_s = Seconds(t0);
      const testing::PressErrors eh = testing::MeasurePress(map, s, rh.rho, &wall);
      const int band = ep.view_angle_deg < 30 ? 0 : ep.view_angle_deg <= 50 ? 1 : 2;
      Band& b = bands[band];
      ++b.n;
      b.view += ep.view_angle_deg;
      b.p_rho += ep.contact_rho, b.d_rho += ed.contact_rho;
      b.p_p2s += ep.contact_p2s, b.d_p2s += ed.contact_p2s;
      b.p_roi += ep.roi_p2s, b.d_roi += ed.roi_p2s;
      b.p_ms += 1e3 * p_s, b.d_ms += 1e3 * d_s;
      b.px += s.roi.area();
      b.h_p2s += eh.contact_p2s, b.h_roi += eh.roi_p2s, b.h_ms += 1e3 * h_s;
      double peak_h = 0.0;
      for (int y = 0; y < rh.height.rows; ++y)
        for (int x = 0; x < rh.height.cols; ++x)
          peak_h = std::max(peak_h, rh.height.at<double>(y, x));
      b.h_peak += std::abs(peak_h - depth), b.h_peak_bias += peak_h - depth;
      if (verbose) {
        std::printf(
            "%6.1f %6.0f %5d %3dx%-3d | %9.4f %9.4f | %9.4f %9.4f | %8.2f %8.2f  it %d | HF p2s "
            "%.4f peak %+.4f\n",
            ep.view_angle_deg, az_deg, s.contact_pixels, s.roi.width, s.roi.height, ep.contact_rho,
            ed.contact_rho, ep.contact_p2s, ed.contact_p2s, 1e3 * p_s, 1e3 * d_s, rd.iterations,
            eh.contact_p2s, peak_h - depth);
      }
    }
  }
  std::printf(
      "\ncylinder wall R = 10 mm, ball r = 2 mm, depth %.2f mm, camera on the axis at z = -1.5 mm; "
      "discontinuity-aware: iterations %d, sharpness %.2f\n",
      depth, da.iterations, da.sharpness);
  std::printf(
      "mean over contact pixels (rho = |rho - rho_true| along the ray; p2s = point-to-surface), "
      "roi p2s = over all visible roi pixels; mm\n");
  std::printf("%-12s %4s %6s | %9s %9s | %9s %9s | %9s %9s | %8s %8s %8s\n", "band", "n", "view",
              "P rho", "DA rho", "P p2s", "DA p2s", "P roi", "DA roi", "roi px", "P ms", "DA ms");
  const char* names[] = {"< 30 deg", "30-50 deg", "> 50 deg"};
  for (auto& [k, b] : bands) {
    const double n = b.n;
    std::printf("%-12s %4d %6.1f | %9.4f %9.4f | %9.4f %9.4f | %9.4f %9.4f | %8.0f %8.2f %8.2f\n",
                names[k], b.n, b.view / n, b.p_rho / n, b.d_rho / n, b.p_p2s / n, b.d_p2s / n,
                b.p_roi / n, b.d_roi / n, b.px / n, b.p_ms / n, b.d_ms / n);
  }
  std::printf("height field (HF, iterations %d):\n%-12s | %9s %9s %8s | %9s %9s\n", hf.iterations,
              "band", "HF p2s", "HF roi", "HF ms", "HF peak", "peak bias");
  for (auto& [k, b] : bands) {
    std::printf("%-12s | %9.4f %9.4f %8.2f | %9.4f %+9.4f\n", names[k], b.h_p2s / b.n,
                b.h_roi / b.n, b.h_ms / b.n, b.h_peak / b.n, b.h_peak_bias / b.n);
  }
  return 0;
}
