// gs360d.toml: defaults, every section, and errors that name the file, the line and the key.

#include <catch2/catch.hpp>

#include "base/json_reader.h"
#include "daemon/daemon_config.h"

using namespace gs360;

namespace {

std::string ErrorOf(const std::string& toml) {
  try {
    DaemonConfigFromToml(toml, "gs360d.toml", "/etc/gs360");
  } catch (const ConfigError& e) {
    return e.what();
  }
  return "no error";
}

}  // namespace

TEST_CASE("an empty gs360d.toml gives the documented defaults", "[daemon][config]") {
  const DaemonConfig c = DaemonConfigFromToml("", "gs360d.toml", "/etc/gs360");
  CHECK(c.server.listen == "127.0.0.1");
  CHECK(c.server.port == 7360);
  CHECK(c.server.token.empty());
  CHECK(c.data_dir == std::filesystem::path("/etc/gs360/gs360-data"));
  CHECK(c.limits.max_press_depth == 1.2);
  CHECK(c.run.machine.uri.empty());  // a daemon may start without a machine
  CHECK(c.run.rig.ball_radius == 2.0);
  CHECK(c.DatabasePath() == std::filesystem::path("/etc/gs360/gs360-data/gs360.db"));
}

TEST_CASE("every section of gs360d.toml is read, relative paths from the file's folder",
          "[daemon][config]") {
  const DaemonConfig c = DaemonConfigFromToml(R"(
data_dir = "/var/lib/gs360"
[server]
listen = "0.0.0.0"
port = 8080
token = "0123456789abcdef0123"
max_body_bytes = 65536
[log]
level = "debug"
files = 3
[limits]
envelope_min = [-200, -150, -40]
envelope_max = [0, 0, 0]
max_press_depth = 1.1
max_feed_mm_per_min = 1500.0
[calibration]
checkerboards = "boards"
threads = 4
[rig]
ball_radius = 2.0
gel_thickness = 1.4
base_in_machine = [-120, -80, -90]
[rig.shape]
type = "cone"
[machine]
uri = "/dev/ttyUSB0"
home = false
[camera]
uri = "v4l2:/dev/video0"
[engine]
max_attempts = 3
[plan]
probe_count = 2000
press_depth = 0.9
)",
                                              "gs360d.toml", "/etc/gs360");
  CHECK(c.data_dir == "/var/lib/gs360");
  CHECK(c.server.listen == "0.0.0.0");
  CHECK(c.server.port == 8080);
  CHECK(c.server.max_body_bytes == 65536);
  CHECK(c.log.level == "debug");
  CHECK(c.log.files == 3);
  CHECK(c.limits.envelope_min.isApprox(Eigen::Vector3d(-200, -150, -40)));
  CHECK(c.limits.max_feed_mm_per_min == 1500.0);
  CHECK(c.calibration.checkerboards == "/etc/gs360/boards");
  CHECK(c.calibration.threads == 4);
  CHECK(c.run.rig.shape.shape == SensorShape::kCone);
  CHECK(c.run.rig.gel_thickness == 1.4);
  CHECK(c.run.rig.base_in_machine.isApprox(Eigen::Vector3d(-120, -80, -90)));
  CHECK(c.run.machine.uri == "/dev/ttyUSB0");
  CHECK_FALSE(c.run.machine.home);
  CHECK(c.run.camera.uri == "v4l2:/dev/video0");
  CHECK(c.run.engine.max_attempts == 3);
  CHECK(c.run.plan.probe_count == 2000);
  CHECK(c.run.plan.press_depth == 0.9);
  // The configuration prints back as TOML that reads to the same values (secrets hidden).
  const std::string printed = DaemonConfigToToml(c);
  CHECK_THAT(printed, Catch::Contains("(set)") && !Catch::Contains("0123456789abcdef0123"));
  std::string reread = printed;
  const auto at = reread.find("(set)");
  REQUIRE(at != std::string::npos);
  reread.replace(at, 5, "another-long-token");
  const DaemonConfig again = DaemonConfigFromToml(reread, "printed.toml");
  CHECK(again.run.plan.probe_count == 2000);
  CHECK(again.limits.envelope_min.isApprox(c.limits.envelope_min));
}

TEST_CASE("gs360d.toml errors name the file, the line and the key", "[daemon][config]") {
  // An unknown key, with the known ones listed.
  CHECK_THAT(ErrorOf("[server]\nport = 80\nlisten_on = \"x\"\n"),
             Catch::Contains("gs360d.toml:3") && Catch::Contains("server.listen_on") &&
                 Catch::Contains("unknown key") && Catch::Contains("port"));
  // A wrong type.
  CHECK_THAT(ErrorOf("\n\n[limits]\nmax_press_depth = \"deep\"\n"),
             Catch::Contains("gs360d.toml:4") && Catch::Contains("limits.max_press_depth") &&
                 Catch::Contains("expected a number"));
  // A bad value: the line of the key that carries it.
  CHECK_THAT(ErrorOf("[server]\n\nport = 70000\n"),
             Catch::Contains("gs360d.toml:3") && Catch::Contains("server.port"));
  CHECK_THAT(ErrorOf("[limits]\nenvelope_min = [0, 0, 0]\n"),
             Catch::Contains("gs360d.toml:2") && Catch::Contains("limits.envelope_min"));
  CHECK_THAT(ErrorOf("[log]\nlevel = \"loud\"\n"),
             Catch::Contains("gs360d.toml:2") && Catch::Contains("log.level"));
  // Nested sections too.
  CHECK_THAT(ErrorOf("[rig.shape]\ntype = \"banana\"\n"),
             Catch::Contains("gs360d.toml:2") && Catch::Contains("rig.shape.type"));
  CHECK_THAT(ErrorOf("[plan]\nmachine = 3\n"),
             Catch::Contains("gs360d.toml:2") && Catch::Contains("plan.machine"));
  // TOML syntax: line and column.
  CHECK_THAT(ErrorOf("[server\nport = 1\n"),
             Catch::Contains("gs360d.toml:1") && Catch::Contains("invalid TOML"));
  // A press deeper than the gel is refused with the rig.
  CHECK_THAT(ErrorOf("[rig]\ngel_thickness = 0.8\n"), Catch::Contains("press_depth"));
}

TEST_CASE("a daemon that listens beyond loopback needs a token", "[daemon][config][security]") {
  CHECK_THAT(ErrorOf("[server]\nlisten = \"0.0.0.0\"\n"),
             Catch::Contains("server.listen") && Catch::Contains("token"));
  CHECK_THAT(ErrorOf("[server]\nlisten = \"192.168.1.20\"\ntoken = \"short\"\n"),
             Catch::Contains("gs360d.toml:3") && Catch::Contains("at least 16"));
  CHECK(ErrorOf("[server]\nlisten = \"0.0.0.0\"\ntoken = \"a-long-enough-token\"\n") == "no error");
  CHECK(ErrorOf("[server]\nlisten = \"127.0.0.2\"\n") == "no error");
  CHECK(IsLoopbackAddress("127.0.0.1"));
  CHECK(IsLoopbackAddress("::1"));
  CHECK(IsLoopbackAddress("localhost"));
  CHECK_FALSE(IsLoopbackAddress("0.0.0.0"));
  CHECK_FALSE(IsLoopbackAddress("10.0.0.1"));
  CHECK_FALSE(IsLoopbackAddress("127.0.0.1.evil.com"));
}
