#include "cli/heldout_rigs.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <numbers>
#include <random>
#include <sstream>
#include <stdexcept>
#include <vector>

#include "base/format.h"
#include "geometry/mesh.h"
#include "geometry/shapes.h"

namespace gs360::cli {
namespace {

// Uniform draws from the seed alone (not std::uniform_real_distribution, whose output the
// standard leaves to the library): the same seed is the same rig everywhere.
class Draw {
 public:
  explicit Draw(std::uint64_t seed) : engine_(seed * 0x9E3779B97F4A7C15ull + 0x5EEDull) {}
  double Uniform(double lo, double hi) {
    const double u = static_cast<double>(engine_() >> 11) * 0x1.0p-53;
    return lo + (hi - lo) * u;
  }
  int Int(int lo, int hi) {  // [lo, hi]
    return std::min(hi, lo + static_cast<int>(Uniform(0.0, 1.0) * (hi - lo + 1)));
  }
  bool Chance(double p) { return Uniform(0.0, 1.0) < p; }

 private:
  std::mt19937_64 engine_;
};

std::string Num(double v, int digits = 3) {
  return FormatFixed(v, digits);
}

// The finger as a spline profile: the base radius, a few bulges and waists, a rounded tip.
SplineOptions DrawSpline(Draw& d, double height, double radius) {
  SplineOptions s;
  s.control_points.clear();
  const double tip_r = radius * d.Uniform(0.5, 0.75);
  // A rounded tip, about as tall as it is wide (a flatter one leaves no room for the fins).
  const double tip_z = height - std::max(1.5, tip_r * d.Uniform(0.8, 1.2));
  const int middle = 4;
  s.control_points.emplace_back(0.0, radius);
  for (int i = 1; i <= middle; ++i) {
    const double z = tip_z * i / (middle + 1.0);
    s.control_points.emplace_back(z, radius * d.Uniform(0.8, 1.05));
  }
  s.control_points.emplace_back(tip_z, tip_r);
  s.control_points.emplace_back(height, 0.0);
  return s;
}

// A finger that is not round: the spline's surface of revolution, squeezed or bent.
TriangleMesh DrawMesh(Draw& d, const std::string& family, const SplineOptions& spline,
                      double height, std::string* how) {
  TriangleMesh mesh = MakeRevolutionMesh(*MakeSplineProfile(spline), TessellationOptions{});
  double a = 1.0, b = 1.0, bend = 0.0;
  if (family == "ellipse") {
    a = d.Uniform(1.05, 1.25);
    b = d.Uniform(0.8, 0.95);
    *how = "section x " + Num(a, 2) + " y " + Num(b, 2);
  } else if (family == "flat") {
    b = d.Uniform(0.65, 0.85);
    *how = "flattened to " + Num(b, 2) + " in y";
  } else {
    bend = d.Uniform(0.03, 0.08) * height;
    *how = "tip bent " + Num(bend, 1) + " mm in x";
  }
  for (Eigen::Vector3d& v : mesh.vertices) {
    const double t = std::clamp(v.z() / height, 0.0, 1.0);
    v = Eigen::Vector3d(a * v.x() + bend * t * t * t, b * v.y(), v.z());
  }
  mesh.normals.clear();
  return mesh;
}

// Closes the open base ring (vertices [0, segments), z = 0) with a flat face looking down (-z):
// the solid a CAD export gives.
void CloseBase(TriangleMesh& mesh, int segments) {
  const int centre = mesh.NumVertices();
  mesh.vertices.emplace_back(0.0, 0.0, 0.0);
  for (int k = 0; k < segments; ++k) {
    mesh.triangles.emplace_back(centre, (k + 1) % segments, k);
  }
}

void WriteText(const std::filesystem::path& path, const std::string& text) {
  std::ofstream out(path);
  out << text;
  if (!out.flush()) throw std::runtime_error("cannot write " + path.string());
}

std::string SplineToml(const SplineOptions& s) {
  std::string points;
  for (const Eigen::Vector2d& p : s.control_points) {
    points += (points.empty() ? "[" : ", [") + Num(p.x()) + ", " + Num(p.y()) + "]";
  }
  return "[rig.shape.spline]\ncontrol_points = [" + points + "]\n";
}

// [sim]: the hidden camera, the noise and the LEDs.
std::string SimToml(Draw& d, std::uint64_t seed, double height_fraction_max) {
  std::ostringstream s;
  s << "\n[sim]\nseed = " << seed << "\nperturbation = " << Num(d.Uniform(0.5, 2.0), 2)
    << "\ncamera_tilt = " << Num(d.Uniform(0.5, 3.0), 2)
    << "\ncamera_offset = " << Num(d.Uniform(0.1, 0.6), 2)
    << "\nread_noise = " << Num(d.Uniform(0.5, 3.0), 2)
    << "\nshot_gain = " << Num(d.Uniform(0.02, 0.12), 3)
    << "\nled_drift = " << Num(d.Uniform(0.0, 0.04), 3);
  std::vector<double> heights(static_cast<std::size_t>(d.Int(1, 3)));
  for (double& h : heights) h = d.Uniform(0.08, height_fraction_max);
  std::sort(heights.begin(), heights.end());
  s << "\nled_heights = [";
  for (std::size_t i = 0; i < heights.size(); ++i) s << (i ? ", " : "") << Num(heights[i]);
  s << "]\nled_radial = " << Num(d.Uniform(0.3, 0.8), 2) << "\nled_intensity = ["
    << Num(d.Uniform(0.5, 1.6), 2) << ", " << Num(d.Uniform(0.5, 1.6), 2) << ", "
    << Num(d.Uniform(4.0, 14.0), 1) << "]\nblue_leds = " << d.Int(6, 24)
    << "\nblue_ring_radius = " << Num(d.Uniform(0.2, 0.6), 2) << "\n";
  return s.str();
}

// [plan] and [rig] mount keys: a machine whose Z reaches over the finger, a stylus as long.
std::string MachineToml(double height, double travel_z, std::uint64_t seed) {
  const double stylus = std::max(25.0, std::ceil(height));
  return "\n[plan]\nseed = " + std::to_string(seed) + "\nstylus_length = " + Num(stylus, 1) +
         "\n\n[plan.machine]\nmax_travel_mm = [300.0, 180.0, " + Num(travel_z, 1) + "]\n";
}

}  // namespace

HeldoutRig DrawHeldoutRig(std::uint64_t seed, const std::filesystem::path& dir) {
  std::filesystem::create_directories(dir);
  Draw d(seed);
  static const char* const kFamilies[] = {"spline", "cone", "cylinder", "dome", "mesh"};
  std::string family = kFamilies[d.Int(0, 4)];
  if (family == "mesh") family = std::vector<std::string>{"ellipse", "flat", "bent"}[d.Int(0, 2)];
  const bool dome = family == "dome";
  const double radius = dome ? d.Uniform(10.0, 18.0) : d.Uniform(6.5, 14.0);
  const double height =
      dome ? radius * d.Uniform(1.0, 1.25) : std::max(d.Uniform(20.0, 60.0), radius + 2.0);
  const bool fins = d.Chance(dome ? 0.25 : 0.75);
  const double fin_thickness = d.Uniform(0.3, 0.9);
  const double camera_z = -d.Uniform(1.0, 4.0);

  HeldoutRig rig;
  rig.seed = seed;
  rig.family = family;
  rig.config = dir / ("rig-" + std::to_string(seed) + ".toml");
  // The mount: the base as far below the machine's Z travel as the default's (45 mm of travel,
  // the base 93 mm below the origin with the 50 mm tool).
  const double travel_z = std::max(45.0, std::ceil(height + 20.0));
  std::string rig_keys = "base_in_machine = [-150.0, -90.0, " + Num(-48.0 - travel_z, 1) + "]\n";
  std::ostringstream tables;
  std::ostringstream what;
  what << family << " " << Num(height, 1) << " mm x r " << Num(radius, 1);
  if (family == "spline" || family == "ellipse" || family == "flat" || family == "bent") {
    const SplineOptions spline = DrawSpline(d, height, radius);
    if (family == "spline") {
      tables << "[rig.shape]\ntype = \"spline\"\n" << SplineToml(spline);
    } else {
      std::string how;
      TriangleMesh mesh = DrawMesh(d, family, spline, height, &how);
      const bool closed = d.Chance(0.5);
      const bool metres = d.Chance(1.0 / 3.0);
      if (closed) CloseBase(mesh, TessellationOptions{}.segments);
      if (metres) {
        for (Eigen::Vector3d& v : mesh.vertices) v /= 1000.0;
      }
      rig.mesh = dir / ("rig-" + std::to_string(seed) + ".stl");
      WriteStlBinary(rig.mesh, mesh);
      rig_keys += "mesh_path = \"" + rig.mesh.filename().string() + "\"\n" +
                  (metres ? "mesh_scale = 1000.0\n" : "");
      what << ", " << how << ", " << (closed ? "closed solid" : "open surface") << " in "
           << (metres ? "m" : "mm");
    }
  } else if (family == "cone") {
    const double tip = d.Uniform(2.0, 0.45 * radius);
    tables << "[rig.shape]\ntype = \"cone\"\n[rig.shape.cone]\nbase_radius = " << Num(radius)
           << "\nheight = " << Num(height) << "\ntip_radius = " << Num(tip) << "\n";
  } else {
    tables << "[rig.shape]\ntype = \"cylinder\"\n[rig.shape.cylinder]\nradius = " << Num(radius)
           << "\nheight = " << Num(height) << "\n";
  }
  tables << "[rig.fins]\nenabled = " << (fins ? "true" : "false")
         << "\nthickness = " << Num(fin_thickness) << "\n[rig.camera]\ncamera_z = " << Num(camera_z)
         << "\n";
  what << (fins ? ", fins " + Num(fin_thickness, 2) + " mm" : ", no fins") << ", camera "
       << Num(camera_z, 1) << " mm";
  WriteText(rig.config, "# held-out rig " + std::to_string(seed) +
                            " of `gs360 bench heldout` (cli/heldout_rigs.h)\n[rig]\n" + rig_keys +
                            tables.str() + MachineToml(height, travel_z, seed) +
                            SimToml(d, seed, dome ? 0.6 : 0.7));
  rig.description = what.str();
  return rig;
}

HeldoutRig OwnRig(const std::string& shape, std::uint64_t seed, const std::filesystem::path& dir) {
  std::filesystem::create_directories(dir);
  HeldoutRig rig;
  rig.seed = seed;
  rig.family = "own " + shape;
  rig.description = "the project's own " + shape + " at its defaults";
  rig.config = dir / ("own-" + shape + "-" + std::to_string(seed) + ".toml");
  WriteText(rig.config, "# the project's own " + shape + " (`gs360 bench heldout --own`)\n" +
                            "[rig.shape]\ntype = \"" + shape +
                            "\"\n\n[plan]\nseed = " + std::to_string(seed) +
                            "\n\n[sim]\nseed = " + std::to_string(seed) + "\n");
  return rig;
}

RunConfig LoadHeldoutRig(const HeldoutRig& rig, SimArgs* sim, std::uint64_t* seed) {
  CLI::App app;
  AddSimArgs(&app, sim);
  app.add_option("--seed", *seed);
  std::vector<std::string> argv = {rig.config.string(), "--config"};  // parsed back to front
  app.parse(argv);
  return LoadSimConfig(app, sim, seed);
}

}  // namespace gs360::cli
