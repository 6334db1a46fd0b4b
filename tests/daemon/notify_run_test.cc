// Notifications from a running gs360d on the virtual rig to a real webhook receiver: what a run
// sends from its creation to its end, an alarm, the API's view and test, and [[notify]] tables
// that are wrong.

#include <catch2/catch.hpp>

#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "api_helpers.h"
#include "base/base64.h"
#include "daemon_fixture.h"
#include "storage/run_database.h"
#include "tests/daemon/webhook_receiver.h"
#include "tests/wait.h"

using namespace gs360;
using Json = nlohmann::json;
using test::Body;
using test::PostJson;
using test::WaitRun;

namespace {

std::string NotifyToml(const test::Receiver& rx, const std::string& path,
                       const std::string& extra = "") {
  return "\n[[notify]]\nurl = \"" + rx.Url(path) + "\"\nbackoff_s = 0.05\n" + extra;
}

// Waits until the receiver has `n` requests; returns their events.
std::vector<std::string> WaitEvents(const test::Receiver& rx, std::size_t n) {
  test::WaitUntil([&] { return rx.Count() >= n; }, std::chrono::seconds(30));
  return rx.Events();
}

}  // namespace

TEST_CASE("notify: a run tells the webhook it was created, started, paused, resumed and done",
          "[daemon][notify]") {
  test::Receiver rx;
  test::RigFixture f("notify-run", 30, 0.0);
  test::InProcessDaemon d(
      test::ConfigFor(f, NotifyToml(rx, "/hook/secret-abc", "attach_frame = true\n")));
  httplib::Client c = d.Client();
  REQUIRE(PostJson(c, "/api/v1/runs", {{"probes", 30}, {"name", "finger-07"}})->status == 201);
  REQUIRE(PostJson(c, "/api/v1/runs/1/start", Json::object())->status == 202);
  WaitRun(c, 1, [](const Json& run) { return run["probes_done"].get<int>() >= 3; });
  REQUIRE(PostJson(c, "/api/v1/runs/1/pause", Json::object())->status == 202);
  WaitRun(c, 1, [](const Json& run) { return run["state"] == "paused"; });
  REQUIRE(PostJson(c, "/api/v1/runs/1/resume", Json::object())->status == 202);
  const Json ended = WaitRun(c, 1, [](const Json& v) { return v["state"] == "done"; });

  const auto events = WaitEvents(rx, 5);
  CHECK(events == std::vector<std::string>{"created", "started", "paused", "resumed", "done"});
  const Json done = Json::parse(rx.Body(rx.Count() - 1));
  CHECK(done["run"] == 1);
  CHECK(done["run_name"] == "finger-07");
  CHECK(done["title"] == "gs360 run 1 (finger-07): done");
  CHECK(done["progress"]["probes_total"] == ended["probes_total"]);
  CHECK(done["progress"]["probes_done"] == ended["probes_done"]);
  CHECK(done["action"] == "gs360 calibrate 1");
  CHECK(done["dashboard_url"] == d.url + "/#run=1");
  CHECK(rx.Path(0) == "/hook/secret-abc");
  // attach_frame: the run's last frame, as the API serves it; none before the first capture.
  CHECK_FALSE(Json::parse(rx.Body(0)).contains("frame_png_base64"));
  const auto latest = c.Get("/api/v1/runs/1/frames/latest.png");
  REQUIRE(latest);
  REQUIRE(latest->status == 200);
  const std::vector<std::uint8_t> png(latest->body.begin(), latest->body.end());
  CHECK(done["frame_png_base64"] == Base64Encode(png));

  // The API names the receiver without its secret path, with its counts.
  const Json view = Body(c.Get("/api/v1/notify"));
  REQUIRE(view["notifiers"].size() == 1);
  const Json& n = view["notifiers"][0];
  CHECK(n["delivered"] == 5);
  CHECK(n["failed"] == 0);
  CHECK(view.dump().find("secret-abc") == std::string::npos);

  // A test notification, about a run or none; a run that is not there is 404.
  auto r = PostJson(c, "/api/v1/notify/test", {{"run", 1}});
  REQUIRE(r);
  CHECK(r->status == 202);
  CHECK(Body(r)["sent_to"] == 1);
  CHECK(WaitEvents(rx, 6).back() == "test");
  CHECK(c.Post("/api/v1/notify/test", "", "application/json")->status == 202);
  CHECK(WaitEvents(rx, 7).back() == "test");
  CHECK(PostJson(c, "/api/v1/notify/test", {{"run", 99}})->status == 404);
  CHECK(PostJson(c, "/api/v1/notify/test", {{"run", "one"}})->status == 400);
  CHECK(PostJson(c, "/api/v1/notify/test", {{"to", "everyone"}})->status == 400);
}

TEST_CASE("notify: an alarm is sent once with what to do, and not again as an interruption",
          "[daemon][notify][fault]") {
  test::Receiver rx;
  test::RigFixture f("notify-alarm", 60, 0.0);
  test::InProcessDaemon d(test::ConfigFor(
      f,
      NotifyToml(rx, "/alarm", "events = [\"started\", \"alarm\", \"interrupted\", \"done\"]\n")));
  httplib::Client c = d.Client();
  REQUIRE(PostJson(c, "/api/v1/runs", {{"probes", 60}})->status == 201);
  REQUIRE(PostJson(c, "/api/v1/runs/1/start", Json::object())->status == 202);
  WaitRun(c, 1, [](const Json& run) { return run["probes_done"].get<int>() >= 3; });
  f.rig->cnc().RaiseAlarmDuringNextMove(1, 0.5);
  WaitRun(c, 1, [](const Json& run) { return run["state"] == "interrupted"; });
  // The alarm reaches the hub through the run log, after the session's end: wait for it, then
  // stop the daemon, which sends whatever is still waiting (an interruption would be).
  REQUIRE(test::WaitUntil([&] { return rx.Count() >= 2; }, std::chrono::seconds(30)));
  d.daemon->Shutdown();
  CHECK(rx.Events() == std::vector<std::string>{"started", "alarm"});
  const Json alarm = Json::parse(rx.Body(1));
  CHECK_THAT(alarm["message"].get<std::string>(), Catch::Contains("ALARM:1"));
  CHECK(alarm["action"] == "gs360 run resume 1");
}

TEST_CASE("notify: gs360d started after a crash says which run was left running",
          "[daemon][notify]") {
  test::Receiver rx;
  test::RigFixture f("notify-unclean", 30, 0.0);
  const DaemonConfig quiet = test::ConfigFor(f);
  {
    test::InProcessDaemon d(quiet);
    httplib::Client c = d.Client();
    REQUIRE(PostJson(c, "/api/v1/runs", {{"probes", 30}, {"name", "overnight"}})->status == 201);
  }
  // As the database is after a power cut mid-run: the run is still marked running.
  RunDatabase(quiet.DatabasePath()).SetRunState(1, RunState::kRunning);
  test::InProcessDaemon d(test::ConfigFor(f, NotifyToml(rx, "/unclean")));
  REQUIRE(WaitEvents(rx, 1) == std::vector<std::string>{"unclean_start"});
  const Json n = Json::parse(rx.Body(0));
  CHECK(n["run"] == 1);
  CHECK(n["title"] == "gs360 run 1 (overnight): was running when gs360d stopped uncleanly");
  CHECK(n["action"] == "gs360 run resume 1");
}

TEST_CASE("notify: a [[notify]] table that is wrong stops gs360d naming the line and the key",
          "[daemon][notify][config]") {
  const std::string ok = "[[notify]]\nurl = \"https://ntfy.sh/lab\"\nformat = \"ntfy\"\n";
  const DaemonConfig c = DaemonConfigFromToml(
      ok + "[[notify]]\ncommand = [\"apprise\", \"-b\"]\nevents = [\"done\", \"alarm\"]\n",
      "gs360d.toml");
  REQUIRE(c.notify.size() == 2);
  CHECK(c.notify[0].format == "ntfy");
  CHECK(c.notify[1].command == std::vector<std::string>{"apprise", "-b"});
  CHECK(c.notify[1].events == std::vector<std::string>{"done", "alarm"});
  // --print-config shows the URL without its path.
  const std::string printed = DaemonConfigToToml(c);
  CHECK(printed.find("https://ntfy.sh/...") != std::string::npos);
  CHECK(printed.find("lab") == std::string::npos);
  // Written for another gs360d to read (gs360 demo --config), the URL is whole.
  const DaemonConfig again = DaemonConfigFromToml(DaemonConfigToToml(c, true), "again.toml");
  REQUIRE(again.notify.size() == 2);
  CHECK(again.notify[0].url == "https://ntfy.sh/lab");
  CHECK(again.notify[1].command == c.notify[1].command);

  struct Case {
    std::string toml, message;
  };
  const std::vector<Case> cases = {
      {ok + "[[notify]]\nurl = \"https://x.org/h\"\nevents = [\"finished\"]\n",
       "gs360d.toml:6: notify[1].events: unknown event \"finished\""},
      {ok + "[[notify]]\nurl = \"https://x.org/h\"\nretries = -2\n",
       "gs360d.toml:6: notify[1].retries must be in [0, 20], got -2"},
      {ok + "[[notify]]\nurl = \"https://x.org/h\"\ncommand = [\"x\"]\n",
       "notify[1]: give exactly one of url and command"},
      {ok + "[[notify]]\nurl = \"https://x.org/h\"\nheaders = 1\n", "notify[1].headers"},
      {ok + "[[notify]]\ncommand = \"apprise -b\"\n", "expected a list of strings"},
      {"notify = 3\n", "expected a list of tables"},
  };
  for (const Case& k : cases) {
    INFO(k.toml);
    CHECK_THROWS_WITH(DaemonConfigFromToml(k.toml, "gs360d.toml"), Catch::Contains(k.message));
  }
}
