#include <catch2/catch.hpp>

#include <fstream>

#include <nlohmann/json.hpp>

#include "base/json_reader.h"
#include "daemon/run_config.h"
#include "rig_fixture.h"

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
