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

#include "cli/daemon_client.h"
#include "daemon_fixture.h"
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
