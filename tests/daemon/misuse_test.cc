// gs360d and gs360 under misuse (issue 32): numbers out of range and names that are no names
// refused where they come in, with the field, its range and the exit code a script can act on;
// what is printed escaped; the errors naming the user's file and field, not the daemon's
// temporary file or a C++ type; a second virtual rig refused on the paths the first one serves.
// Each test goes through the real executables (gs360d, gs360).

#include <catch2/catch.hpp>

#include <signal.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <fstream>
#include <regex>
#include <sstream>
#include <thread>
#include <utility>

#include <nlohmann/json.hpp>

#include "cli_runner.h"
#include "daemon_fixture.h"
#include "run/run_engine.h"
#include "tests/wait.h"

using namespace gs360;
using Json = nlohmann::json;
using test::CliResult;
using test::RunGs360;

namespace {

httplib::Client ClientOf(const std::string& url) {
  httplib::Client c(url);
  c.set_read_timeout(120, 0);
  return c;
}

httplib::Result PostRun(httplib::Client& c, const std::string& body) {
  return c.Post("/api/v1/runs", body, "application/json");
}

bool HasControlBytes(const std::string& s) {
  for (const char ch : s) {
    const auto c = static_cast<unsigned char>(ch);
    if ((c < 0x20 && c != '\n') || c == 0x7f) return true;
  }
  return false;
}

// A gs360d.toml for `f` with `home = false`: each start asks the user to confirm the position.
std::unique_ptr<cli::DaemonProcess> StartNoHomingDaemon(const test::RigFixture& f) {
  std::string toml = test::RigToml(f.config);
  toml.replace(toml.find("[machine]\n"), 10, "[machine]\nhome = false\n");
  std::ofstream(f.dir / "gs360d.toml") << toml;
  return std::make_unique<cli::DaemonProcess>(std::string(GS360_BINARY_DIR) + "/daemon/gs360d",
                                              f.dir / "gs360d.toml", f.dir / "data",
                                              f.dir / "gs360d.log");
}

}  // namespace

TEST_CASE(
    "misuse: every number of a run request is checked where it is read: 400 naming the "
    "field and its range, never 500",
    "[daemon][api][security][misuse]") {
  test::RigFixture f("misuse-numbers", 40, 0.0);
  auto daemon = test::StartDaemonProcess(f);
  httplib::Client c = ClientOf(daemon->url());
  struct Case {
    const char* body;
    const char* field;
    const char* says;  // the range (or rule) the message must state
  };
  const Case cases[] = {
      {R"({"plan": {"probe_count": 2e9}})", "plan.probe_count", "1..1000000"},
      {R"({"plan": {"probe_count": 2000000000}})", "plan.probe_count", "1..1000000"},
      {R"({"plan": {"probe_count": 20000000}})", "plan.probe_count", "1..1000000"},
      {R"({"probes": 0})", "probes", "1..1000000"},
      {R"({"probes": -3})", "probes", "1..1000000"},
      {R"({"probes": 2.5})", "probes", "1..1000000"},
      {R"({"probes": "many"})", "probes", "1..1000000"},
      {R"({"plan": {"seed": -5}})", "plan.seed", "0..18446744073709551615"},
      {R"({"plan": {"candidate_factor": 1e9}})", "plan.candidate_factor", "[1, 100]"},
      {R"({"probes": 1000000, "plan": {"candidate_factor": 50}})", "plan.candidate_factor",
       "at most 10000000"},
      {R"({"plan": {"neighbours": 2000000000}})", "plan.neighbours", "1..100"},
      {R"({"plan": {"checkpoint_probes": 2000000000}})", "plan.checkpoint_probes", "0..1000000"},
      {R"({"plan": {"settle_dwell_s": 1e300}})", "plan.settle_dwell_s", "[0, 3600] s"},
      {R"({"plan": {"press_feed_mm_per_min": 1e300}})", "plan.press_feed_mm_per_min",
       "[1, 100000] mm/min"},
      {R"({"plan": {"clearance": 1e300}})", "plan.clearance", "(0, 100] mm"},
      {R"({"plan": {"start_machine": [1e300, 0, 0]}})", "plan.start_machine",
       "[-100000, 100000] mm"},
      {R"({"shape": {"segments": 1000000}})", "shape.segments", "3..4096"},
      {R"({"shape": {"cylinder": {"radius": 1e300, "height": 1e300}}})", "shape.cylinder.radius",
       "(0, 1000] mm"},
      {R"({"shape": {"type": "spline", "spline": {"control_points": [[0, 5], [2000, 0]]}}})",
       "shape.spline.control_points", "[0, 1000] mm"},
      {R"({"converge": {"min_improvement": -1}})", "converge.min_improvement", "[0, 1)"},
      // Rules between fields: named by the request's path, not the C++ type that checks them.
      {R"({"shape": {"cylinder": {"radius": -1}}})", "shape.cylinder.radius", "(0, 1000] mm"},
      {R"({"shape": {"cylinder": {"radius": 20, "height": 10}}})", "shape.cylinder.height",
       "must be >= radius"},
      {R"({"plan": {"press_depth": 5}})", "plan.press_depth", "must be <"},
  };
  for (const Case& k : cases) {
    INFO(k.body);
    const auto r = PostRun(c, k.body);
    REQUIRE(r);
    INFO(r->body);
    CHECK(r->status == 400);
    const Json e = Json::parse(r->body, nullptr, false);
    REQUIRE(e.is_object());
    CHECK(e["error"]["code"] == "invalid");
    CHECK(e["error"]["field"] == k.field);
    const std::string message = e["error"].value("message", "");
    CHECK_THAT(message, Catch::Contains(k.field) && Catch::Contains(k.says));
    CHECK_THAT(message, !Catch::Contains("Options.") && !Catch::Contains("RigConfig."));
  }
  // Shapes that the rig's fins or a sane mesh cannot have: the planner's refusal is the
  // request's fault, a 400 about the shape.
  for (const char* body :
       {R"({"shape": {"type": "spline", "spline": {"control_points": [[0, 5], [1e-6, 0]]}}})",
        R"({"shape": {"cylinder": {"radius": 0.001, "height": 1000}}})"}) {
    INFO(body);
    const auto r = PostRun(c, body);
    REQUIRE(r);
    INFO(r->body);
    CHECK(r->status == 400);
    CHECK_THAT(r->body, Catch::Contains("\"field\":\"shape") && !Catch::Contains("Options.") &&
                            !Catch::Contains("\"internal\""));
  }

  // By hand it was curl; here every numeric field of a request gets a negative, a zero, a huge,
  // a fractional and a string value: each is planned or refused with 400, never a 500.
  const std::vector<std::string> plan_fields = {"candidate_factor",
                                                "ball_radius",
                                                "press_depth",
                                                "clearance",
                                                "stylus_radius",
                                                "stylus_length",
                                                "holder_radius",
                                                "holder_length",
                                                "press_feed_mm_per_min",
                                                "retract_feed_mm_per_min",
                                                "settle_dwell_s",
                                                "capture_time_s",
                                                "status_poll_latency_s",
                                                "host_latency_s",
                                                "reference_dwell_s",
                                                "fov_margin_rad",
                                                "image_margin_px",
                                                "max_view_angle_rad",
                                                "travel_clearance",
                                                "travel_limit_margin",
                                                "probe_count",
                                                "reference_every",
                                                "neighbours",
                                                "max_improvement_passes",
                                                "checkpoint_probes",
                                                "seed"};
  const std::vector<Json> values = {-3, 0, 1e300, 2.5, "x", 2000000000, -1e-300, 1e-300};
  std::vector<Json> requests;
  for (const auto& field : plan_fields) {
    for (const Json& v : values) requests.push_back({{"plan", {{field, v}}}});
  }
  for (const Json& v : values) {
    requests.push_back({{"probes", v}});
    requests.push_back({{"shape", {{"cylinder", {{"radius", v}}}}}});
    requests.push_back({{"shape", {{"cylinder", {{"height", v}}}}}});
    requests.push_back({{"shape", {{"type", "cone"}, {"cone", {{"base_radius", v}}}}}});
    requests.push_back({{"shape", {{"type", "cone"}, {"cone", {{"height", v}}}}}});
    requests.push_back({{"shape", {{"type", "cone"}, {"cone", {{"tip_radius", v}}}}}});
    requests.push_back({{"shape", {{"segments", v}}}});
    requests.push_back({{"shape", {{"rings", v}}}});
    requests.push_back({{"plan", {{"start_machine", {v, 0, 0}}}}});
    requests.push_back({{"converge", {{"min_improvement", v}}}});
  }
  for (Json& request : requests) {
    if (!request.contains("probes")) request["probes"] = 40;
    request["plan_only"] = true;
    INFO(request.dump());
    const auto r = c.Post("/api/v1/runs", request.dump(), "application/json");
    REQUIRE(r);
    INFO(r->body);
    CHECK((r->status == 200 || r->status == 400));
    if (r->status == 400) {
      const Json e = Json::parse(r->body, nullptr, false);
      CHECK(e["error"]["code"] == "invalid");
      CHECK(e["error"]["field"].is_string());
      CHECK_THAT(r->body, !Catch::Contains("Options."));
    }
  }
  // The calibration request's numbers too: named by the request's keys, with their ranges.
  REQUIRE(PostRun(c, R"({"probes": 40})")->status == 201);
  const std::pair<const char*, const char*> calibrate_cases[] = {
      {R"({"max_epochs": 2e9})", "max_epochs"},
      {R"({"hidden": [0]})", "hidden"},
      {R"({"edge_exclusion": -1})", "edge_exclusion"},
      {R"({"fourier": 3000000000})", "fourier"},
      {R"({"smooth_sigma": 1e300})", "smooth_sigma"},
      {R"({"board_cols": 1.5})", "board_cols"},
      {R"({"max_validation_probes": 0})", "max_validation_probes"},
      {R"({"small_probe_repeat": 0})", "small_probe_repeat"},
      {R"({"small_probe_repeat": 17})", "small_probe_repeat"},
      {R"({"small_probe_repeat": "twice"})", "small_probe_repeat"}};
  for (const auto& [body, field] : calibrate_cases) {
    INFO(body);
    const auto r = c.Post("/api/v1/runs/1/calibrate", body, "application/json");
    REQUIRE(r);
    INFO(r->body);
    CHECK(r->status == 400);
    const Json e = Json::parse(r->body, nullptr, false);
    CHECK(e["error"]["field"] == field);
    CHECK_THAT(r->body, !Catch::Contains("Options."));
  }
  CHECK(c.Get("/api/v1/info")->status == 200);
  CHECK(daemon->Stop() == 0);
}

TEST_CASE(
    "misuse: `run start` hands every number to the daemon: 0, negatives and fractions "
    "exit 2 naming the field and its range",
    "[daemon][cli][misuse]") {
  test::RigFixture f("misuse-cli-numbers", 40, 0.0);
  auto daemon = test::StartDaemonProcess(f);
  const std::string url = daemon->url();
  for (const char* probes : {"0", "-3", "2.5", "1e9", "many"}) {
    INFO("--probes " << probes);
    const CliResult r = RunGs360(f.dir, url, {"run", "start", "--probes", probes, "--plan-only"});
    INFO(r.out << r.err);
    CHECK(r.exit_code == 2);
    CHECK_THAT(r.err, Catch::Contains("probes") && Catch::Contains("1..1000000"));
    CHECK_THAT(r.out, !Catch::Contains("plan:"));
  }
  CliResult r =
      RunGs360(f.dir, url, {"run", "start", "--probes", "40", "--seed", "-5", "--plan-only"});
  INFO(r.out << r.err);
  CHECK(r.exit_code == 2);
  CHECK_THAT(r.err, Catch::Contains("plan.seed") && Catch::Contains("0..18446744073709551615"));
  // In range, they are used as given.
  r = RunGs360(f.dir, url,
               {"run", "start", "--probes", "40", "--seed", "0", "--plan-only", "--json"});
  CHECK(r.exit_code == 0);
  CHECK(Json::parse(r.out)["candidates"] == 40);
  CHECK(daemon->Stop() == 0);
}

TEST_CASE(
    "misuse: names with control characters are refused at creation, and escaped where "
    "an older database's are printed",
    "[daemon][cli][api][misuse]") {
  test::RigFixture f("misuse-names", 40, 0.0);
  // An older database: a run whose name would clear the screen of whoever lists the runs.
  {
    std::filesystem::create_directories(f.dir / "data");
    RunEngine engine(f.dir / "data" / "gs360.db");
    RunConfig config = f.config;
    const RunEngine::PlannedRun planned = RunEngine::PlanRun(config);
    config.name = "\x1b[2J\x1b[Hevil\xc2\x9b";
    REQUIRE(engine.StoreRun(config, planned) == 1);
  }
  auto daemon = test::StartDaemonProcess(f);
  const std::string url = daemon->url();
  for (const auto& args :
       {std::vector<std::string>{"run", "list"}, std::vector<std::string>{"run", "status"},
        std::vector<std::string>{"run", "status", "1"}}) {
    const CliResult r = RunGs360(f.dir, url, args);
    INFO(args.back() << ": " << r.out << r.err);
    CHECK(r.exit_code == 0);
    CHECK_FALSE(HasControlBytes(r.out));
    CHECK_THAT(r.out, Catch::Contains("run 1 \\e[2J\\e[Hevil\\u{009b}"));
  }

  httplib::Client c = ClientOf(url);
  for (const Json& name : {Json("\x1b[2Jevil"), Json("a\nb"), Json("tab\there"),
                           Json("rtl\xe2\x80\xae"
                                "txt"),
                           Json(std::string(101, 'x'))}) {
    INFO(name.dump());
    const auto r =
        c.Post("/api/v1/runs", Json{{"name", name}, {"probes", 40}}.dump(), "application/json");
    REQUIRE(r);
    INFO(r->body);
    CHECK(r->status == 400);
    const Json e = Json::parse(r->body);
    CHECK(e["error"]["field"] == "name");
    CHECK_THAT(e["error"]["message"].get<std::string>(),
               Catch::Contains("printable UTF-8 without control characters") &&
                   Catch::Contains("at most 100 characters"));
    CHECK_FALSE(HasControlBytes(e["error"]["message"].get<std::string>()));
  }
  CHECK(Json::parse(c.Get("/api/v1/runs")->body)["runs"].size() == 1);
  // Letters of any script are names.
  const std::string fine = "Fingerspitze \xc3\xa4 \xe6\x8c\x87 07";
  auto r = c.Post("/api/v1/runs", Json{{"name", fine}, {"probes", 40}}.dump(), "application/json");
  REQUIRE(r->status == 201);
  CHECK(Json::parse(r->body)["name"] == fine);
  CliResult cli = RunGs360(
      f.dir, url, {"run", "start", "--name", "\x1b]0;pwned\x07", "--probes", "40", "--plan-only"});
  INFO(cli.out << cli.err);
  CHECK(cli.exit_code == 2);
  CHECK_THAT(cli.err, Catch::Contains("name") && Catch::Contains("U+001B"));
  CHECK_FALSE(HasControlBytes(cli.err));
  CHECK(daemon->Stop() == 0);
}

TEST_CASE(
    "misuse: export of a run without a finished calibration says so, exits 9 and creates "
    "nothing",
    "[daemon][cli][misuse]") {
  test::RigFixture f("misuse-export", 40, 0.0);
  auto daemon = test::StartDaemonProcess(f);
  const std::string url = daemon->url();
  httplib::Client c = ClientOf(url);
  REQUIRE(PostRun(c, R"({"probes": 40})")->status == 201);
  const auto out = f.dir / "exported";
  CliResult r = RunGs360(f.dir, url, {"export", "1", "--out", out.string()});
  INFO(r.out << r.err);
  CHECK(r.exit_code == 9);
  CHECK_THAT(r.err, Catch::Contains("run 1 has no finished calibration") &&
                        Catch::Contains("`gs360 calibrate 1`"));
  CHECK_FALSE(std::filesystem::exists(out));
  r = RunGs360(f.dir, url, {"export", "7", "--out", out.string()});
  CHECK(r.exit_code == 3);
  CHECK_THAT(r.err, Catch::Contains("no run 7"));
  CHECK_FALSE(std::filesystem::exists(out));
  CHECK(daemon->Stop() == 0);
}

TEST_CASE("misuse: a conflict reads right with the state the CLI adds to it",
          "[daemon][cli][misuse]") {
  // A daemon whose answers are fixed: the CLI's wording of each is what is under test.
  httplib::Server server;
  std::string state = "paused";
  std::string message = "run is already running";
  server.Post(
      R"(/api/v1/runs/1/(resume|pause))", [&](const httplib::Request&, httplib::Response& res) {
        res.status = 409;
        res.set_content(
            Json{{"error", {{"code", "conflict"}, {"message", message}, {"field", nullptr}}},
                 {"state", state}}
                .dump(),
            "application/json");
      });
  const int port = server.bind_to_any_port("127.0.0.1");
  std::thread serving([&] { server.listen_after_bind(); });
  const std::string url = "http://127.0.0.1:" + std::to_string(port);
  const auto dir = test::FreshDir("misuse-conflict");

  CliResult r = RunGs360(dir, url, {"run", "resume", "1"});
  INFO(r.err);
  CHECK(r.exit_code == 4);
  CHECK_THAT(r.err, !Catch::Contains("already running (the run is paused)"));
  CHECK_THAT(r.err, Catch::Contains("still ending") && Catch::Contains("paused") &&
                        Catch::Contains("try again"));
  state = "running";
  r = RunGs360(dir, url, {"run", "resume", "1"});
  CHECK(r.exit_code == 4);
  CHECK_THAT(r.err, Catch::EndsWith("run is already running\n"));
  state = "paused";
  message = "only a running run can be paused";
  r = RunGs360(dir, url, {"run", "pause", "1"});
  CHECK(r.exit_code == 4);
  CHECK_THAT(r.err, Catch::Contains("only a running run can be paused (the run is paused)"));
  server.stop();
  serving.join();
  std::filesystem::remove_all(dir);
}

TEST_CASE("misuse: a bad --mesh is named as the user gave it, and a folder is said to be one",
          "[daemon][cli][misuse]") {
  test::RigFixture f("misuse-mesh", 40, 0.0);
  auto daemon = test::StartDaemonProcess(f);
  const std::string url = daemon->url();
  const auto bad = f.dir / "finger-bad.stl";
  std::ofstream(bad) << "solid nothing\n garbage\n";
  CliResult r = RunGs360(f.dir, url, {"run", "start", "--mesh", bad.string(), "--plan-only"});
  INFO(r.out << r.err);
  CHECK(r.exit_code == 2);
  CHECK_THAT(r.err, Catch::Contains(bad.string()));
  CHECK_THAT(r.err, !Catch::Contains("upload-") && !Catch::Contains("the uploaded mesh") &&
                        !Catch::Contains((f.dir / "data").string()));
  const auto folder = f.dir / "meshes.stl";
  std::filesystem::create_directories(folder);
  r = RunGs360(f.dir, url, {"run", "start", "--mesh", folder.string(), "--plan-only"});
  INFO(r.out << r.err);
  CHECK(r.exit_code == 2);
  CHECK_THAT(r.err, Catch::Contains(folder.string()) && Catch::Contains("is a folder"));
  CHECK_THAT(r.err, !Catch::Contains("got \"\""));
  CHECK(daemon->Stop() == 0);
}

TEST_CASE("misuse: an invalid value in gs360d.toml names its line", "[daemon][misuse]") {
  const auto dir = test::FreshDir("misuse-toml");
  const auto config = dir / "gs360d.toml";
  std::ofstream(config) << "data_dir = \"data\"\n\n[machine]\nuri = \"/dev/null\"\nbaud = -5\n"
                        << "\n[plan]\nsettle_dwell_s = 1e300\n";
  CliResult r = test::RunProgram(
      dir, {std::string(GS360_BINARY_DIR) + "/daemon/gs360d", "--config", config.string()});
  INFO(r.out << r.err);
  CHECK(r.exit_code != 0);
  // The range check of [plan] comes as the file is read, naming its line too.
  CHECK_THAT(r.err, Catch::Contains(config.string() + ":8: plan.settle_dwell_s"));
  std::ofstream(config) << "data_dir = \"data\"\n\n[machine]\nuri = \"/dev/null\"\nbaud = -5\n";
  r = test::RunProgram(
      dir, {std::string(GS360_BINARY_DIR) + "/daemon/gs360d", "--config", config.string()});
  INFO(r.out << r.err);
  CHECK(r.exit_code != 0);
  CHECK_THAT(r.err, Catch::Contains(config.string() + ":5: machine.baud must be > 0, got -5"));
  std::filesystem::remove_all(dir);
}

TEST_CASE(
    "misuse: a second sim-rig on the paths a first one serves is refused and leaves them "
    "alone",
    "[daemon][cli][misuse]") {
  const auto dir = test::FreshDir("misuse-simrig");
  const auto tty = dir / "ttyCNC";
  const auto sock = dir / "cam.sock";
  const std::vector<std::string> args = {
      test::Gs360Path(), "sim-rig",    "--time-scale", "0",
      "--symlink",       tty.string(), "--socket",     sock.string()};
  const pid_t first = test::SpawnProgram(args, dir / "first.out", dir / "first.err");
  const auto ready = [&] {
    const std::string out = test::ReadWholeFile(dir / "first.out");
    return std::count(out.begin(), out.end(), '\n') >= 2;
  };
  REQUIRE(test::WaitUntil(ready, std::chrono::seconds(60)));
  const auto exits = [](pid_t pid, int* status) {
    return test::WaitUntil([&] { return waitpid(pid, status, WNOHANG) == pid; },
                           std::chrono::seconds(60));
  };

  // A second rig on the same symlink, then on the same socket: refused, naming the path.
  for (const auto& [what, second_args] :
       {std::pair{tty, args},
        std::pair{sock, std::vector<std::string>{test::Gs360Path(), "sim-rig", "--time-scale", "0",
                                                 "--socket", sock.string()}}}) {
    INFO(what);
    const pid_t second = test::SpawnProgram(second_args, dir / "second.out", dir / "second.err");
    int status = 0;
    const bool exited = exits(second, &status);
    if (!exited) {
      kill(second, SIGKILL);
      waitpid(second, &status, 0);
    }
    CHECK(exited);
    const std::string err = test::ReadWholeFile(dir / "second.err");
    INFO(err);
    CHECK(WIFEXITED(status));
    CHECK(WEXITSTATUS(status) == 1);
    CHECK_THAT(err, Catch::Contains(what.string()) && Catch::Contains("in use"));
  }
  // The first rig's paths are still its own and still serve.
  CHECK(std::filesystem::is_symlink(tty));
  CHECK(std::filesystem::exists(tty));
  const int fd = ::socket(AF_UNIX, SOCK_STREAM, 0);
  sockaddr_un addr{};
  addr.sun_family = AF_UNIX;
  std::snprintf(addr.sun_path, sizeof addr.sun_path, "%s", sock.c_str());
  CHECK(::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0);
  ::close(fd);

  // Once it has ended, the paths are free for the next one.
  kill(first, SIGTERM);
  int status = 0;
  REQUIRE(exits(first, &status));
  CHECK_FALSE(std::filesystem::exists(sock));
  const pid_t third = test::SpawnProgram(args, dir / "third.out", dir / "third.err");
  const auto third_ready = [&] {
    const std::string out = test::ReadWholeFile(dir / "third.out");
    return std::count(out.begin(), out.end(), '\n') >= 2;
  };
  CHECK(test::WaitUntil(third_ready, std::chrono::seconds(60)));
  kill(third, SIGTERM);
  CHECK(exits(third, &status));
  std::filesystem::remove_all(dir);
}

TEST_CASE(
    "misuse: `run resume` that goes straight back to a question exits 8 with the question "
    "and its answer, --watch follows, `run log` has times",
    "[daemon][cli][misuse][confirm]") {
  test::RigFixture f("misuse-resume", 40, 0.0, false, [](VirtualRigOptions& o) {
    o.cnc.settings.homing_enable = false;  // boots Idle at MPos 0,0,0
    o.cnc.settings.soft_limits = false;
  });
  auto daemon = StartNoHomingDaemon(f);
  const std::string url = daemon->url();
  REQUIRE(RunGs360(f.dir, url, {"run", "start", "--probes", "40"}).exit_code == 0);
  const auto asks = [&] {
    const CliResult s = RunGs360(f.dir, url, {"run", "status", "1", "--json"});
    const Json j = Json::parse(s.out, nullptr, false);
    return j.is_object() && j["awaiting"] == "position" && j["state"] == "created";
  };
  REQUIRE(test::WaitUntil(asks, std::chrono::seconds(60)));

  for (const auto& args : {std::vector<std::string>{"run", "resume", "1"},
                           std::vector<std::string>{"run", "resume", "1", "--watch"}}) {
    const CliResult r = RunGs360(f.dir, url, args);
    INFO(args.back() << ": " << r.out << r.err);
    CHECK(r.exit_code == 8);
    CHECK_THAT(r.out + r.err, Catch::Contains("confirm its position") &&
                                  Catch::Contains("`gs360 run resume 1 --confirm position`"));
    REQUIRE(test::WaitUntil(asks, std::chrono::seconds(60)));
  }
  const CliResult r =
      RunGs360(f.dir, url, {"run", "resume", "1", "--confirm", "position", "--watch"});
  INFO(r.out << r.err);
  CHECK(r.exit_code == 0);
  CHECK_THAT(r.out, Catch::Contains("done"));

  const CliResult log = RunGs360(f.dir, url, {"run", "log", "1"});
  INFO(log.out << log.err);
  REQUIRE(log.exit_code == 0);
  const std::regex timed(
      R"(^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} +(debug|info|warning|error) .+)");
  std::istringstream lines(log.out);
  int n = 0;
  for (std::string line; std::getline(lines, line); ++n) {
    INFO(line);
    CHECK(std::regex_match(line, timed));
  }
  CHECK(n >= 3);
  CHECK(daemon->Stop() == 0);
}
