// The notifier (daemon/notifier.h) against real receivers: a local HTTP server that answers,
// hangs, fails with 500 or is not there, and real commands (sh) reading the notification.

#include <catch2/catch.hpp>

#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <set>
#include <sstream>
#include <thread>

#include <httplib.h>
#include <nlohmann/json.hpp>

#include "base/base64.h"
#include "daemon/notifier.h"
#include "daemon/notify_feed.h"
#include "tests/daemon/webhook_receiver.h"
#include "tests/wait.h"

using namespace gs360;
using namespace std::chrono_literals;
using Json = nlohmann::json;

namespace {

Json RunView() {
  return {{"id", 3},
          {"name", "finger-07"},
          {"state", "interrupted"},
          {"probes_done", 812},
          {"probes_total", 2011},
          {"probes_failed", 2},
          {"eta_s", 3720.0},
          {"last_error", "ALARM:1 hard limit"},
          {"awaiting", "position"}};
}

NotifyTarget Webhook(const std::string& url) {
  NotifyTarget t;
  t.url = url;
  t.timeout_s = 2.0;
  t.retries = 0;
  t.backoff_s = 0.01;
  return t;
}

const Json& Target(const Notifier& n, std::size_t i) {
  static Json view;
  view = n.View();
  return view["notifiers"].at(i);
}

}  // namespace

TEST_CASE("notify: a notification says what happened, the progress, the error and what to do",
          "[daemon][notify]") {
  const Notification n =
      MakeNotification(NotifyEvent::kAwaitingConfirmation, RunView(), "", "http://127.0.0.1:7360/");
  CHECK(n.title == "gs360 run 3 (finger-07): waits for you to confirm");
  CHECK(n.run == 3);
  CHECK(n.action == "gs360 run resume 3 --confirm position");
  CHECK_THAT(n.message, Catch::Contains("812 of 2011 probes, 2 failed, ETA 1h 02m"));
  CHECK_THAT(n.message, Catch::Contains("Last error: ALARM:1 hard limit"));
  CHECK_THAT(n.message, Catch::Contains("To go on: gs360 run resume 3 --confirm position"));
  CHECK(n.dashboard_url == "http://127.0.0.1:7360/#run=3");
  const Json j = n.ToJson();
  CHECK(j["event"] == "awaiting_confirmation");
  CHECK(j["progress"]["probes_total"] == 2011);

  const Notification alarm =
      MakeNotification(NotifyEvent::kAlarm, RunView(), "ALARM:1 hard limit", "");
  CHECK(alarm.action == "gs360 run resume 3");
  // The detail is the error: said once.
  CHECK(alarm.message.find("Last error") == std::string::npos);
  CHECK(MakeNotification(NotifyEvent::kTest, nullptr, "", "").title == "gs360: test notification");

  SECTION("each format") {
    const WebhookRequest ntfy = FormatWebhook(alarm, "ntfy");
    CHECK(ntfy.content_type.rfind("text/plain", 0) == 0);
    CHECK(ntfy.body.rfind("ALARM:1 hard limit", 0) == 0);
    CHECK(std::count(ntfy.headers.begin(), ntfy.headers.end(),
                     std::pair<std::string, std::string>{"Priority", "high"}) == 1);
    CHECK(Json::parse(FormatWebhook(alarm, "slack").body)["text"].get<std::string>().rfind(
              alarm.title, 0) == 0);
    CHECK(Json::parse(FormatWebhook(alarm, "discord").body).contains("content"));
    CHECK(Json::parse(FormatWebhook(alarm, "json").body)["event"] == "alarm");
  }
}

TEST_CASE("notify: a [[notify]] table that cannot work is refused naming the field",
          "[daemon][notify]") {
  NotifyTarget t;
  CHECK_THROWS_WITH(t.Check(), Catch::Contains("exactly one of url and command"));
  t.url = "ftp://example.org/x";
  CHECK_THROWS_WITH(t.Check(), Catch::Contains("notify.url must start with http:// or https://"));
  t.url = "https://ntfy.sh/topic\r\nX-Injected: 1";
  CHECK_THROWS_WITH(t.Check(), Catch::Contains("must not contain spaces or control characters"));
  t.url = "https://ntfy.sh/a topic";
  CHECK_THROWS_WITH(t.Check(), Catch::Contains("must not contain spaces or control characters"));
  t.url = "https://ntfy.sh/secret-topic";
  t.command = {"apprise"};
  CHECK_THROWS_WITH(t.Check(), Catch::Contains("exactly one of url and command"));
  t.command.clear();
  t.events = {"done", "finished"};
  CHECK_THROWS_WITH(t.Check(), Catch::Contains("unknown event \"finished\""));
  t.events = {"done"};
  t.format = "teams";
  CHECK_THROWS_WITH(t.Check(),
                    Catch::Contains("notify.format must be json, ntfy, slack or discord"));
  t.format = "ntfy";
  t.timeout_s = 0;
  CHECK_THROWS_WITH(t.Check(), Catch::Contains("notify.timeout_s must be in (0, 600] s, got 0"));
  t.timeout_s = 5;
  CHECK_NOTHROW(t.Check());
  CHECK(t.Describe() == "https://ntfy.sh/... (ntfy)");
  CHECK(t.RedactedUrl() == "https://ntfy.sh/...");
  CHECK(t.Wants(NotifyEvent::kDone));
  CHECK_FALSE(t.Wants(NotifyEvent::kStarted));
  CHECK(t.Wants(NotifyEvent::kTest));  // a test reaches every target
  // The notifier names which table.
  NotifyTarget bad = t;
  bad.retries = -1;
  CHECK_THROWS_WITH(Notifier({t, bad}), Catch::StartsWith("notify[1].retries must be in [0, 20]"));
}

TEST_CASE("notify: a webhook receives every event kind, in order, as JSON", "[daemon][notify]") {
  test::Receiver rx;
  Notifier notifier({Webhook(rx.Url("/hook"))});
  for (NotifyEvent e : AllNotifyEvents()) notifier.Send(MakeNotification(e, RunView(), "", ""));
  REQUIRE(notifier.WaitIdle(test::Scaled(20s)));
  REQUIRE(rx.Count() == AllNotifyEvents().size());
  for (std::size_t i = 0; i < rx.Count(); ++i) {
    const Json body = Json::parse(rx.Body(i));
    CHECK(body["event"] == std::string(ToString(AllNotifyEvents()[i])));
    CHECK(body["run"] == 3);
    CHECK(body["run_name"] == "finger-07");
    CHECK(rx.Path(i) == "/hook");
  }
  const Json& view = Target(notifier, 0);
  CHECK(view["delivered"] == AllNotifyEvents().size());
  CHECK(view["failed"] == 0);
  CHECK(view["recent"][0]["ok"] == true);
}

TEST_CASE("notify: only the events a target asks for reach it, and ntfy gets its headers",
          "[daemon][notify]") {
  test::Receiver rx;
  NotifyTarget t = Webhook(rx.Url("/gs360-lab"));
  t.format = "ntfy";
  t.events = {"alarm", "done"};
  Notifier notifier({t});
  notifier.Send(MakeNotification(NotifyEvent::kStarted, RunView(), "", ""));
  notifier.Send(MakeNotification(NotifyEvent::kAlarm, RunView(), "ALARM:1", ""));
  notifier.Send(MakeNotification(NotifyEvent::kPaused, RunView(), "", ""));
  REQUIRE(notifier.WaitIdle(test::Scaled(10s)));
  REQUIRE(rx.Count() == 1);
  CHECK(rx.Title(0) == "gs360 run 3 (finger-07): machine alarm");
  CHECK(rx.Body(0).rfind("ALARM:1", 0) == 0);
}

namespace {

// Bytes that stand for a frame's PNG: the notifier passes them on as they are.
std::shared_ptr<const std::vector<std::uint8_t>> FramePng() {
  std::vector<std::uint8_t> png = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n', 0, 0xff};
  for (int i = 0; i < 3000; ++i) png.push_back(static_cast<std::uint8_t>(i * 7));
  return std::make_shared<const std::vector<std::uint8_t>>(std::move(png));
}

}  // namespace

TEST_CASE(
    "notify: attach_frame sends the frame: base64 in JSON, an ntfy attachment, a Discord file",
    "[daemon][notify]") {
  test::Receiver rx;
  NotifyTarget json = Webhook(rx.Url("/json"));
  json.attach_frame = true;
  NotifyTarget ntfy = Webhook(rx.Url("/ntfy"));
  ntfy.format = "ntfy";
  ntfy.attach_frame = true;
  NotifyTarget discord = Webhook(rx.Url("/discord"));
  discord.format = "discord";
  discord.attach_frame = true;
  const NotifyTarget plain = Webhook(rx.Url("/plain"));
  NotifyTarget slack = Webhook(rx.Url("/slack"));
  slack.format = "slack";
  slack.attach_frame = true;
  CHECK_THROWS_WITH(slack.Check(), Catch::Contains("notify.attach_frame: Slack"));

  Notification n = MakeNotification(NotifyEvent::kAlarm, RunView(), "ALARM:1", "http://h/");
  n.frame_png = FramePng();
  const std::string png(n.frame_png->begin(), n.frame_png->end());
  // One target at a time: the receiver's order is then the targets'.
  for (const NotifyTarget& t : {json, ntfy, discord, plain}) {
    Notifier notifier({t});
    CHECK(notifier.WantsFrame(NotifyEvent::kAlarm) == t.attach_frame);
    notifier.Send(n);
    REQUIRE(notifier.WaitIdle(test::Scaled(10s)));
  }
  REQUIRE(rx.Count() == 4);
  CHECK(Json::parse(rx.Body(0))["frame_png_base64"] == Base64Encode(*n.frame_png));
  CHECK(Json::parse(rx.Body(0))["event"] == "alarm");

  CHECK(rx.Header(1, "Content-Type") == "image/png");
  CHECK(rx.Body(1) == png);
  CHECK(rx.Title(1) == "gs360 run 3 (finger-07): machine alarm");
  CHECK(rx.Header(1, "Filename") == "gs360-run-3-frame.png");
  const std::string message = rx.Header(1, "Message");
  CHECK(message.rfind("ALARM:1\\n812 of 2011 probes", 0) == 0);
  CHECK(message.find('\n') == std::string::npos);

  CHECK_THAT(rx.Header(2, "Content-Type"), Catch::StartsWith("multipart/form-data; boundary="));
  CHECK(rx.Part(2, "files[0]") == png);
  CHECK_THAT(Json::parse(rx.Part(2, "payload_json"))["content"].get<std::string>(),
             Catch::StartsWith("gs360 run 3 (finger-07): machine alarm\nALARM:1"));

  CHECK_FALSE(Json::parse(rx.Body(3)).contains("frame_png_base64"));
}

TEST_CASE("notify: a receiver that fails, hangs or is not there costs retries, then a count",
          "[daemon][notify]") {
  std::ostringstream log;
  auto sink = std::make_shared<spdlog::sinks::ostream_sink_mt>(log);
  auto logger = std::make_shared<spdlog::logger>("notify-test", sink);
  logger->set_level(spdlog::level::debug);
  auto previous = spdlog::default_logger();
  spdlog::set_default_logger(logger);

  SECTION("500: every attempt is made, then the notification is dropped and counted") {
    test::Receiver rx;
    rx.status = 500;
    NotifyTarget t = Webhook(rx.Url("/secret-token-123"));
    t.retries = 2;
    Notifier notifier({t});
    notifier.Send(MakeNotification(NotifyEvent::kDone, RunView(), "", ""));
    REQUIRE(notifier.WaitIdle(test::Scaled(20s)));
    CHECK(rx.Count() == 3);
    const Json& view = Target(notifier, 0);
    CHECK(view["failed"] == 1);
    CHECK(view["delivered"] == 0);
    CHECK(view["recent"][0]["error"] == "HTTP 500");
    CHECK(view["recent"][0]["attempts"] == 3);
  }
  SECTION("nobody listens: no answer") {
    int port = 0;
    {
      test::Receiver gone;  // a port that was free a moment ago and is closed now
      port = std::stoi(gone.Url("").substr(std::string("http://127.0.0.1:").size()));
    }
    NotifyTarget t = Webhook("http://127.0.0.1:" + std::to_string(port) + "/secret-token-123");
    t.retries = 1;
    Notifier notifier({t});
    notifier.Send(MakeNotification(NotifyEvent::kAlarm, RunView(), "", ""));
    REQUIRE(notifier.WaitIdle(test::Scaled(20s)));
    const Json& view = Target(notifier, 0);
    CHECK(view["failed"] == 1);
    CHECK_THAT(view["recent"][0]["error"].get<std::string>(), Catch::StartsWith("no answer"));
  }
  SECTION("a receiver that hangs: Send never waits for it, and a full queue drops and counts") {
    test::Receiver rx;
    rx.delay_ms = 2500;
    NotifyTarget t = Webhook(rx.Url("/secret-token-123"));
    t.timeout_s = 1.0;  // long enough that the first is still under way while the rest are sent
    t.queue_size = 3;
    Notifier notifier({t});
    // The first is taken by the worker (and hangs); three wait; the rest find the queue full.
    notifier.Send(MakeNotification(NotifyEvent::kStarted, RunView(), "", ""));
    REQUIRE(test::WaitUntil([&] { return rx.Count() == 1; }, 10s));
    for (int i = 0; i < 10; ++i)
      notifier.Send(MakeNotification(NotifyEvent::kDone, RunView(), "", ""));
    CHECK(Target(notifier, 0)["dropped"] == 7);
    CHECK(Target(notifier, 0)["waiting"] == 3);
    REQUIRE(notifier.WaitIdle(test::Scaled(30s)));
    const Json& view = Target(notifier, 0);
    CHECK(view["failed"] == 4);  // each timed out
    CHECK_THAT(view["recent"][0]["error"].get<std::string>(), Catch::StartsWith("no answer"));
  }
  spdlog::set_default_logger(previous);
  // A URL's path and query hold the receiver's secret: never logged, never shown.
  CHECK_THAT(log.str(), Catch::Contains("dropped after"));
  CHECK(log.str().find("secret-token-123") == std::string::npos);
}

TEST_CASE("notify: a command gets the notification as JSON on stdin and in GS360_ variables",
          "[daemon][notify]") {
  const auto dir =
      std::filesystem::temp_directory_path() / ("gs360-notify-" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  const std::string out = (dir / "out").string();
  NotifyTarget t;
  t.command = {
      "sh", "-c",
      "cat > '" + out + "'; echo \"$GS360_EVENT $GS360_RUN $GS360_ACTION\" >> '" + out + "'"};
  t.timeout_s = 5;
  t.retries = 0;
  {
    Notifier notifier({t});
    notifier.Send(MakeNotification(NotifyEvent::kAwaitingConfirmation, RunView(), "", ""));
    REQUIRE(notifier.WaitIdle(test::Scaled(20s)));
    CHECK(Target(notifier, 0)["delivered"] == 1);
  }
  std::ifstream in(out);
  std::string json_line, env_line;
  std::getline(in, json_line);
  std::getline(in, env_line);
  CHECK(Json::parse(json_line)["event"] == "awaiting_confirmation");
  CHECK(env_line == "awaiting_confirmation 3 gs360 run resume 3 --confirm position");

  SECTION("with attach_frame, a file of the frame for the command, removed after it") {
    t.attach_frame = true;
    t.command = {"sh", "-c",
                 "cat > '" + out + "'; cp \"$GS360_FRAME\" '" + out +
                     ".png'; echo \"$GS360_FRAME\" >> '" + out + "'"};
    Notification n = MakeNotification(NotifyEvent::kDone, RunView(), "", "");
    n.frame_png = FramePng();
    {
      Notifier notifier({t});
      notifier.Send(n);
      REQUIRE(notifier.WaitIdle(test::Scaled(20s)));
      CHECK(Target(notifier, 0)["delivered"] == 1);
    }
    std::ifstream result(out);
    std::string stdin_line, path_line;
    std::getline(result, stdin_line);
    std::getline(result, path_line);
    CHECK(Json::parse(stdin_line)["frame_path"] == path_line);
    CHECK_FALSE(path_line.empty());
    CHECK_FALSE(std::filesystem::exists(path_line));
    std::ifstream copy(out + ".png", std::ios::binary);
    const std::string copied((std::istreambuf_iterator<char>(copy)), {});
    CHECK(copied == std::string(n.frame_png->begin(), n.frame_png->end()));
  }
  SECTION("a failing command: its exit code and last line") {
    t.command = {"sh", "-c", "echo first; echo 'no route to host' >&2; exit 3"};
    Notifier notifier({t});
    notifier.Send(MakeNotification(NotifyEvent::kDone, RunView(), "", ""));
    REQUIRE(notifier.WaitIdle(test::Scaled(20s)));
    CHECK(Target(notifier, 0)["recent"][0]["error"] == "exit code 3: no route to host");
  }
  SECTION("a command that hangs is killed at its time-out") {
    t.command = {"sleep", "30"};
    t.timeout_s = 0.2;
    Notifier notifier({t});
    notifier.Send(MakeNotification(NotifyEvent::kDone, RunView(), "", ""));
    REQUIRE(notifier.WaitIdle(test::Scaled(20s)));
    CHECK(Target(notifier, 0)["recent"][0]["error"] == "timed out; killed");
  }
  SECTION("a program that is not there") {
    t.command = {"gs360-no-such-notifier"};
    Notifier notifier({t});
    notifier.Send(MakeNotification(NotifyEvent::kDone, RunView(), "", ""));
    REQUIRE(notifier.WaitIdle(test::Scaled(20s)));
    CHECK_THAT(Target(notifier, 0)["recent"][0]["error"].get<std::string>(),
               Catch::StartsWith("cannot run gs360-no-such-notifier"));
  }
  std::filesystem::remove_all(dir);
}

TEST_CASE("notify: a session that fails leaves an interruption, sent unless its alarm was",
          "[daemon][notify]") {
  std::set<std::int64_t> alarmed;
  const auto end = [](const std::string& outcome, const std::string& state) {
    return HubEvent{0, "run_end",
                    Json{{"run", 3}, {"outcome", outcome}, {"state", state}, {"message", "why"}}};
  };
  // The run can be resumed (a camera that stopped): an interruption, with its reason.
  auto item = TranslateHubEvent(end("failed", "interrupted"), alarmed);
  REQUIRE(item);
  CHECK(item->event == NotifyEvent::kInterrupted);
  CHECK(item->detail == "why");
  // The run itself failed.
  item = TranslateHubEvent(end("failed", "failed"), alarmed);
  REQUIRE(item);
  CHECK(item->event == NotifyEvent::kFailed);
  // After the session's alarm, its end says nothing new: neither "failed" nor "interrupted".
  REQUIRE(TranslateHubEvent(HubEvent{0, "alarm", Json{{"run", 3}, {"message", "ALARM:1"}}}, alarmed)
              ->event == NotifyEvent::kAlarm);
  CHECK_FALSE(TranslateHubEvent(end("failed", "interrupted"), alarmed));
  CHECK_FALSE(TranslateHubEvent(end("stopped", "interrupted"), alarmed));
}
