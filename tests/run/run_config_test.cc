#include <catch2/catch.hpp>

#include <fstream>

#include <nlohmann/json.hpp>

#include "base/json_reader.h"
#include "daemon/daemon_config.h"
#include "rig_fixture.h"
#include "run/run_config.h"

using namespace gs360;

namespace {
std::string Write(const std::filesystem::path& dir, const std::string& text) {
  const auto p = dir / "config.json";
  std::ofstream(p) << text;
  return p.string();
}
}  // namespace

TEST_CASE("run config round-trips through JSON", "[daemon][config]") {
  RunConfig c;
  c.name = "x";
  c.rig.shape.shape = SensorShape::kCone;
  c.plan.probe_count = 123;
  c.plan.press_depth = 0.8;
  c.machine.uri = "/dev/ttyUSB0";
  c.machine.status_interval_ms = 25;
  c.camera.uri = "libcamera:0";
  c.camera.capture.frames_to_average = 5;
  const RunConfig back = RunConfigFromJson(RunConfigToJson(c), "mem");
  CHECK(back.machine.status_interval_ms == 25);
  CHECK(back.rig.shape.shape == SensorShape::kCone);
  CHECK(back.plan.probe_count == 123);
  CHECK(back.plan.press_depth == 0.8);
  CHECK(back.camera.capture.frames_to_average == 5);
  CHECK(RunConfigToJson(back) == RunConfigToJson(c));
}

TEST_CASE("malformed configs name the file, the line and the field", "[daemon][config]") {
  const auto dir = test::FreshDir("config");
  // Syntax error on line 3.
  auto p = Write(dir, "{\n  \"name\": \"a\",\n  \"plan\": {\"probe_count\": 10,,}\n}\n");
  CHECK_THROWS_WITH(LoadRunConfigFile(p), Catch::Contains(p + ":3:"));
  // Wrong type.
  p = Write(dir, R"({"machine": {"uri": "/dev/x"}, "camera": {"uri": "v4l2:0"},
                    "plan": {"press_depth": "deep"}})");
  CHECK_THROWS_WITH(LoadRunConfigFile(p),
                    Catch::Contains("plan.press_depth") && Catch::Contains("expected a number"));
  // Unknown key (a typo must not pass silently).
  p = Write(dir,
            R"({"machine": {"uri": "/dev/x", "baudrate": 9600}, "camera": {"uri": "v4l2:0"}})");
  CHECK_THROWS_WITH(LoadRunConfigFile(p),
                    Catch::Contains("machine.baudrate") && Catch::Contains("unknown key"));
  // Invalid value.
  p = Write(dir, R"({"machine": {"uri": "/dev/x"}, "camera": {"uri": "v4l2:0"},
                    "rig": {"shape": {"type": "banana"}}})");
  CHECK_THROWS_WITH(LoadRunConfigFile(p), Catch::Contains("rig.shape.type"));
  p = Write(dir, R"({"machine": {"uri": ""}, "camera": {"uri": "v4l2:0"}})");
  CHECK_THROWS_WITH(LoadRunConfigFile(p), Catch::Contains("machine.uri"));
  CHECK_THROWS_WITH(LoadRunConfigFile((dir / "missing.json").string()),
                    Catch::Contains("missing.json") && Catch::Contains("cannot open"));
  std::filesystem::remove_all(dir);
}

TEST_CASE("a probe count given is the count planned, machine_hours sizes the rest",
          "[daemon][config]") {
  // gs360d's default: sized in machine time.
  CHECK(DaemonConfig{}.run.plan.machine_hours == kDefaultMachineHours);
  const auto read = [](const nlohmann::json& plan) {
    PlanOptions p = DefaultDaemonRun().plan;
    JsonReader r(plan, "mem", "plan");
    ReadPlanOptions(r, p);
    return p;
  };
  CHECK(read({{"press_depth", 0.8}}).machine_hours == kDefaultMachineHours);
  CHECK(read({{"probe_count", 500}}).machine_hours == 0.0);
  CHECK(read({{"probe_count", 500}, {"machine_hours", 2.0}}).machine_hours == 2.0);
  CHECK(read({{"machine_hours", 0.5}}).machine_hours == 0.5);
  // A request's "probes" is an explicit count.
  PlanOptions p = DefaultDaemonRun().plan;
  const nlohmann::json request = {{"probes", 300}};
  JsonReader r(request, "request", "");
  ReadProbeCount(r, "probes", p);
  CHECK(p.probe_count == 300);
  CHECK(p.machine_hours == 0.0);
  // A run stored before the option (probe_count, no machine_hours) plans and hashes as it did.
  RunConfig stored;
  stored.machine.uri = "/dev/ttyUSB0";
  stored.camera.uri = "v4l2:/dev/video0";
  nlohmann::json j = RunConfigToJson(stored);
  j["plan"].erase("machine_hours");
  CHECK(RunConfigFromJson(j, "stored").plan.machine_hours == 0.0);
  // Out of range: named.
  CHECK_THROWS_WITH(read({{"machine_hours", -1.0}}), Catch::Contains("machine_hours"));
}

TEST_CASE("the impression check: derived by default, a user's threshold, an older run's contrast",
          "[daemon][config]") {
  RunConfig c;
  c.machine.uri = "/dev/ttyUSB0";
  c.camera.uri = "libcamera:0";
  nlohmann::json j = RunConfigToJson(c);
  CHECK(j["engine"]["impression_min_snr"] == 0.0);
  CHECK_FALSE(j["engine"].contains("impression_min_contrast"));
  j["engine"]["impression_min_snr"] = 12.5;
  CHECK(RunConfigFromJson(j, "mem").engine.impression_min_snr == 12.5);
  // A run stored before the signal-to-noise check resumes with the contrast it started with.
  j["engine"]["impression_min_contrast"] = 1.4;
  const RunConfig older = RunConfigFromJson(j, "mem");
  CHECK(older.engine.impression_min_contrast == 1.4);
  CHECK(RunConfigToJson(older)["engine"]["impression_min_contrast"] == 1.4);
  j["engine"]["impression_min_contrast"] = 0.5;
  CHECK_THROWS_WITH(RunConfigFromJson(j, "mem"), Catch::Contains("engine.impression_min_contrast"));
  j["engine"]["impression_min_contrast"] = 0.0;
  j["engine"]["impression_min_snr"] = -1.0;
  CHECK_THROWS_WITH(RunConfigFromJson(j, "mem"), Catch::Contains("engine.impression_min_snr"));
}

TEST_CASE("machine.firmware and plan.machine.travel_min_mm: stored, and refused when wrong",
          "[daemon][config]") {
  RunConfig c;
  c.machine.uri = "/dev/ttyUSB0";
  c.camera.uri = "libcamera:0";
  c.machine.firmware = MachineFirmware::kMarlin;
  c.plan.machine.travel_min_mm = Eigen::Vector3d(0.0, 0.0, 0.0);
  const RunConfig back = RunConfigFromJson(RunConfigToJson(c), "mem");
  CHECK(back.machine.firmware == MachineFirmware::kMarlin);
  REQUIRE(back.plan.machine.travel_min_mm);
  CHECK(back.plan.machine.TravelMax().isApprox(c.plan.machine.max_travel_mm));
  // Absent, GRBL's [-travel, 0] and "auto": what runs stored before the keys read as.
  RunConfig defaults;
  defaults.machine.uri = "/dev/ttyUSB0";
  defaults.camera.uri = "libcamera:0";
  const RunConfig plain = RunConfigFromJson(RunConfigToJson(defaults), "mem");
  CHECK_FALSE(plain.plan.machine.travel_min_mm);
  CHECK(plain.machine.firmware == MachineFirmware::kAuto);

  const auto dir = test::FreshDir("config-firmware");
  auto p = Write(dir, R"({"machine": {"uri": "/dev/x", "firmware": "smoothieware"},
                         "camera": {"uri": "v4l2:0"}})");
  CHECK_THROWS_WITH(LoadRunConfigFile(p), Catch::Contains("machine.firmware") &&
                                              Catch::Contains("smoothieware") &&
                                              Catch::Contains("\"marlin\""));
  p = Write(dir, R"({"machine": {"uri": "/dev/x", "firmware": 2}, "camera": {"uri": "v4l2:0"}})");
  CHECK_THROWS_WITH(LoadRunConfigFile(p), Catch::Contains("machine.firmware"));
  p = Write(dir, R"({"machine": {"uri": "/dev/x"}, "camera": {"uri": "v4l2:0"},
                    "plan": {"machine": {"travel_min_mm": [0, "low", 0]}}})");
  CHECK_THROWS_WITH(LoadRunConfigFile(p), Catch::Contains("travel_min_mm"));
  p = Write(dir, R"({"machine": {"uri": "/dev/x"}, "camera": {"uri": "v4l2:0"},
                    "plan": {"machine": {"travel_min_mm": [0, 0, 1e300]}}})");
  CHECK_THROWS_WITH(LoadRunConfigFile(p), Catch::Contains("travel_min_mm"));
  std::filesystem::remove_all(dir);
}
