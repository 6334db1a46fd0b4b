// gs360d's HTTP API with a real HTTP client, on the virtual rig: the run's life through the API,
// one controller per run, the event stream, meshes, and the attacks a listening daemon must
// survive.

#include <catch2/catch.hpp>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <fstream>
#include <regex>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

#include "api_helpers.h"
#include "base/version.h"
#include "daemon_fixture.h"
#include "geometry/mesh.h"
#include "geometry/shapes.h"
#include "storage/run_database.h"
#include "tests/wait.h"

using namespace gs360;
using Json = nlohmann::json;
using test::Body;
using test::kNone;
using test::PostJson;
using test::WaitRun;

namespace {

// Sends an HTTP request head on a raw socket, then up to `body_bytes` of body (as a client
// streaming a large upload would before the server answers), and returns the status line.
std::string RawStatus(const std::string& url, const std::string& head, std::size_t body_bytes) {
  const auto colon = url.rfind(':');
  const int port = std::stoi(url.substr(colon + 1));
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<std::uint16_t>(port));
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  REQUIRE(::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0);
  ::send(fd, head.data(), head.size(), MSG_NOSIGNAL);
  const std::string chunk(64 << 10, ' ');
  for (std::size_t sent = 0; sent < body_bytes; sent += chunk.size()) {
    if (::send(fd, chunk.data(), std::min(chunk.size(), body_bytes - sent), MSG_NOSIGNAL) <= 0) {
      break;  // the server answered and closed: fine
    }
  }
  ::shutdown(fd, SHUT_WR);  // the whole request is out: a server waiting for more sees the end
  std::string response;
  char buf[4096];
  for (ssize_t n; (n = ::recv(fd, buf, sizeof buf, 0)) > 0;) response.append(buf, n);
  ::close(fd);
  return response.substr(0, response.find("\r\n"));
}

}  // namespace

TEST_CASE("api: plan_only answers the plan, its rounds and its advice, and stores nothing",
          "[daemon][api]") {
  test::RigFixture f("api-plan", 60, 0.0);
  test::InProcessDaemon d(test::ConfigFor(f));
  httplib::Client c = d.Client();

  // plan_only answers the plan and stores nothing.
  auto r = PostJson(c, "/api/v1/runs", {{"probes", 60}, {"plan_only", true}});
  REQUIRE(r->status == 200);
  const Json plan = Body(r);
  CHECK(plan["probes_total"].get<int>() > 20);
  CHECK(plan["estimate_s"].get<double>() > 0.0);
  CHECK(plan["checkpoint_probes"] == 0);
  CHECK(Body(c.Get("/api/v1/runs"))["runs"].empty());
  // Rounds that each cover the surface: asked for in the request, said in the summary.
  r = PostJson(c, "/api/v1/runs",
               {{"probes", 60}, {"plan_only", true}, {"plan", {{"checkpoint_probes", 10}}}});
  REQUIRE(r->status == 200);
  CHECK(Body(r)["checkpoint_probes"] == 10);
  CHECK(Body(r)["probes_total"] == plan["probes_total"]);
  r = PostJson(c, "/api/v1/runs", {{"probes", 60}, {"plan", {{"checkpoint_probes", -1}}}});
  CHECK(r->status == 400);
  CHECK(Body(r)["error"]["message"].get<std::string>().find("checkpoint_probes") !=
        std::string::npos);
  // A plan that keeps little says what to change; one that keeps nothing is a 400 saying it.
  r = PostJson(c, "/api/v1/runs",
               {{"probes", 60}, {"plan_only", true}, {"plan", {{"max_view_angle_rad", 0.5}}}});
  REQUIRE(r->status == 200);
  REQUIRE_FALSE(Body(r)["advice"].empty());
  CHECK(Body(r)["advice"][0].get<std::string>().find("max_view_angle_rad") != std::string::npos);
  CHECK(plan["advice"].empty());
  r = PostJson(c, "/api/v1/runs", {{"probes", 60}, {"plan", {{"max_view_angle_rad", 0.01}}}});
  CHECK(r->status == 400);
  CHECK(Body(r)["error"]["field"] == "plan");
  CHECK(Body(r)["error"]["message"].get<std::string>().find("max_view_angle_rad") !=
        std::string::npos);
  CHECK(Body(c.Get("/api/v1/runs"))["runs"].empty());
}

TEST_CASE("api: plan, start, pause and resume a run, and two resumes at once get one 409",
          "[daemon][api]") {
  test::RigFixture f("api-run", 60, 0.0);
  test::InProcessDaemon d(test::ConfigFor(f));
  httplib::Client c = d.Client();

  // The plan a run will get, to compare with the run created below.
  auto r = PostJson(c, "/api/v1/runs", {{"probes", 60}, {"plan_only", true}});
  REQUIRE(r->status == 200);
  const Json plan = Body(r);

  r = PostJson(c, "/api/v1/runs", {{"name", "api"}, {"probes", 60}});
  REQUIRE(r->status == 201);
  const Json created = Body(r);
  const std::int64_t id = created["id"];
  CHECK(created["state"] == "created");
  CHECK(created["probes_total"] == plan["probes_total"]);  // kept probes, not candidates
  CHECK(created["candidates"] == 60);

  // Follow the event stream from the start.
  std::atomic<bool> stop_stream{false};
  std::vector<std::pair<std::string, Json>> events;
  std::mutex events_mutex;
  std::thread stream([&] {
    httplib::Client s(d.url);
    s.set_read_timeout(30, 0);
    std::string buffer;
    s.Get("/api/v1/events?run=1", [&](const char* data, std::size_t n) {
      buffer.append(data, n);
      for (std::size_t end; (end = buffer.find("\n\n")) != std::string::npos;) {
        std::istringstream block(buffer.substr(0, end));
        buffer.erase(0, end + 2);
        std::string line, type;
        Json payload;
        while (std::getline(block, line)) {
          if (line.rfind("event: ", 0) == 0) type = line.substr(7);
          if (line.rfind("data: ", 0) == 0) payload = Json::parse(line.substr(6));
        }
        if (!type.empty()) {
          std::lock_guard lock(events_mutex);
          events.emplace_back(type, payload);
        }
      }
      return !stop_stream.load();
    });
  });

  REQUIRE(PostJson(c, "/api/v1/runs/1/start", Json::object())->status == 202);
  // Starting it again, or another action that does not apply, is a conflict naming the state.
  r = PostJson(c, "/api/v1/runs/1/start", Json::object());
  CHECK(r->status == 409);
  CHECK(Body(r)["error"]["code"] == "conflict");
  CHECK(Body(r).contains("state"));

  WaitRun(c, id, [](const Json& run) { return run["probes_done"].get<int>() >= 5; });
  REQUIRE(PostJson(c, "/api/v1/runs/1/pause", Json::object())->status == 202);
  const Json paused = WaitRun(c, id, [](const Json& run) { return run["state"] == "paused"; });
  const int done_at_pause = paused["probes_done"];

  // Two clients resume at once: exactly one wins.
  std::vector<int> statuses(2);
  {
    const auto resume = [&](int k) {
      httplib::Client own(d.url);
      statuses[k] = PostJson(own, "/api/v1/runs/1/resume", Json::object())->status;
    };
    std::thread a(resume, 0);
    std::thread b(resume, 1);
    a.join();
    b.join();
  }
  CHECK(std::multiset<int>(statuses.begin(), statuses.end()) == std::multiset<int>{202, 409});
  const Json done = WaitRun(c, id, [](const Json& run) { return run["state"] == "done"; });
  // Every probe pressed; the few the true camera cannot see (behind a fin's edge) fail for want
  // of an impression.
  CHECK(done["probes_done"].get<int>() + done["probes_failed"].get<int>() ==
        done["probes_total"].get<int>());
  CHECK(done["probes_failed"].get<int>() <= 2);
  CHECK(done["probes_done"].get<int>() > done_at_pause);
  CHECK(done["last_error"].is_null());

  // The run's probes and frames.
  const Json probes = Body(c.Get("/api/v1/runs/1/probes"));
  CHECK(probes["probes"].size() == done["probes_total"].get<std::size_t>());
  CHECK(probes["probes"][0]["state"] == "captured");
  r = c.Get("/api/v1/runs/1/probes/0/frame.png");
  REQUIRE(r->status == 200);
  CHECK(r->get_header_value("Content-Type") == "image/png");
  CHECK(r->body.substr(1, 3) == "PNG");
  CHECK(c.Get("/api/v1/runs/1/frames/latest.png")->status == 200);
  CHECK(c.Get("/api/v1/runs/1/probes/99999/frame.png")->status == 404);

  // The stream saw the progress advance and the state changes (the run log reaches it within
  // the event pump's period).
  const auto seen_done = [&] {
    std::lock_guard lock(events_mutex);
    for (const auto& [type, data] : events) {
      if (type == "state" && data["state"] == "done") return true;
    }
    return false;
  };
  test::WaitUntil(seen_done, std::chrono::seconds(10));
  stop_stream = true;
  d.daemon->events().Publish("log", {{"run", 1}});  // the stream's next chunk ends it
  stream.join();
  std::lock_guard lock(events_mutex);
  int last_done = -1, progress = 0;
  std::set<std::string> states;
  for (const auto& [type, data] : events) {
    if (type == "progress") {
      CHECK(data["probes_done"].get<int>() >= last_done);
      last_done = data["probes_done"];
      ++progress;
    }
    if (type == "state") states.insert(data["state"].get<std::string>());
  }
  CHECK(progress >= 3);
  CHECK(last_done > 0);
  CHECK(states.count("running"));
  CHECK(states.count("paused"));
  CHECK(states.count("done"));
}

TEST_CASE("api: delete, cancel and calibrate answer 202, 204, 404 or 409 by state",
          "[daemon][api]") {
  test::RigFixture f("api-states", 40, 0.0);
  test::InProcessDaemon d(test::ConfigFor(f));
  httplib::Client c = d.Client();
  REQUIRE(PostJson(c, "/api/v1/runs", {{"probes", 40}})->status == 201);
  REQUIRE(PostJson(c, "/api/v1/runs", {{"probes", 40}})->status == 201);
  // Nothing captured yet: nothing to calibrate.
  auto r = PostJson(c, "/api/v1/runs/1/calibrate", Json::object());
  CHECK(r->status == 409);
  CHECK_THAT(Body(r)["error"]["message"].get<std::string>(), Catch::Contains("no captured"));
  CHECK(Body(c.Get("/api/v1/runs/1/calibration"))["state"] == "none");
  CHECK(c.Get("/api/v1/runs/1/model")->status == 404);
  // A created run can be resumed only after it started; it can be cancelled at once.
  CHECK(PostJson(c, "/api/v1/runs/2/resume", Json::object())->status == 409);
  r = PostJson(c, "/api/v1/runs/2/cancel", Json::object());
  CHECK(r->status == 202);
  CHECK(Body(r)["state"] == "cancelled");
  CHECK(PostJson(c, "/api/v1/runs/2/cancel", Json::object())->status == 409);
  // Half-created or finished runs can be deleted; then they are gone.
  CHECK(c.Delete("/api/v1/runs/2")->status == 204);
  CHECK(c.Get("/api/v1/runs/2")->status == 404);
  CHECK(c.Delete("/api/v1/runs/2")->status == 404);
  // A running run cannot.
  REQUIRE(PostJson(c, "/api/v1/runs/1/start", Json::object())->status == 202);
  r = c.Delete("/api/v1/runs/1");
  CHECK(r->status == 409);
  CHECK(PostJson(c, "/api/v1/runs/1/calibrate", Json::object())->status == 409);
  REQUIRE(PostJson(c, "/api/v1/runs/1/cancel", Json::object())->status == 202);
  const Json cancelled = WaitRun(c, 1, [](const Json& run) { return run["state"] == "cancelled"; });
  CHECK(cancelled["probes_done"].get<int>() >= 0);
  // Cancel parked the tool at the plan's start position.
  const Eigen::Vector3d at = f.rig->cnc().ReportedPosition();
  const Eigen::Vector3d start = PlanOptions{}.start_machine;
  CHECK((at - start).norm() < 0.01);
  CHECK(c.Delete("/api/v1/runs/1")->status == 204);
}

TEST_CASE("api: uploaded meshes are checked and addressed by id", "[daemon][api]") {
  test::RigFixture f("api-mesh", 40, 0.0);
  test::InProcessDaemon d(test::ConfigFor(f));
  httplib::Client c = d.Client();
  const auto stl = f.dir / "finger.stl";
  WriteStlBinary(stl, MakeRevolutionMesh(*MakeProfile(SensorShapeOptions{})));
  std::ifstream in(stl, std::ios::binary);
  std::stringstream bytes;
  bytes << in.rdbuf();
  auto r = c.Post("/api/v1/meshes?format=stl", bytes.str(), "application/octet-stream");
  REQUIRE(r->status == 201);
  const Json mesh = Body(r);
  const std::string id = mesh["id"];
  CHECK(id.size() == 16);
  CHECK(mesh["triangles"].get<int>() > 1000);
  CHECK(Body(c.Get("/api/v1/meshes"))["meshes"].size() == 1);
  r = PostJson(c, "/api/v1/runs", {{"mesh", id}, {"probes", 40}, {"plan_only", true}});
  CHECK(r->status == 200);
  CHECK(Body(r)["probes_total"].get<int>() > 5);
  // A mesh that is not one, an unknown format, an unknown id.
  r = c.Post("/api/v1/meshes?format=stl", std::string("solid nothing\n garbage"),
             "application/octet-stream");
  CHECK(r->status == 400);
  CHECK(Body(r)["error"]["code"] == "invalid_mesh");
  CHECK(Body(r)["error"]["message"].get<std::string>().find(f.dir.string()) == std::string::npos);
  CHECK(c.Post("/api/v1/meshes?format=exe", bytes.str(), "application/octet-stream")->status ==
        400);
  r = PostJson(c, "/api/v1/runs", {{"mesh", "../../etc/passwd"}});
  CHECK(r->status == 400);
  CHECK(Body(r)["error"]["field"] == "mesh");
  // Only the good mesh was kept.
  CHECK(Body(c.Get("/api/v1/meshes"))["meshes"].size() == 1);
}

TEST_CASE("api: info reports the version and the commit the daemon was built from",
          "[daemon][api]") {
  test::RigFixture f("api-info", 40, 0.0);
  test::InProcessDaemon d(test::ConfigFor(f));
  httplib::Client c = d.Client();
  const auto r = c.Get("/api/v1/info");
  REQUIRE(r);
  REQUIRE(r->status == 200);
  const nlohmann::json info = nlohmann::json::parse(r->body);
  CHECK(info.at("version") == std::string(Version()));
  CHECK(std::regex_match(std::string(Version()), std::regex(R"(\d+\.\d+\.\d+)")));
  const std::string commit = info.at("commit");
  CHECK(commit == std::string(Commit()));
  // A build from this git clone knows its commit (a tarball build says "unknown").
  CHECK(std::regex_match(commit, std::regex("[0-9a-f]{12}(-dirty)?")));
  CHECK(VersionLine("gs360d") == "gs360d " + std::string(Version()) + " (commit " + commit + ")");
}

TEST_CASE("api: bad requests get 400 naming the field, and the daemon keeps serving",
          "[daemon][api][security]") {
  test::RigFixture f("api-bad", 40, 0.0);
  test::InProcessDaemon d(test::ConfigFor(f));
  httplib::Client c = d.Client();
  struct Case {
    std::string body;
    std::string field;
  };
  const Case cases[] = {
      {R"({"probes": "many"})", "probes"},
      {R"({"probes": -3})", "probes"},
      {R"({"shape": {"type": "banana"}})", "shape.type"},
      {R"({"shape": {"cylinder": {"radius": -1}}})", ""},
      {R"({"plan": {"press_depth": 5}})", "plan.press_depth"},
      {R"({"plan": {"machine": {}}})", "plan.machine"},
      {R"({"colour": "red"})", "colour"},
      {R"([1, 2, 3])", ""},
      {R"({"probes": 40,)", ""},
      {"\xff\xfe{}", ""},
  };
  for (const Case& k : cases) {
    INFO(k.body);
    const auto r = c.Post("/api/v1/runs", k.body, "application/json");
    REQUIRE(r);
    CHECK(r->status == 400);
    const Json e = Body(r);
    CHECK(e["error"]["code"] == "invalid");
    if (!k.field.empty()) CHECK(e["error"]["field"] == k.field);
  }
  auto r = PostJson(c, "/api/v1/runs", {{"probes", 40}});
  REQUIRE(r->status == 201);
  r = PostJson(c, "/api/v1/runs/1/pause", {{"force", true}});
  CHECK(r->status == 400);
  CHECK(Body(r)["error"]["field"] == "force");
  r = PostJson(c, "/api/v1/runs/1/calibrate", {{"max_epochs", "ten"}});
  CHECK(r->status == 400);
  CHECK(Body(r)["error"]["field"] == "max_epochs");
  for (const char* field : {"board_cols", "board_rows", "square_mm"}) {
    r = PostJson(c, "/api/v1/runs/1/calibrate", {{field, 0}});
    CHECK(r->status == 400);
    CHECK(Body(r)["error"]["field"] == field);
  }
  r = PostJson(c, "/api/v1/runs/1/calibrate", {{"from", "everything"}});
  CHECK(r->status == 400);
  CHECK(Body(r)["error"]["field"] == "from");
  r = PostJson(c, "/api/v1/runs/1/calibrate", {{"to", "the end"}});
  CHECK(r->status == 400);
  CHECK(Body(r)["error"]["field"] == "to");
  r = PostJson(c, "/api/v1/runs/1/calibrate", {{"only", 3}});
  CHECK(r->status == 400);
  CHECK(Body(r)["error"]["field"] == "only");
  r = PostJson(c, "/api/v1/runs/1/calibrate", {{"only", "train"}, {"to", "export"}});
  CHECK(r->status == 400);
  // Named by the request's key, not the C++ option it sets.
  CHECK(Body(r)["error"]["field"] == "only");
  CHECK_THAT(
      Body(r)["error"]["message"].get<std::string>(),
      Catch::Contains("only (\"train\") runs one stage") && !Catch::Contains("CalibrationOptions"));
  CHECK(c.Get("/api/v1/info")->status == 200);
  CHECK(Body(c.Get("/api/v1/runs"))["runs"].size() == 1);
}

TEST_CASE("api: attacks: path-like ids, huge bodies, foreign hosts, cross-site posts",
          "[daemon][api][security]") {
  test::RigFixture f("api-attack", 40, 0.0);
  test::InProcessDaemon d(test::ConfigFor(f));
  httplib::Client c = d.Client();
  REQUIRE(PostJson(c, "/api/v1/runs", {{"probes", 40}})->status == 201);
  // Ids are numbers; anything path-like names nothing.
  for (const char* path :
       {"/api/v1/runs/..%2F..%2F..%2Fetc%2Fpasswd", "/api/v1/runs/1%2F..%2F..%2Fgs360.db",
        "/api/v1/runs/../../gs360.db", "/api/v1/runs/-1", "/api/v1/runs/0x1",
        "/api/v1/runs/99999999999999999999999", "/api/v1/runs/1/probes/..%2F0/frame.png",
        "/api/v1/runs/1/probes/-1/frame.png", "/gs360.db", "/../gs360.db", "/api/v1/../../x",
        "/api/v1/runs/%00/model", "/app.js/../../gs360.db"}) {
    INFO(path);
    const auto r = c.Get(path);
    REQUIRE(r);
    CHECK((r->status == 404 || r->status == 400));
    CHECK(r->body.find("SQLite") == std::string::npos);
  }
  // A 10 MB JSON body: 413 as soon as its length is known, nothing read into memory.
  const std::size_t huge = 10u << 20;
  CHECK(RawStatus(d.url,
                  "POST /api/v1/runs HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: "
                  "application/json\r\nContent-Length: " +
                      std::to_string(huge) + "\r\n\r\n",
                  huge)
            .rfind("HTTP/1.1 413 ", 0) == 0);
  // Cross-site posts: a form or text/plain body is refused before anything happens.
  auto r = c.Post("/api/v1/runs/1/start", "a=1", "application/x-www-form-urlencoded");
  CHECK(r->status == 415);
  r = c.Post("/api/v1/runs/1/start", "{}", "text/plain");
  CHECK(r->status == 415);
  CHECK(Body(c.Get("/api/v1/runs/1"))["state"] == "created");
  // DNS rebinding: a Host that is not loopback is refused when there is no token.
  r = c.Get("/api/v1/info", {{"Host", "attacker.example:7360"}});
  CHECK(r->status == 403);
  r = c.Get("/", {{"Host", "attacker.example"}});
  CHECK(r->status == 403);
  // And the daemon still answers.
  CHECK(c.Get("/api/v1/info")->status == 200);
  r = c.Get("/");
  REQUIRE(r->status == 200);
  CHECK_THAT(r->get_header_value("Content-Security-Policy"), Catch::Contains("default-src 'self'"));
}

TEST_CASE("api: with a token every request needs it, and a wrong one gets 401",
          "[daemon][api][security]") {
  test::RigFixture f("api-token", 40, 0.0);
  const std::string token = "s3cret-token-for-the-test-0123";
  DaemonConfig config = test::ConfigFor(f);
  config.server.token = token;
  config.server.max_upload_bytes = 2 << 20;
  test::InProcessDaemon d(config);
  httplib::Client c = d.Client();
  auto r = c.Get("/api/v1/info");
  CHECK(r->status == 401);
  CHECK(r->get_header_value("WWW-Authenticate") == "Bearer");
  CHECK(Body(r)["error"]["code"] == "unauthorized");
  CHECK(c.Get("/api/v1/info", {{"Authorization", "Bearer wrong-token"}})->status == 401);
  CHECK(c.Get("/api/v1/info", {{"Authorization", "Bearer " + token + "x"}})->status == 401);
  CHECK(c.Get("/api/v1/info", {{"Authorization", "Basic " + token}})->status == 401);
  CHECK(PostJson(c, "/api/v1/runs", {{"probes", 40}})->status == 401);
  CHECK(Body(c.Get("/api/v1/runs", {{"Authorization", "Bearer " + token}}))["runs"].empty());
  const httplib::Headers auth = {{"Authorization", "Bearer " + token}};
  CHECK(c.Get("/api/v1/info", auth)->status == 200);
  CHECK(c.Get(("/api/v1/info?token=" + token).c_str())->status == 200);
  // With a token, the Host does not matter (the daemon may be reached by any name).
  CHECK(
      c.Get("/api/v1/info", {{"Authorization", "Bearer " + token}, {"Host", "rig.lab"}})->status ==
      200);
  // The dashboard's page itself holds no data and is served; the API behind it is not.
  CHECK(c.Get("/")->status == 200);
  // An upload above the limit: 413 before the body is read, even without the token's check
  // coming first for an authorised client.
  CHECK(RawStatus(d.url,
                  "POST /api/v1/meshes?format=stl HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                  "Authorization: Bearer " +
                      token + "\r\nContent-Type: application/octet-stream\r\nContent-Length: " +
                      std::to_string(3 << 20) + "\r\n\r\n",
                  3 << 20)
            .rfind("HTTP/1.1 413 ", 0) == 0);
  // A chunked body that passes the limit and then never ends (the client stops sending): no
  // answer can follow a body that never ended, the connection is closed, nothing is stored.
  CHECK_THAT(RawStatus(d.url,
                       "POST /api/v1/meshes?format=stl HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                       "Authorization: Bearer " +
                           token +
                           "\r\nContent-Type: application/octet-stream\r\nTransfer-Encoding: "
                           "chunked\r\n\r\n300000\r\n",
                       3 << 20),
             !Catch::StartsWith("HTTP/1.1 2"));
  CHECK(Body(c.Get("/api/v1/meshes", auth))["meshes"].empty());
  CHECK(c.Get("/api/v1/info", auth)->status == 200);
  CHECK(SameSecret("abc", "abc"));
  CHECK_FALSE(SameSecret("abc", "abd"));
  CHECK_FALSE(SameSecret("abc", "abcd"));
  CHECK_FALSE(SameSecret("", "a"));
}

TEST_CASE("api: an unplugged machine interrupts the run with last_error, and resume reconnects",
          "[daemon][api][fault]") {
  test::RigFixture f("api-unplug", 60, 0.0, /*symlink=*/true);
  test::InProcessDaemon d(
      DaemonConfigFromToml(test::RigToml(f.config, "", 1.0), "test.toml", f.dir));
  httplib::Client c = d.Client();
  REQUIRE(PostJson(c, "/api/v1/runs", {{"probes", 60}})->status == 201);
  REQUIRE(PostJson(c, "/api/v1/runs/1/start", Json::object())->status == 202);
  WaitRun(c, 1, [](const Json& run) { return run["probes_done"].get<int>() >= 4; });
  f.rig->cnc().Unplug();  // and nobody plugs it back in within the reconnect timeout
  const Json stopped = WaitRun(c, 1, [](const Json& run) { return run["state"] == "interrupted"; });
  REQUIRE(stopped["last_error"].is_string());
  CHECK_THAT(stopped["last_error"].get<std::string>(),
             Catch::Contains("did not come back") || Catch::Contains("could not recover"));
  f.rig->cnc().Replug();  // under another /dev/pts name; the configured symlink follows it
  REQUIRE(PostJson(c, "/api/v1/runs/1/resume", Json::object())->status == 202);
  const auto ended = [](const Json& run) {
    return run["state"] == "done" || run["state"] == "interrupted";
  };
  Json done = WaitRun(c, 1, ended);
  // The board lost power with the cable: if the tool may have been in the gel, the run asks
  // before homing; the user checks and confirms.
  if (done["awaiting"] == "position") {
    CHECK_THAT(done["last_error"].get<std::string>(), Catch::Contains("in or near the gel"));
    // Confirming something else than what it waits for is refused.
    CHECK(PostJson(c, "/api/v1/runs/1/resume", {{"confirm", "sensor"}})->status == 409);
    REQUIRE(PostJson(c, "/api/v1/runs/1/resume", {{"confirm", "position"}})->status == 202);
    done = WaitRun(c, 1, ended);
  }
  CHECK(done["state"] == "done");
  CHECK(done["last_error"].is_null());  // cleared when it ran again
  CHECK(done["awaiting"].is_null());
  CHECK(done["probes_done"].get<int>() + done["probes_failed"].get<int>() ==
        done["probes_total"].get<int>());
}

TEST_CASE("api: a machine alarm stops the run, says why, and nothing unlocks it",
          "[daemon][api][fault]") {
  test::RigFixture f("api-alarm", 60, 0.0);
  test::InProcessDaemon d(test::ConfigFor(f));
  httplib::Client c = d.Client();
  REQUIRE(PostJson(c, "/api/v1/runs", {{"probes", 60}})->status == 201);
  REQUIRE(PostJson(c, "/api/v1/runs/1/start", Json::object())->status == 202);
  WaitRun(c, 1, [](const Json& run) { return run["probes_done"].get<int>() >= 3; });
  f.rig->cnc().RaiseAlarmDuringNextMove(1, 0.5);
  const Json stopped = WaitRun(c, 1, [](const Json& run) { return run["state"] == "interrupted"; });
  REQUIRE(stopped["last_error"].is_string());
  CHECK_THAT(stopped["last_error"].get<std::string>(), Catch::Contains("ALARM:1"));
  // The controller is left in its alarm: the daemon did not clear it.
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  CHECK(f.rig->cnc().State() == GrblState::kAlarm);
  // The log has it as an alarm.
  const Json log = Body(c.Get("/api/v1/runs/1/log"));
  bool alarm = false;
  for (const Json& e : log["events"]) {
    if (e["level"] == "error" &&
        e["message"].get<std::string>().find("ALARM:1") != std::string::npos) {
      alarm = true;
    }
  }
  CHECK(alarm);
}
