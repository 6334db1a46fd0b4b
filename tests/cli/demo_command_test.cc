// `gs360 demo` as a user runs it, on a held-out rig described by a gs360d.toml: the daemon gets
// that rig, the virtual rig is built from it, and every frame is checked against its truth.

#include <catch2/catch.hpp>

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>

#include "cli/sim_args.h"
#include "daemon/daemon_config.h"
#include "run/calibration_inputs.h"
#include "sim/tactile_camera.h"
#include "storage/run_database.h"
#include "tests/cli/run_gs360.h"

using namespace gs360;
using Catch::Contains;
namespace fs = std::filesystem;
using test::Gs360;

namespace {

struct TempDir {
  fs::path path = fs::temp_directory_path() / ("gs360-demo-cmd-" + std::to_string(::getpid()));
  TempDir() {
    fs::remove_all(path);
    fs::create_directories(path);
  }
  ~TempDir() { fs::remove_all(path); }
};

}  // namespace

TEST_CASE("demo runs a held-out rig from a gs360d.toml through the daemon", "[cli][demo]") {
  TempDir dir;
  const fs::path config = dir.path / "heldout.toml";
  std::ofstream(config) << "# a slimmer spline finger, the camera lower, thinner fins\n"
                           "[rig.shape]\ntype = \"spline\"\n[rig.shape.spline]\n"
                           "control_points = [[0, 9], [8, 8.5], [16, 8], [22, 7.5], [26, 5], "
                           "[29, 0]]\n[rig.fins]\nthickness = 0.4\n[rig.camera]\ncamera_z = -2.0\n"
                           "[sim]\nperturbation = 2\nread_noise = 2\nfaults = \"frame-drop\"\n"
                           "fault_every = 10\n";
  const fs::path data = dir.path / "data";
  const auto r = Gs360("demo --config " + config.string() + " --probes 80 --no-calibrate " +
                       "--data-dir " + data.string());
  INFO(r.out);
  REQUIRE(r.status == 0);
  CHECK_THAT(r.out, Contains("(spline)"));
  CHECK_THAT(r.out, Contains("faults: frame-drop, one every ~10 presses"));
  CHECK_THAT(r.out, Contains("0 taken off the press point, 0 unverifiable"));

  RunDatabaseOptions ro;
  ro.read_only = true;
  RunDatabase db(data / "gs360.db", ro);
  const RunConfig stored = StoredRunConfig(db, 1);
  CHECK(stored.rig.shape.shape == SensorShape::kSpline);
  REQUIRE(stored.rig.shape.spline.control_points.size() == 6);
  CHECK(stored.rig.shape.spline.control_points[1].y() == 8.5);
  CHECK(stored.rig.camera_z == -2.0);
  CHECK(stored.rig.fins.thickness == 0.4);
  CHECK(db.CountProbes(1).captured > 40);
}

TEST_CASE("demo names the file, line and key of a bad rig description", "[cli][demo]") {
  TempDir dir;
  const fs::path config = dir.path / "bad.toml";
  std::ofstream(config) << "[rig.shape]\ntype = \"spline\"\n[rig.fins]\nthicknes = 0.4\n";
  auto r = Gs360("demo --config " + config.string() + " --no-calibrate --data-dir " +
                 (dir.path / "data").string());
  CHECK(r.status != 0);
  CHECK_THAT(r.out, Contains("bad.toml:4: rig.fins.thicknes: unknown key"));
  r = Gs360("demo --config " + config.string() + " --shape cone");
  CHECK(r.status != 0);
  CHECK_THAT(r.out, Contains("--shape excludes --config"));
}

TEST_CASE("a gs360d.toml's [sim] sets the virtual rig's knobs and the command line wins",
          "[cli][demo]") {
  TempDir dir;
  const fs::path path = dir.path / "rig.toml";
  const auto load = [&](const std::string& sim, const std::string& command_line) {
    std::ofstream(path) << "[rig.camera]\ncamera_z = -2.0\n[sim]\n" << sim;
    CLI::App app;
    std::uint64_t seed = 1;
    app.add_option("--seed", seed);
    cli::SimArgs args;
    cli::AddSimArgs(&app, &args);
    app.parse("--config " + path.string() + " " + command_line, false);
    const RunConfig config = cli::LoadSimConfig(app, &args, &seed);
    CHECK(config.rig.camera_z == -2.0);
    return std::make_pair(args, seed);
  };
  const auto [args, seed] = load(
      "seed = 7\nperturbation = 0.5\nnoise = false\nread_noise = 2\nshot_gain = 0.2\n"
      "led_drift = 0.03\ncamera_tilt = 2\ncamera_offset = 0.4\nled_heights = [0.2, 0.6]\n"
      "led_radial = 0.3\nled_intensity = [2, 1, 5]\nblue_leds = 8\nblue_ring_radius = 0.4\n"
      "faults = \"drop,stall\"\nfault_every = 20\n",
      "--read-noise 3 --fault-every 30");
  CHECK(seed == 7);
  CHECK(args.perturbation == 0.5);
  CHECK(args.no_noise);
  CHECK(args.read_noise == 3.0);  // the command line's
  CHECK(args.shot_gain == 0.2);
  CHECK(args.drift == 0.03);
  CHECK(args.camera_tilt_deg == 2.0);
  CHECK(args.camera_offset_mm == 0.4);
  CHECK(args.led_heights == std::vector<double>{0.2, 0.6});
  CHECK(args.led_radial == 0.3);
  CHECK(args.led_intensity == std::vector<double>{2.0, 1.0, 5.0});
  CHECK(args.blue_leds == 8);
  CHECK(args.blue_ring_radius == 0.4);
  CHECK(args.faults == "drop,stall");
  CHECK(args.fault_every == 30.0);  // the command line's

  // Wrong values name the file, the line and the key; gs360d itself leaves [sim] alone.
  const std::string where = path.string() + ":";
  CHECK_THROWS_WITH(load("read_noise = 1\nred_noise = 2\n", ""),
                    Contains(where + "5: sim.red_noise: unknown key"));
  CHECK_THROWS_WITH(load("led_radial = 2\n", ""),
                    Contains(where + "4: sim.led_radial") && Contains("must be in 0.000..1.000"));
  CHECK_THROWS_WITH(load("led_intensity = [1, 2]\n", ""), Contains("takes 3 values, got 2"));
  CHECK_THROWS_WITH(load("faults = \"drop,boom\"\n", ""),
                    Contains("sim.faults") && Contains("boom"));
  CHECK_THROWS_WITH(load("seed = \"x\"\n", ""), Contains("sim.seed"));
  std::ofstream(path) << "[sim]\nred_noise = 2\n";
  CHECK_NOTHROW(LoadDaemonConfig(path));
}

TEST_CASE("the virtual rig's knobs scale its hidden truth and noise, and refuse a folded lens",
          "[cli][demo]") {
  cli::SimArgs args;
  args.perturbation = 2.0;
  args.read_noise = 3.0;
  args.drift = 0.0;
  VirtualRigOptions options;
  const TruePerturbationOptions before = options.rig.perturbation;
  cli::ApplySimArgs(args, &options);
  CHECK(options.rig.perturbation.translation_mm == 2.0 * before.translation_mm);
  CHECK(options.rig.perturbation.focal_relative == 2.0 * before.focal_relative);
  CHECK(options.rig.perturbation.k1 == 2.0 * before.k1);
  CHECK(options.camera.sensor.read_noise == 3.0);
  CHECK(options.camera.sensor.drift_amplitude == 0.0);
  CHECK(options.camera.sensor.noise);

  args = {};
  args.perturbation = 0.0;
  args.no_noise = true;
  VirtualRigOptions exact;
  cli::ApplySimArgs(args, &exact);
  CHECK(exact.rig.perturbation.rotation_deg == 0.0);
  CHECK_FALSE(exact.camera.sensor.noise);

  // 25 times the default focal offset is 25 %: past what the simulator accepts.
  args = {};
  args.perturbation = 25.0;
  VirtualRigOptions folded;
  CHECK_THROWS_WITH(cli::ApplySimArgs(args, &folded), Contains("--perturbation 25.00"));
}

TEST_CASE("the camera's tilt and offset and the LEDs' layout are set from the command line",
          "[cli][demo]") {
  cli::SimArgs args;
  args.perturbation = 0.0;
  args.camera_tilt_deg = 3.0;
  args.camera_offset_mm = 0.5;
  args.led_heights = {0.2, 0.5, 0.7};
  args.led_radial = 0.4;
  args.led_intensity = {2.0, 1.0, 5.0};
  args.blue_leds = 6;
  args.blue_ring_radius = 0.5;
  VirtualRigOptions options;
  cli::ApplySimArgs(args, &options);
  CHECK(options.rig.perturbation.rotation_deg == 3.0);
  CHECK(options.rig.perturbation.translation_mm == 0.5);
  CHECK(options.rig.perturbation.focal_relative == 0.0);  // the rest scaled by --perturbation 0
  const LightingOptions& l = options.camera.lighting;
  CHECK(l.fin_led_heights == std::vector<double>{0.2, 0.5, 0.7});
  CHECK(l.fin_led_radial == 0.4);
  CHECK(l.red_intensity == 2.0);
  CHECK(l.blue_intensity == 5.0);
  CHECK(l.blue_ring_count == 6);
  CHECK(l.blue_ring_radius == 0.5);

  // The rig they make is another one: its frames differ from the default rig's.
  options.camera.sensor.noise = false;
  VirtualRigOptions plain;
  plain.rig.perturbation = TruePerturbationOptions::None();
  plain.camera.sensor.noise = false;
  TactileCamera changed(std::make_shared<const SimRig>(options.rig), options.camera);
  TactileCamera reference(std::make_shared<const SimRig>(plain.rig), plain.camera);
  const cv::Mat a = changed.RenderReference(0), b = reference.RenderReference(0);
  CHECK(cv::norm(a, b, cv::NORM_L1) / static_cast<double>(a.total()) > 5.0);

  // Wrong values name the option.
  args = {};
  args.led_intensity = {1.0, 2.0};
  VirtualRigOptions bad;
  CHECK_THROWS_WITH(cli::ApplySimArgs(args, &bad), Contains("--led-intensity"));
  args = {};
  args.led_heights = {0.0};
  CHECK_THROWS_WITH(cli::ApplySimArgs(args, &bad), Contains("fin_led_heights[0]"));
}

TEST_CASE("demo with faults resumes as a user would and every frame is at its press point",
          "[cli][demo][fault]") {
  TempDir dir;
  const auto r = Gs360(
      "demo --probes 90 --no-calibrate --faults all --fault-every 12 --seed 2 "
      "--data-dir " +
      (dir.path / "data").string());
  INFO(r.out);
  REQUIRE(r.status == 0);
  CHECK_THAT(r.out, Contains("faults: all, one every ~12 presses"));
  CHECK_THAT(r.out, Contains("  injected: ") && Contains(" faults ("));
  CHECK_THAT(r.out, Contains("0 taken off the press point, 0 unverifiable"));
  RunDatabaseOptions ro;
  ro.read_only = true;
  RunDatabase db(dir.path / "data" / "gs360.db", ro);
  CHECK(db.CountProbes(1).planned == 0);
  CHECK(db.GetRun(1)->state == RunState::kDone);
}

TEST_CASE("an unknown fault kind is a usage error naming the known ones", "[cli][demo][fault]") {
  for (const char* cmd :
       {"demo --faults drop,meteor", "sim-rig --faults meteor", "bench soak --faults meteor"}) {
    INFO(cmd);
    const auto r = Gs360(cmd);
    CHECK(r.status == 2);
    CHECK_THAT(r.out, Contains("unknown fault 'meteor'") && Contains("frame-corrupt"));
  }
}

TEST_CASE("demo --firmware marlin runs the rig on a virtual printer through the daemon",
          "[cli][demo][marlin]") {
  TempDir dir;
  const fs::path data = dir.path / "data";
  const auto r =
      Gs360("demo --firmware marlin --probes 80 --no-calibrate --data-dir " + data.string());
  INFO(r.out);
  REQUIRE(r.status == 0);
  CHECK_THAT(r.out, Contains("0 taken off the press point, 0 unverifiable"));
  RunDatabaseOptions ro;
  ro.read_only = true;
  RunDatabase db(data / "gs360.db", ro);
  std::string events;
  for (const EventRecord& e : db.ListEvents(1, 0, 1000)) events += e.message + "\n";
  INFO(events);
  CHECK_THAT(events, Contains("connected to Marlin 2.1"));
  const RunConfig stored = StoredRunConfig(db, 1);
  CHECK(stored.machine.firmware == MachineFirmware::kMarlin);
  REQUIRE(stored.plan.machine.travel_min_mm);
  CHECK(stored.plan.machine.TravelMax().isApprox(Eigen::Vector3d(235.0, 235.0, 250.0)));
  CHECK_FALSE(Gs360("demo --firmware smoothie --probes 80").status == 0);
}

TEST_CASE("docs/daemon.md's Ender-3 example is the printer demo --firmware marlin runs",
          "[cli][demo][marlin]") {
  std::ifstream in(fs::path(GS360_SOURCE_DIR) / "docs" / "daemon.md");
  REQUIRE(in);
  const std::string doc((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const std::size_t section = doc.find("### Printers (Marlin)");
  REQUIRE(section != std::string::npos);
  const std::size_t start = doc.find("```toml\n", section);
  REQUIRE(start != std::string::npos);
  const std::size_t end = doc.find("```", start + 8);
  TempDir dir;
  const fs::path file = dir.path / "ender3.toml";
  std::ofstream(file) << doc.substr(start + 8, end - start - 8);
  const DaemonConfig loaded = LoadDaemonConfig(file.string());
  RunConfig expected;
  cli::ApplyPrinterDefaults(&expected);
  const RunConfig& got = loaded.run;
  CHECK(got.machine.firmware == MachineFirmware::kMarlin);
  CHECK(got.rig.base_in_machine.isApprox(expected.rig.base_in_machine));
  CHECK(got.rig.tool_offset.isApprox(expected.rig.tool_offset));
  CHECK(got.plan.start_machine.isApprox(expected.plan.start_machine));
  CHECK(got.plan.machine.max_rate_mm_per_min.isApprox(expected.plan.machine.max_rate_mm_per_min));
  CHECK(got.plan.machine.acceleration_mm_per_s2.isApprox(
      expected.plan.machine.acceleration_mm_per_s2));
  CHECK(got.plan.machine.TravelMin().isApprox(expected.plan.machine.TravelMin()));
  CHECK(got.plan.machine.TravelMax().isApprox(expected.plan.machine.TravelMax()));
  CHECK(got.plan.machine.junction_deviation_mm ==
        Approx(expected.plan.machine.junction_deviation_mm));
  CHECK(loaded.limits.envelope_min.isApprox(expected.plan.machine.TravelMin()));
  CHECK(loaded.limits.envelope_max.isApprox(expected.plan.machine.TravelMax()));
}
