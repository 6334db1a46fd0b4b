// The gs360 command line as a user drives it against gs360d on the virtual rig: start, status
// --json, pause, resume, the daemon SIGKILLed mid-run and started again (the run interrupted, the
// machine unmoved), resume to the end, calibrate and export; every kept probe has exactly one
// frame and the exported files load. Then the exit codes of the mistakes a user makes.

#include <catch2/catch.hpp>

#include <fcntl.h>
#include <spawn.h>
#include <sys/wait.h>

#include <fstream>
#include <set>
#include <sstream>
#include <thread>

#include <opencv2/dnn.hpp>

#include "api_helpers.h"
#include "cli/daemon_client.h"
#include "daemon_fixture.h"
#include "gcode/grbl_client.h"
#include "recon/model_bundle.h"
#include "storage/run_database.h"
#include "tests/wait.h"

extern char** environ;

using namespace gs360;
using Json = nlohmann::json;

namespace {

struct CliResult {
  int exit_code = -1;
  std::string out;
  std::string err;
};

std::string ReadFile(const std::filesystem::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// Runs `gs360 --daemon URL ARGS...` and collects its exit code, stdout and stderr.
CliResult Gs360(const std::filesystem::path& dir, const std::string& url,
                const std::vector<std::string>& args) {
  static int n = 0;
  const auto out = dir / ("cli-" + std::to_string(++n) + ".out");
  const auto err = dir / ("cli-" + std::to_string(n) + ".err");
  std::vector<std::string> full = {std::string(GS360_BINARY_DIR) + "/cli/gs360", "--daemon", url};
  full.insert(full.end(), args.begin(), args.end());
  std::vector<char*> argv;
  for (auto& a : full) argv.push_back(a.data());
  argv.push_back(nullptr);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, out.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_addopen(&actions, 2, err.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  pid_t pid = -1;
  REQUIRE(posix_spawn(&pid, argv[0], &actions, nullptr, argv.data(), environ) == 0);
  posix_spawn_file_actions_destroy(&actions);
  int status = 0;
  waitpid(pid, &status, 0);
  CliResult r;
  r.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : 128;
  r.out = ReadFile(out);
  r.err = ReadFile(err);
  return r;
}

Json JsonOf(const CliResult& r) {
  INFO("stdout: " << r.out << "\nstderr: " << r.err);
  const Json j = Json::parse(r.out, nullptr, false);
  REQUIRE_FALSE(j.is_discarded());
  return j;
}

Json Status(const std::filesystem::path& dir, const std::string& url) {
  const CliResult r = Gs360(dir, url, {"run", "status", "1", "--json"});
  REQUIRE(r.exit_code == 0);
  return JsonOf(r);
}

template <typename Pred>
Json WaitStatus(const std::filesystem::path& dir, const std::string& url, Pred pred) {
  Json run;
  const auto done = [&] {
    run = Status(dir, url);
    return pred(run);
  };
  if (!test::WaitUntil(done, std::chrono::seconds(60)))
    FAIL("timed out; last status " << run.dump());
  return run;
}

}  // namespace

TEST_CASE(
    "the CLI drives a run on gs360d through pause, resume, a SIGKILL of the daemon, "
    "calibration and export",
    "[daemon][cli][e2e]") {
  // Enough probes that the run is still going when the test pauses and kills it: at instant
  // motion a probe takes some 20-100 ms and each CLI poll a few hundred.
  test::RigFixture f("cli", 300, 0.0);
  auto daemon = test::StartDaemonProcess(f);
  const auto& dir = f.dir;

  CliResult r =
      Gs360(dir, daemon->url(), {"run", "start", "--name", "cli", "--probes", "300", "--json"});
  REQUIRE(r.exit_code == 0);
  const Json started = JsonOf(r);
  REQUIRE(started["run"]["id"] == 1);
  const int total = started["run"]["probes_total"];
  CHECK(total >= 150);
  CHECK(total <= 260);

  Json run = WaitStatus(dir, daemon->url(), [](const Json& s) { return s["probes_done"] >= 8; });
  CHECK(run["state"] == "running");
  CHECK(run["rate_per_h"].get<double>() > 0.0);
  CHECK(run["eta_s"].get<double>() >= 0.0);
  CHECK(run["machine_position"].size() == 3);

  REQUIRE(Gs360(dir, daemon->url(), {"run", "pause", "1"}).exit_code == 0);
  run = WaitStatus(dir, daemon->url(), [](const Json& s) { return s["state"] == "paused"; });
  const int paused_at = run["probes_done"];
  r = Gs360(dir, daemon->url(), {"run", "pause", "1"});
  CHECK(r.exit_code == 4);  // conflict: not running
  CHECK_THAT(r.err, Catch::Contains("paused"));

  REQUIRE(Gs360(dir, daemon->url(), {"run", "resume", "1"}).exit_code == 0);
  WaitStatus(dir, daemon->url(), [&](const Json& s) { return s["probes_done"] >= paused_at + 8; });

  // Power cut, as far as the daemon knows.
  daemon->Kill();
  // Let the controller finish what it had queued (lines still in its receive buffer too, and
  // their replies written out), then note where it stands. A restart sooner is the kill loop's
  // case; here the start-up must find it at rest.
  const auto at_rest = [&] {
    const auto& cnc = f.rig->cnc();
    return cnc.PlannerBlocksQueued() == 0 && cnc.RxBufferUsed() == 0 &&
           cnc.PendingOutputBytes() == 0 && cnc.TrueSpeed(std::chrono::steady_clock::now()) == 0.0;
  };
  REQUIRE(test::WaitUntil(
      [&] {
        if (!at_rest()) return false;
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
        return at_rest();
      },
      std::chrono::seconds(5)));
  const Eigen::Vector3d before = f.rig->cnc().TruePositionNow();
  daemon = test::StartDaemonProcess(f);
  run = Status(dir, daemon->url());
  CHECK(run["state"] == "interrupted");  // never "running" after its daemon died
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  CHECK((f.rig->cnc().TruePositionNow() - before).norm() < 1e-9);  // start-up did not move it

  REQUIRE(Gs360(dir, daemon->url(), {"run", "resume", "1"}).exit_code == 0);
  r = Gs360(dir, daemon->url(), {"run", "status", "1", "--watch"});
  INFO("last_error: " << Status(dir, daemon->url())["last_error"].dump());
  INFO(test::DaemonLogProblems(f.dir / "gs360d.log"));
  INFO(r.out << r.err);
  CHECK(r.exit_code == 0);
  CHECK_THAT(r.out, Catch::Contains("done"));
  run = Status(dir, daemon->url());
  CHECK(run["state"] == "done");
  // Every probe pressed; the few the true camera cannot see fail for want of an impression.
  const int captured = run["probes_done"];
  CHECK(captured + run["probes_failed"].get<int>() == total);
  CHECK(captured >= total - 6);
  // Both resumes re-pressed committed probes and found them where they were: noise alone once
  // made this one stop with "the sensor has moved" (issue 32; docs/running.md, "Interruptions").
  r = Gs360(dir, daemon->url(), {"run", "log", "1"});
  CHECK_THAT(r.out, Catch::Contains("re-pressed probes match their stored frames") &&
                        !Catch::Contains("sensor has moved"));

  {
    RunDatabaseOptions ro;
    ro.read_only = true;
    RunDatabase db(f.dir / "data" / "gs360.db", ro);
    const auto frames = db.ListFrames(1, FrameKind::kPress);
    CHECK(frames.size() == static_cast<std::size_t>(captured));
    std::set<std::int64_t> probes;
    for (const auto& fr : frames) CHECK(probes.insert(*fr.probe_id).second);
    const cli::CaptureTruth truth = cli::CheckCapturesAgainstTruth(*f.rig, db, 1);
    CHECK(truth.frames == captured);
    CHECK(truth.off_target == 0);
    CHECK(truth.unverified == 0);
  }

  // Up to the pose only: the later stages are skipped, and no model is claimed.
  r = Gs360(dir, daemon->url(), {"calibrate", "1", "--to", "pose"});
  INFO(r.out << r.err);
  REQUIRE(r.exit_code == 0);
  CHECK_THAT(r.out, Catch::Contains("no model exported") && Catch::Contains("skipped"));
  CHECK_THAT(r.out, Catch::Contains("intrinsics: fx ") && Catch::Contains("nominal"));
  r = Gs360(dir, daemon->url(), {"calibrate", "1", "--max-epochs", "4"});
  INFO(r.out << r.err);
  REQUIRE(r.exit_code == 0);
  CHECK_THAT(r.out, Catch::Contains("targets:") && Catch::Contains("export"));
  // A few probes and four epochs cannot meet the targets: the summary says so, and what to do.
  CHECK_THAT(r.out, Catch::Contains("warning: the model misses accuracy targets") &&
                        Catch::Contains("warning: only ") && Catch::Contains("probe_count"));
  const auto out = dir / "exported";
  r = Gs360(dir, daemon->url(), {"export", "1", "--out", out.string(), "--json"});
  REQUIRE(r.exit_code == 0);
  const Json exported = JsonOf(r);
  CHECK(exported["files"].size() == 4);
  const ModelBundle bundle = ReadModelBundle(out / "run-1.gs360model");
  CHECK(bundle.mlp.input_size() > 0);
  CHECK_NOTHROW(cv::dnn::readNetFromONNX((out / "run-1.onnx").string()));
  CHECK_THAT(ReadFile(out / "run-1-report.html"), Catch::Contains("<html"));
  CHECK(Json::parse(ReadFile(out / "run-1-validation.json")).contains("results"));
  CHECK(daemon->Stop() == 0);
}

TEST_CASE("the CLI's exit codes say what went wrong", "[daemon][cli]") {
  test::RigFixture f("cli-codes", 40, 0.0);
  auto daemon = test::StartDaemonProcess(f);
  const auto& dir = f.dir;
  // No such run: an error, not silence.
  CliResult r = Gs360(dir, daemon->url(), {"run", "status", "7"});
  CHECK(r.exit_code == 3);
  CHECK_THAT(r.err, Catch::Contains("no run 7"));
  CHECK(r.out.empty());
  CHECK(Gs360(dir, daemon->url(), {"run", "resume", "7"}).exit_code == 3);
  // Invalid requests name the field.
  r = Gs360(dir, daemon->url(), {"run", "start", "--shape", "banana"});
  CHECK(r.exit_code == 2);
  CHECK_THAT(r.err, Catch::Contains("shape.type"));
  // Usage errors.
  CHECK(Gs360(dir, daemon->url(), {"run", "status", "one"}).exit_code == 2);
  CHECK(Gs360(dir, daemon->url(), {"frobnicate"}).exit_code == 2);
  // Nothing at the URL.
  r = Gs360(dir, "http://127.0.0.1:1", {"run", "list"});
  CHECK(r.exit_code == 5);
  CHECK_THAT(r.err, Catch::Contains("cannot reach gs360d"));
  // -v logs go to stderr: --json output stays parseable.
  REQUIRE(Gs360(dir, daemon->url(), {"run", "start", "--probes", "40", "--plan-only"}).exit_code ==
          0);
  r = Gs360(dir, daemon->url(), {"-vv", "run", "list", "--json"});
  CHECK(r.exit_code == 0);
  CHECK(JsonOf(r)["runs"].empty());
  // Plan-only stores nothing; a created run can be deleted, and then it is gone.
  r = Gs360(dir, daemon->url(), {"run", "start", "--probes", "40", "--plan-only", "--json"});
  CHECK(JsonOf(r)["probes_total"].get<int>() > 5);
  CHECK(daemon->Stop() == 0);
}

namespace {

// Jogs the virtual machine as a user at a terminal would while gs360d is down: `lines`, each
// waited for; returns where the tool then truly stands.
Eigen::Vector3d JogByHand(test::RigFixture& f, const std::vector<std::string>& lines) {
  GrblClientOptions o;
  o.status_poll_interval = std::chrono::milliseconds(0);
  auto client = GrblClient::ForUri(f.rig->PtyPath(), TransportOptions{}, o);
  client->Connect();
  client->MarkPositionTrusted();
  for (const std::string& line : lines) {
    const GrblReply r = client->Send(line).Wait(std::chrono::seconds(10));
    INFO(line << ": " << r.Describe());
    REQUIRE(r.Ok());
  }
  REQUIRE(client->WaitIdle(std::chrono::seconds(10)) == GrblWaitResult::kIdle);
  return f.rig->cnc().TruePositionNow();
}

// The distance in "..., 2.999 mm from any point of ..." (a position message); -1 if none.
double MmFromMotion(const std::string& text) {
  const auto end = text.find(" mm from any point");
  if (end == std::string::npos) return -1.0;
  const auto start = text.find_last_of(" (", end - 1);
  return std::stod(text.substr(start + 1, end - start - 1));
}

std::string RunLog(const std::filesystem::path& dir, const std::string& url) {
  const CliResult r = Gs360(dir, url, {"run", "log", "1"});
  REQUIRE(r.exit_code == 0);
  return r.out;
}

}  // namespace

TEST_CASE(
    "a confirmation nobody asked for gets 409 and exit code 4, an asked one answers only its "
    "question and goes on record with the difference",
    "[daemon][cli][confirm]") {
  test::RigFixture f("confirm", 60, 0.0);
  auto daemon = test::StartDaemonProcess(f);
  const auto& dir = f.dir;
  REQUIRE(Gs360(dir, daemon->url(), {"run", "start", "--probes", "60"}).exit_code == 0);
  WaitStatus(dir, daemon->url(), [](const Json& s) { return s["probes_done"] >= 3; });
  REQUIRE(daemon->Stop() == 0);  // finishes the probe, retracts: the run is interrupted
  // With the daemon down, the tool is jogged 3 mm (up, away from the gel).
  const Eigen::Vector3d jogged = JogByHand(f, {"G91 G0 Z3", "G90"});
  daemon = test::StartDaemonProcess(f);
  const std::string url = daemon->url();

  // Nothing was asked: the confirmation is refused, through the API and the CLI, nothing moves.
  httplib::Client http(url);
  const auto refused = test::PostJson(http, "/api/v1/runs/1/resume", {{"confirm", "position"}});
  REQUIRE(refused);
  CHECK(refused->status == 409);
  const Json error = Json::parse(refused->body);
  CHECK(error["error"]["code"] == "conflict");
  CHECK_THAT(
      error["error"]["message"].get<std::string>(),
      Catch::Contains("no confirmation was asked for") && Catch::Contains("without --confirm"));
  CliResult r = Gs360(dir, url, {"run", "resume", "1", "--confirm", "position"});
  CHECK(r.exit_code == 4);
  CHECK_THAT(r.err, Catch::Contains("no confirmation was asked for") &&
                        Catch::Contains("`gs360 run resume 1`"));
  Json run = Status(dir, url);
  CHECK(run["state"] == "interrupted");
  CHECK(run["awaiting"].is_null());
  CHECK((f.rig->cnc().TruePositionNow() - jogged).norm() < 1e-9);

  // Resumed without: the position check runs and asks, naming the difference.
  r = Gs360(dir, url, {"run", "resume", "1"});
  CHECK(r.exit_code == cli::kExitAwaiting);
  run = WaitStatus(dir, url, [](const Json& s) {
    return s["awaiting"] == "position" && s["state"] == "interrupted";
  });
  CHECK(MmFromMotion(run["last_error"].get<std::string>()) == Approx(3.0).margin(0.002));
  CHECK((f.rig->cnc().TruePositionNow() - jogged).norm() < 1e-9);
  // Another question's answer is no answer.
  CHECK(Gs360(dir, url, {"run", "resume", "1", "--confirm", "sensor"}).exit_code == 4);

  // Confirmed: the run goes on, and its log says what the user took as true.
  REQUIRE(Gs360(dir, url, {"run", "resume", "1", "--confirm", "position"}).exit_code == 0);
  r = Gs360(dir, url, {"run", "status", "1", "--watch"});
  INFO(r.out << r.err);
  CHECK(r.exit_code == 0);
  const std::string log = RunLog(dir, url);
  const auto confirmed = log.find("position confirmed by the user");
  REQUIRE(confirmed != std::string::npos);
  CHECK(MmFromMotion(log.substr(confirmed)) == Approx(3.0).margin(0.002));
  CHECK(daemon->Stop() == 0);
}

TEST_CASE("a start refused while another run holds the machine names the run it created",
          "[daemon][cli]") {
  test::RigFixture f("orphan", 300, 0.0);
  auto daemon = test::StartDaemonProcess(f);
  const auto& dir = f.dir;
  const std::string url = daemon->url();
  REQUIRE(Gs360(dir, url, {"run", "start", "--probes", "1000"}).exit_code == 0);

  CliResult r = Gs360(dir, url, {"run", "start", "--probes", "40"});
  INFO(r.out << r.err);
  CHECK(r.exit_code == 4);
  CHECK_THAT(r.out, Catch::Contains("created run 2"));
  CHECK_THAT(r.err, Catch::Contains("run 2 created but not started") &&
                        Catch::Contains("run 1 is using the machine") &&
                        Catch::Contains("`gs360 run start 2`") &&
                        Catch::Contains("`gs360 run delete 2`"));
  r = Gs360(dir, url, {"run", "start", "--probes", "40", "--json"});
  CHECK(r.exit_code == 4);
  const Json refused = JsonOf(r);
  CHECK(refused["run"]["id"] == 3);
  CHECK(refused["start"]["http_status"] == 409);
  // A new run has asked nothing to confirm: refused before anything is created.
  r = Gs360(dir, url, {"run", "start", "--probes", "40", "--confirm", "position"});
  CHECK(r.exit_code == 2);
  CHECK_THAT(r.err, Catch::Contains("a new run has asked nothing"));
  CHECK(JsonOf(Gs360(dir, url, {"run", "list", "--json"}))["runs"].size() == 3);

  // Once the machine is free, the run named starts as planned.
  REQUIRE(Gs360(dir, url, {"run", "cancel", "1"}).exit_code == 0);
  WaitStatus(dir, url, [](const Json& s) { return s["state"] == "cancelled"; });
  CHECK(Gs360(dir, url, {"run", "start", "2", "--probes", "40"}).exit_code == 2);
  r = Gs360(dir, url, {"run", "start", "2", "--watch"});
  INFO(r.out << r.err);
  CHECK(r.exit_code == 0);
  CHECK(JsonOf(Gs360(dir, url, {"run", "status", "2", "--json"}))["state"] == "done");
  CHECK(daemon->Stop() == 0);
}

TEST_CASE("`gs360 run start N --confirm position` answers the question a created run asked",
          "[daemon][cli][confirm]") {
  test::RigFixture f("startconfirm", 40, 0.0, false, [](VirtualRigOptions& o) {
    o.cnc.settings.homing_enable = false;  // boots Idle at MPos 0,0,0
    o.cnc.settings.soft_limits = false;
  });
  std::string toml = test::RigToml(f.config);
  toml.replace(toml.find("[machine]\n"), 10, "[machine]\nhome = false\n");
  std::ofstream(f.dir / "gs360d.toml") << toml;
  cli::DaemonProcess daemon(std::string(GS360_BINARY_DIR) + "/daemon/gs360d", f.dir / "gs360d.toml",
                            f.dir / "data", f.dir / "gs360d.log");
  const auto& dir = f.dir;
  REQUIRE(Gs360(dir, daemon.url(), {"run", "start", "--probes", "40"}).exit_code == 0);
  // Without homing the first start asks: is MPos where the tool is?
  const Json asked = WaitStatus(dir, daemon.url(), [](const Json& s) {
    return s["awaiting"] == "position" && s["state"] != "starting";
  });
  CHECK(asked["state"] == "created");
  CliResult r = Gs360(dir, daemon.url(), {"run", "start", "1", "--confirm", "position"});
  INFO(r.out << r.err);
  REQUIRE(r.exit_code == 0);
  CHECK_THAT(r.out, Catch::Contains("run 1 starting"));
  r = Gs360(dir, daemon.url(), {"run", "status", "1", "--watch"});
  CHECK(r.exit_code == 0);
  CHECK_THAT(RunLog(dir, daemon.url()), Catch::Contains("position confirmed by the user: MPos"));
  CHECK(daemon.Stop() == 0);
}
